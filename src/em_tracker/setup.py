"""ament_python package em_tracker; see package.xml for the description."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'em_tracker'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.dbc')),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='C-GAIL catheter maintainers',
    maintainer_email='maintainers@cgail-catheter.dev',
    description=('NDI Aurora EM tracker node (Combined API over serial through ndicapi) and a '
                 'simulated Aurora that speaks the Combined API on a pty.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'aurora_node = em_tracker.nodes.aurora_node:main',
            'sim_aurora = em_tracker.hw.sim_aurora:main',
            'register_phantom = em_tracker.cli.register_phantom:main',
            'pivot_calibrate = em_tracker.cli.pivot_calibrate:main',
        ],
    },
)

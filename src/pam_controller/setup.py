"""ament_python package pam_controller; see package.xml for the description."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'pam_controller'

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
    description=('Pressure control of the four pneumatic artificial muscles that bend the '
                 'catheter tip (CAN through python-can), bending model with hysteresis, '
                 'simulated regulator bank.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'pam_node = pam_controller.nodes.pam_node:main',
            'sim_regulators = pam_controller.hw.sim_regulators:main',
        ],
    },
)

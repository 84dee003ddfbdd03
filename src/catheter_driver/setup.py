"""ament_python package catheter_driver; see package.xml for the description."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'catheter_driver'

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
    description=('Sleeve-based relay insertion driver (CAN), gamepad joy node (SDL2) and '
                 'joystick teleop with a deadman button.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'driver_node = catheter_driver.nodes.driver_node:main',
            'joy_node = catheter_driver.nodes.joy_node:main',
            'teleop_node = catheter_driver.nodes.teleop_node:main',
            'sim_driver = catheter_driver.hw.sim_driver:main',
        ],
    },
)

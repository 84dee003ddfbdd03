"""ament_python package cgail_node_utils; see package.xml for the description."""

from setuptools import find_packages, setup

PACKAGE = 'cgail_node_utils'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='C-GAIL catheter maintainers',
    maintainer_email='maintainers@cgail-catheter.dev',
    description=("Helpers shared by the workspace's ROS 2 nodes: a console entry point's spin "
                 'and shutdown, parameter declaration with descriptors, configure-time '
                 "parameters of lifecycle nodes, and the lifecycle state read through rclpy's "
                 'public API.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
)

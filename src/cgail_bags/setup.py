"""ament_python package cgail_bags; see package.xml for the description."""

from setuptools import find_packages, setup

PACKAGE = 'cgail_bags'

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
    description=('rosbag2 (MCAP) recording and playback through rclpy raw publishers and '
                 'subscriptions, bag repair, and the offline metrics of in-vitro trials and '
                 'sessions.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
)

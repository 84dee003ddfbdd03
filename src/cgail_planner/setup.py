"""ament_python package cgail_planner; see package.xml for the description."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'cgail_planner'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
    ],
    # The committed C-GAIL policies ship inside the package so the planner finds them installed.
    package_data={PACKAGE: ['models/*.onnx']},
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='C-GAIL catheter maintainers',
    maintainer_email='maintainers@cgail-catheter.dev',
    description=('C-GAIL planner: the ONNX policy, the planner core (paths, guidance, markers, '
                 'metrics) and its ROS 2 nodes (planner_node, operator_node, autonomy_node); '
                 'onnxruntime and numba, no torch. What a rig PC installs.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            # Nodes: ROS executables (ros2 run cgail_planner <node>; scripts/ros2run here).
            'planner_node = cgail_planner.nodes.planner_node:main',
            'operator_node = cgail_planner.nodes.operator_node:main',
            'autonomy_node = cgail_planner.nodes.autonomy_node:main',
        ],
    },
)

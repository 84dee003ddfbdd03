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
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.dbc')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.yaml')),
        ('share/' + PACKAGE + '/config/presets', glob('config/presets/*.yaml')),
        # RViz2 and Foxglove views of the markers (phantom/markers, planner/markers)
        ('share/' + PACKAGE + '/config/rviz', glob('config/rviz/*.rviz')),
        ('share/' + PACKAGE + '/config/foxglove', glob('config/foxglove/*.json')),
        # Guidance page of gui_node; three.js comes from `npm ci` in web/ (scripts/setup.sh).
        ('share/' + PACKAGE + '/web', glob('web/*.html') + glob('web/*.js') + glob('web/*.css')
         + glob('web/package*.json')),
        ('share/' + PACKAGE + '/web/node_modules/three/build',
         glob('web/node_modules/three/build/three.module.js')
         + glob('web/node_modules/three/build/three.core.js')),
        ('share/' + PACKAGE + '/web/node_modules/three/examples/jsm/controls',
         glob('web/node_modules/three/examples/jsm/controls/OrbitControls.js')),
    ],
    # The committed C-GAIL policy ships inside the package so the planner finds it installed.
    package_data={PACKAGE: ['learning/models/*.onnx']},
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='C-GAIL catheter maintainers',
    maintainer_email='maintainers@cgail-catheter.dev',
    description=('C-GAIL catheter path planner: deformable beating-aorta simulator, '
                 'demonstrations, C-GAIL/GAIL trainer, ONNX planner node, bag recording/metrics, '
                 'guidance GUI, rig launcher.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            # Nodes: ROS executables (ros2 run cgail_planner <node>; scripts/ros2run here).
            'planner_node = cgail_planner.nodes.planner_node:main',
            'phantom_node = cgail_planner.nodes.phantom_node:main',
            'operator_node = cgail_planner.nodes.operator_node:main',
            'gui_node = cgail_planner.nodes.gui_node:main',
            'igtl_bridge = cgail_planner.nodes.igtl_bridge:main',
            # Tools: one command line, `cgail <verb>` (cgail_planner/cli.py holds the verbs).
            'cgail = cgail_planner.cli:main',
            # The tools' names of the last release: a deprecation line, then `cgail <verb>`.
            # Remove in the next release.
            *(f'{old} = cgail_planner.cli:legacy_{old}' for old in (
                'rig_launch', 'bag_record', 'bag_play', 'bag_metrics', 'session_compare',
                'bag_recover', 'sim_render', 'prepare_anatomy', 'synthetic_ct', 'plan_patient',
                'make_demos', 'record_demos', 'train', 'refine', 'evaluate', 'export_onnx',
                'invitro_session', 'identify_pam')),
        ],
    },
)

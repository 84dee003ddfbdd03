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
        ('share/' + PACKAGE + '/config/launch', glob('config/launch/*.yaml')),
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
            'planner_node = cgail_planner.nodes.planner_node:main',
            'phantom_node = cgail_planner.nodes.phantom_node:main',
            'operator_node = cgail_planner.nodes.operator_node:main',
            'gui_node = cgail_planner.nodes.gui_node:main',
            'igtl_bridge = cgail_planner.nodes.igtl_bridge:main',
            'rig_launch = cgail_planner.system.launcher:main',
            'bag_record = cgail_planner.bags.record:main',
            'bag_play = cgail_planner.bags.play:main',
            'bag_metrics = cgail_planner.bags.metrics_cli:main',
            'session_compare = cgail_planner.bags.compare_cli:main',
            'bag_recover = cgail_planner.bags.recover:main',
            'sim_render = cgail_planner.sim.render:main',
            'prepare_anatomy = cgail_planner.patient.prepare_cli:main',
            'synthetic_ct = cgail_planner.patient.synthetic:main',
            'plan_patient = cgail_planner.patient.plan:main',
            'make_demos = cgail_planner.learning.demos_cli:main',
            'record_demos = cgail_planner.system.record_demos:main',
            'train = cgail_planner.learning.train:main',
            'refine = cgail_planner.learning.refine:main',
            'evaluate = cgail_planner.learning.evaluate:main',
            'export_onnx = cgail_planner.learning.export:main',
            'invitro_session = cgail_planner.system.session:main',
            'identify_pam = cgail_planner.system.identify_pam:main',
        ],
    },
)

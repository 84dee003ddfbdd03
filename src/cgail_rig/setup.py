"""ament_python package cgail_rig; see package.xml for the description."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'cgail_rig'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.yaml')),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/config/rviz', glob('config/rviz/*.rviz')),
        ('share/' + PACKAGE + '/config/foxglove', glob('config/foxglove/*.json')),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='C-GAIL catheter maintainers',
    maintainer_email='maintainers@cgail-catheter.dev',
    description=('Rig bring-up: the simulated phantom (physics and the true plant), the launcher'
                 ' and launch files, the lockstep clock, in-vitro sessions, PAM identification, '
                 'demonstration recording, and the cgail command line.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'phantom_node = cgail_rig.nodes.phantom_node:main',
            # Tools: one command line, `cgail <verb>` (cgail_rig/cli.py holds the verbs).
            'cgail = cgail_rig.cli:main',
            # The tools' names of the last release: a deprecation line, then `cgail <verb>`.
            # Remove in the next release.
            *(f'{old} = cgail_rig.cli:legacy_{old}' for old in (
                'rig_launch', 'bag_record', 'bag_play', 'bag_metrics', 'session_compare',
                'bag_recover', 'sim_render', 'prepare_anatomy', 'synthetic_ct', 'plan_patient',
                'make_demos', 'record_demos', 'train', 'refine', 'evaluate', 'export_onnx',
                'invitro_session', 'identify_pam')),
        ],
    },
)

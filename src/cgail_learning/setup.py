"""ament_python package cgail_learning; see package.xml for the description."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'cgail_learning'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config/presets', glob('config/presets/*.yaml')),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='C-GAIL catheter maintainers',
    maintainer_email='maintainers@cgail-catheter.dev',
    description=('Learning (torch): scripted-expert and teleoperated demonstrations, the '
                 'C-GAIL/GAIL/BC/curiosity trainer with its presets, in-silico evaluation, '
                 'DAgger refinement and ONNX export.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
)

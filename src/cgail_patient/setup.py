"""ament_python package cgail_patient; see package.xml for the description."""

from setuptools import find_packages, setup

PACKAGE = 'cgail_patient'

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
    description=("Patient tools: prepare a patient's anatomy from a CT label map or a lumen "
                 'surface (checked with the scripted expert), synthetic CT of the built-in '
                 'aortas, and plan-patient (train and evaluate a planner for one anatomy).'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
)

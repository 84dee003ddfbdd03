"""ament_python package cgail_sim; see package.xml for the description."""

from setuptools import find_packages, setup

PACKAGE = 'cgail_sim'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    # the real aortas named avt-<case> (cgail_sim.anatomy_spec), with their licence
    package_data={PACKAGE: ['anatomies/avt/*/lumen.stl', 'anatomies/avt/*/lumen.yaml',
                            'anatomies/avt/*.md']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='C-GAIL catheter maintainers',
    maintainer_email='maintainers@cgail-catheter.dev',
    description=('Catheter-navigation simulator: parametric and patient aortic anatomies with '
                 'their centrelines, the follow-the-leader catheter model, the deformable '
                 'beating wall (PBD), contacts, rewards and the Gymnasium env. No ROS, no torch.'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
)

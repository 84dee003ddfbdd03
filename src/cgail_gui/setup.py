"""ament_python package cgail_gui; see package.xml for the description."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'cgail_gui'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        # Guidance page of gui_node; three.js comes from `npm ci` in web/ (scripts/setup.sh).
        ('share/' + PACKAGE + '/web', glob('web/*.html') + glob('web/*.js') + glob('web/*.css')
         + glob('web/package*.json')),
        ('share/' + PACKAGE + '/web/node_modules/three/build',
         glob('web/node_modules/three/build/three.module.js')
         + glob('web/node_modules/three/build/three.core.js')),
        ('share/' + PACKAGE + '/web/node_modules/three/examples/jsm/controls',
         glob('web/node_modules/three/examples/jsm/controls/OrbitControls.js')),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='C-GAIL catheter maintainers',
    maintainer_email='maintainers@cgail-catheter.dev',
    description=('Guidance displays of the rig: the browser GUI (gui_node; three.js scene, live '
                 'state, bag replay), the OpenIGTLink bridge to 3D Slicer (igtl_bridge) and the '
                 'live Foxglove view (foxglove_bridge).'),
    license='Apache-2.0',
    tests_require=['pytest'],
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'gui_node = cgail_gui.nodes.gui_node:main',
            'igtl_bridge = cgail_gui.nodes.igtl_bridge:main',
            'foxglove_bridge = cgail_gui.nodes.foxglove_bridge:main',
        ],
    },
)

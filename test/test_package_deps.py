"""Every package.xml declares what its Python code imports, and no more (full-install parity).

On a full ROS 2 install ``rosdep install --from-paths src`` installs what the package.xml files
declare, and nothing else; this test holds each one to the imports of its package, both ways.
That each key resolves (rosdistro or ``rosdep/cgail.yaml``) is test/test_rosdep_keys.py's.

How imports become rosdep keys (the convention):

* Scanned: ``src/<pkg>/<pkg>/**.py`` (runtime code) and ``src/<pkg>/test/**.py`` (tests). Not
  ``setup.py``: its ``setuptools`` is the ``python3-setuptools`` buildtool_depend.
* A package's ``testing`` module (``src/<pkg>/<pkg>/testing.py``, or a ``testing/``
  subpackage; :data:`TESTING_MODULES`) is test code, though it ships in the package: the test
  helpers and fixtures that the tests of this package and of the packages above it import
  (``cgail_sim.testing``), as ``numpy.testing`` is. Its imports count as the tests' (``pytest``
  may be a ``<test_depend>``). A package whose tests import another's ``testing`` module
  declares that package, as any import. No runtime code imports a ``testing`` module
  (test/test_import_layers.py checks it), so a runtime-only install never runs one.
* Every absolute ``import X`` / ``from X import ...`` counts, at any depth: an import inside a
  function or a ``try`` (an optional feature, a fallback) is still needed by a full install. The
  key is looked up by the top-level name, or the first two names for namespace packages
  (``backports.zstd``).
* Not dependencies: the standard library (``sys.stdlib_module_names`` and :data:`NO_KEY`), the
  package itself, and modules next to the importing test file (test helpers of one test
  directory, such as ``tiny_pipeline``).
* A ROS package's key is its name: the workspace's packages, message/service/interface packages
  (``*_msgs``, ``*_srvs``, ``*_interfaces``) and :data:`ROS_PACKAGES`.
* A Python module's key comes from the explicit table :data:`PYTHON_KEYS`, written as rosdistro's
  ``rosdep/python.yaml`` names keys: ``python3-<name>`` (the Debian/Ubuntu package name) where
  Ubuntu Noble, Jazzy's platform, packages the module, and ``python3-<pypi name>-pip`` where only
  PyPI has it (rosdep installs those with pip). A module in none of these fails the test until it
  is added to the table (which is also the one place to correct a key).
* A module the runtime code imports must be a ``<depend>`` or an ``<exec_depend>``; one that only
  tests import may also be a ``<test_depend>``.
* The other way round: every ``<depend>``/``<exec_depend>`` key must be imported by the runtime
  code (one only the tests import belongs in ``<test_depend>``), and every ``<test_depend>`` key
  by the tests or the runtime code, unless :data:`NOT_IMPORTED` says why the package needs it.
* ``install_requires`` of ``setup.py`` (besides ``setuptools``) must be declared the same way, by
  the PyPI column of :data:`PYTHON_KEYS`; and every PyPI distribution of the table that a package
  imports is pinned in ``requirements.txt`` (the pip-only workspace installs from it).
"""

from __future__ import annotations

import ast
from pathlib import Path
import re
import sys
from typing import NamedTuple
import xml.etree.ElementTree as ET

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent.name for p in (ROOT / 'src').glob('*/package.xml'))


class Key(NamedTuple):
    """A Python module's rosdep key and the PyPI distribution that provides it."""

    rosdep: str
    pypi: str


#: Import name -> rosdep key (python3-<debian name>, or python3-<pypi name>-pip) and PyPI name.
#: Each key is rosdistro's where it has one (rosdep/rosdistro_keys.txt), otherwise ours
#: (rosdep/cgail.yaml); test/test_rosdep_keys.py checks that.
PYTHON_KEYS = {
    'can': Key('python3-can', 'python-can'),
    'matplotlib': Key('python3-matplotlib', 'matplotlib'),
    'mpl_toolkits': Key('python3-matplotlib', 'matplotlib'),
    'networkx': Key('python3-networkx', 'networkx'),
    'nibabel': Key('python3-nibabel', 'nibabel'),
    'numba': Key('python3-numba', 'numba'),
    'numpy': Key('python3-numpy', 'numpy'),
    'onnx': Key('python3-onnx', 'onnx'),
    'pygame': Key('python3-pygame', 'pygame'),
    'pytest': Key('python3-pytest', 'pytest'),
    'scipy': Key('python3-scipy', 'scipy'),
    'serial': Key('python3-serial', 'pyserial'),
    'skimage': Key('python3-skimage', 'scikit-image'),
    'torch': Key('python3-torch', 'torch'),
    'tqdm': Key('python3-tqdm', 'tqdm'),
    'websockets': Key('python3-websockets', 'websockets'),
    'yaml': Key('python3-yaml', 'PyYAML'),
    'zstandard': Key('python3-zstandard', 'zstandard'),
    # PyPI only (rosdep installs them with pip)
    'cantools': Key('python3-cantools-pip', 'cantools'),
    'fast_simplification': Key('python3-fast-simplification-pip', 'fast-simplification'),
    'foxglove': Key('python3-foxglove-sdk-pip', 'foxglove-sdk'),
    'gymnasium': Key('python3-gymnasium-pip', 'gymnasium'),
    'nrrd': Key('python3-pynrrd-pip', 'pynrrd'),
    'mcap': Key('python3-mcap-pip', 'mcap'),
    'ndicapy': Key('python3-ndicapi-pip', 'ndicapi'),
    'ompl': Key('python3-ompl-pip', 'ompl'),  # the PyPI bindings (rosdep's ompl is the C++ lib)
    'onnxruntime': Key('python3-onnxruntime-pip', 'onnxruntime'),
    'pyigtl': Key('python3-pyigtl-pip', 'pyigtl'),
    'rosbags': Key('python3-rosbags-pip', 'rosbags'),
    'tensorboardX': Key('python3-tensorboardX-pip', 'tensorboardX'),
    'trimesh': Key('python3-trimesh-pip', 'trimesh'),
}
#: ROS packages that the naming rule (*_msgs, *_srvs, *_interfaces) does not catch.
ROS_PACKAGES = {'ament_index_python', 'rclpy', 'rosidl_runtime_py'}
#: Imports that need no key of their own, and why.
NO_KEY = {
    'compression': 'standard library from Python 3.14 (compression.zstd)',
    'backports.zstd': "what rosbags imports for zstd before Python 3.14 (rosbags' dependency)",
}
#: ``'<package>: <key>'`` -> why the package declares a key that none of its code imports
#: (a launch file's node, a plugin loaded by name, a runtime resource). Empty: every declared key
#: is imported.
NOT_IMPORTED: dict[str, str] = {}
#: Top-level modules (``<name>.py``) or subpackages (``<name>/``) of a package that are test
#: code though they ship in it (see the docstring).
TESTING_MODULES = ('testing',)
RUNTIME_TAGS = ('depend', 'exec_depend')
TEST_TAGS = (*RUNTIME_TAGS, 'test_depend')


NAMESPACE_PACKAGES = {'backports'}
"""Top-level names whose subpackages are separate distributions (keyed by two names)."""


def _module_key(name: str) -> str:
    parts = name.split('.')
    return '.'.join(parts[:2]) if parts[0] in NAMESPACE_PACKAGES else parts[0]


def imported_modules(path: Path) -> set[str]:
    """Absolute imports of a file, as :func:`_module_key` names (``os``, ``backports.zstd``)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(_module_key(alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module in NAMESPACE_PACKAGES:  # from backports import zstd
                found.update(f'{node.module}.{alias.name}' for alias in node.names)
            else:
                found.add(_module_key(node.module))
    return found


def rosdep_key(module: str, workspace: set[str]) -> str | None:
    """The rosdep key of an imported module (None: needs none).

    Raises:
        LookupError: a module this convention does not know.
    """
    if module in sys.stdlib_module_names or module in NO_KEY:
        return None
    if module in PYTHON_KEYS:
        return PYTHON_KEYS[module].rosdep
    if module in workspace or module in ROS_PACKAGES or module.endswith(
            ('_msgs', '_srvs', '_interfaces')):
        return module
    raise LookupError(module)


def declared(package_xml: Path) -> dict[str, set[str]]:
    """The keys of each dependency tag of a package.xml."""
    root = ET.parse(package_xml).getroot()
    return {tag: {(e.text or '').strip() for e in root.findall(tag)} for tag in TEST_TAGS}


def install_requires(setup_py: Path) -> list[str]:
    """The distribution names of ``install_requires=[...]`` in a setup.py (literal lists)."""
    for node in ast.walk(ast.parse(setup_py.read_text(), str(setup_py))):
        if isinstance(node, ast.keyword) and node.arg == 'install_requires':
            requirements = ast.literal_eval(node.value)
            return [re.split(r'[\s<>=!~;\[]', r, maxsplit=1)[0] for r in requirements]
    return []


def is_testing_module(path: Path, pkg_dir: Path) -> bool:
    """Whether a file of ``src/<pkg>/<pkg>/`` is (in) one of the :data:`TESTING_MODULES`."""
    top = path.relative_to(pkg_dir / pkg_dir.name).parts[0]
    return top.removesuffix('.py') in TESTING_MODULES


def _imports(pkg_dir: Path) -> tuple[dict[str, str], dict[str, str]]:
    """``{module: first importing file}`` of the runtime code and of the tests (the package's
    testing modules included)."""
    name = pkg_dir.name
    shipped = sorted((pkg_dir / name).rglob('*.py'))
    runtime = [p for p in shipped if not is_testing_module(p, pkg_dir)]
    tests = sorted((pkg_dir / 'test').rglob('*.py')) + [
        p for p in shipped if is_testing_module(p, pkg_dir)]
    scans: list[dict[str, str]] = []
    for paths in (runtime, tests):
        found: dict[str, str] = {}
        for path in paths:
            in_test_dir = path.is_relative_to(pkg_dir / 'test')
            for module in sorted(imported_modules(path)):
                local = (path.parent / f'{module}.py').is_file() or \
                    (path.parent / module / '__init__.py').is_file()
                if module != name and not (in_test_dir and local):
                    found.setdefault(module, str(path.relative_to(pkg_dir.parent)))
        scans.append(found)
    return scans[0], scans[1]


def missing_dependencies(pkg_dir: Path, workspace: set[str]) -> list[str]:
    """One line per import (or install_requires entry) the package.xml does not declare."""
    xml = pkg_dir / 'package.xml'
    tags = declared(xml)
    runtime, tests = _imports(pkg_dir)
    where = xml.relative_to(pkg_dir.parent)
    problems = []
    for modules, allowed, tag in ((runtime, RUNTIME_TAGS, 'exec_depend'),
                                  (tests, TEST_TAGS, 'test_depend')):
        for module, path in sorted(modules.items()):
            if tag == 'test_depend' and module in runtime:
                continue
            try:
                key = rosdep_key(module, workspace)
            except LookupError:
                problems.append(f'{where}: unknown import {module!r} ({path}): add its '
                                'rosdep key to PYTHON_KEYS (or ROS_PACKAGES) in '
                                'test/test_package_deps.py')
                continue
            if key is not None and not any(key in tags[t] for t in allowed):
                problems.append(f'{where}: missing <{tag}>{key}</{tag}> ({module}, imported by '
                                f'{path})')
    setup_py = pkg_dir / 'setup.py'
    by_pypi = {k.pypi.lower(): k.rosdep for k in PYTHON_KEYS.values()}
    for requirement in install_requires(setup_py) if setup_py.is_file() else []:
        if requirement.lower() == 'setuptools':
            continue
        key = by_pypi.get(requirement.lower())
        if key is None:
            problems.append(f'{where}: setup.py install_requires {requirement!r} has no rosdep '
                            'key in PYTHON_KEYS')
        elif not any(key in tags[t] for t in RUNTIME_TAGS):
            problems.append(f'{where}: missing <exec_depend>{key}</exec_depend> ({requirement} '
                            'in setup.py install_requires)')
    return problems


def _keys(modules: dict[str, str], workspace: set[str]) -> dict[str, str]:
    """``{rosdep key: first importing file}`` of imported modules (those with a known key)."""
    keys: dict[str, str] = {}
    for module, path in sorted(modules.items()):
        try:
            key = rosdep_key(module, workspace)
        except LookupError:  # missing_dependencies reports it
            continue
        if key is not None:
            keys.setdefault(key, path)
    return keys


def unused_dependencies(pkg_dir: Path, workspace: set[str],
                        not_imported: dict[str, str] | None = None) -> list[str]:
    """One line per declared key that the package's code does not import (see the docstring)."""
    allowed = NOT_IMPORTED if not_imported is None else not_imported
    tags = declared(pkg_dir / 'package.xml')
    runtime, tests = (_keys(scan, workspace) for scan in _imports(pkg_dir))
    where = (pkg_dir / 'package.xml').relative_to(pkg_dir.parent)
    problems = []
    for tag in TEST_TAGS:
        for key in sorted(tags[tag]):
            if f'{pkg_dir.name}: {key}' in allowed or key in runtime:
                continue
            if tag == 'test_depend' and key in tests:
                continue
            if key in tests:
                problems.append(f'{where}: <{tag}>{key}</{tag}> only the tests import (first '
                                f'{tests[key]}): make it a <test_depend>')
            else:
                problems.append(f'{where}: <{tag}>{key}</{tag}> is imported by no code of '
                                f'{pkg_dir.name}: remove it (or say why in NOT_IMPORTED)')
    return problems


@pytest.mark.parametrize('package', PACKAGES)
def test_package_xml_declares_every_import(package: str) -> None:
    problems = missing_dependencies(ROOT / 'src' / package, set(PACKAGES))
    assert not problems, '\n' + '\n'.join(problems)


@pytest.mark.parametrize('package', PACKAGES)
def test_package_xml_declares_nothing_its_code_does_not_import(package: str) -> None:
    problems = unused_dependencies(ROOT / 'src' / package, set(PACKAGES))
    assert not problems, '\n' + '\n'.join(problems)


def test_not_imported_entries_name_a_declared_key() -> None:
    declared_keys = {f'{package}: {key}' for package in PACKAGES
                     for keys in declared(ROOT / 'src' / package / 'package.xml').values()
                     for key in keys}
    assert sorted(set(NOT_IMPORTED) - declared_keys) == []


def test_every_imported_pypi_distribution_is_pinned_in_requirements() -> None:
    pinned = {re.split(r'[\s<>=!~;\[]', line, maxsplit=1)[0].lower().replace('_', '-')
              for line in (ROOT / 'requirements.txt').read_text().splitlines()
              if line.strip() and not line.startswith('#')}
    imported = set()
    for package in PACKAGES:
        runtime, tests = _imports(ROOT / 'src' / package)
        imported |= {PYTHON_KEYS[m].pypi for m in {*runtime, *tests} if m in PYTHON_KEYS}
    assert sorted(d for d in imported if d.lower().replace('_', '-') not in pinned) == []


def _fake_package(root: Path, package_xml_deps: str, setup_requires: str = "['setuptools']",
                  ) -> Path:
    pkg = root / 'fake_pkg'
    (pkg / 'fake_pkg' / 'nodes').mkdir(parents=True)
    (pkg / 'test' / 'unit').mkdir(parents=True)
    (pkg / 'package.xml').write_text(
        '<?xml version="1.0"?>\n<package format="3">\n  <name>fake_pkg</name>\n'
        f'{package_xml_deps}\n</package>\n')
    (pkg / 'setup.py').write_text(f'from setuptools import setup\n\n'
                                  f'setup(name="fake_pkg", install_requires={setup_requires})\n')
    (pkg / 'fake_pkg' / '__init__.py').write_text('')
    (pkg / 'fake_pkg' / 'nodes' / 'thing_node.py').write_text(
        'import os\nimport numpy as np\nfrom rclpy.node import Node\n'
        'from std_msgs.msg import String\nfrom fake_pkg import nodes\nfrom . import sibling\n\n\n'
        'def plan():\n    try:\n        import scipy.optimize\n    except ImportError:\n'
        '        scipy = None\n    return scipy\n')
    (pkg / 'test' / 'unit' / 'helper_shapes.py').write_text('import numpy\n')
    (pkg / 'test' / 'unit' / 'test_thing.py').write_text(
        'import pytest\nimport yaml\nfrom helper_shapes import numpy\nfrom em_tracker import hw\n')
    return pkg


def test_checker_reports_each_missing_dependency_in_one_line(tmp_path: Path) -> None:
    pkg = _fake_package(tmp_path, '  <exec_depend>rclpy</exec_depend>\n'
                                  '  <depend>python3-numpy</depend>\n'
                                  '  <test_depend>python3-scipy</test_depend>\n'
                                  '  <test_depend>python3-pytest</test_depend>',
                        setup_requires="['setuptools', 'PyYAML>=6', 'left-pad']")
    assert missing_dependencies(pkg, {'fake_pkg', 'em_tracker'}) == [
        # a runtime import declared only for tests is still missing
        'fake_pkg/package.xml: missing <exec_depend>python3-scipy</exec_depend> (scipy, '
        'imported by fake_pkg/fake_pkg/nodes/thing_node.py)',
        'fake_pkg/package.xml: missing <exec_depend>std_msgs</exec_depend> (std_msgs, imported '
        'by fake_pkg/fake_pkg/nodes/thing_node.py)',
        'fake_pkg/package.xml: missing <test_depend>em_tracker</test_depend> (em_tracker, '
        'imported by fake_pkg/test/unit/test_thing.py)',
        'fake_pkg/package.xml: missing <test_depend>python3-yaml</test_depend> (yaml, imported '
        'by fake_pkg/test/unit/test_thing.py)',
        'fake_pkg/package.xml: missing <exec_depend>python3-yaml</exec_depend> (PyYAML in '
        'setup.py install_requires)',
        "fake_pkg/package.xml: setup.py install_requires 'left-pad' has no rosdep key in "
        'PYTHON_KEYS',
    ]


#: The dependencies of :func:`_fake_package` that make it complete.
COMPLETE_DEPS = (
    ('depend', 'rclpy'), ('exec_depend', 'std_msgs'), ('exec_depend', 'python3-numpy'),
    ('exec_depend', 'python3-scipy'), ('test_depend', 'python3-pytest'),
    ('test_depend', 'python3-yaml'), ('test_depend', 'em_tracker'))


def _deps(pairs: tuple[tuple[str, str], ...]) -> str:
    return '\n'.join(f'  <{tag}>{key}</{tag}>' for tag, key in pairs)


def test_checker_passes_a_complete_package_and_names_unknown_imports(tmp_path: Path) -> None:
    pkg = _fake_package(tmp_path, _deps(COMPLETE_DEPS))
    assert missing_dependencies(pkg, {'fake_pkg', 'em_tracker'}) == []
    (pkg / 'fake_pkg' / 'extra.py').write_text('import frobnicate.core\n')
    assert missing_dependencies(pkg, {'fake_pkg', 'em_tracker'}) == [
        "fake_pkg/package.xml: unknown import 'frobnicate' (fake_pkg/fake_pkg/extra.py): add "
        'its rosdep key to PYTHON_KEYS (or ROS_PACKAGES) in test/test_package_deps.py']


def test_unused_checker_reports_each_key_no_code_imports(tmp_path: Path) -> None:
    deps = '\n'.join(f'  <{tag}>{key}</{tag}>' for tag, key in (
        ('depend', 'rclpy'), ('exec_depend', 'std_msgs'), ('exec_depend', 'python3-numpy'),
        ('exec_depend', 'python3-scipy'), ('exec_depend', 'python3-serial'),
        ('exec_depend', 'python3-yaml'), ('exec_depend', 'python3-websockets'),
        ('test_depend', 'python3-pytest'), ('test_depend', 'em_tracker'),
        ('test_depend', 'python3-torch'), ('test_depend', 'python3-numpy')))
    pkg = _fake_package(tmp_path, deps)
    assert unused_dependencies(pkg, {'fake_pkg', 'em_tracker'}, {}) == [
        'fake_pkg/package.xml: <exec_depend>python3-serial</exec_depend> is imported by no code '
        'of fake_pkg: remove it (or say why in NOT_IMPORTED)',
        'fake_pkg/package.xml: <exec_depend>python3-websockets</exec_depend> is imported by no '
        'code of fake_pkg: remove it (or say why in NOT_IMPORTED)',
        'fake_pkg/package.xml: <exec_depend>python3-yaml</exec_depend> only the tests import '
        '(first fake_pkg/test/unit/test_thing.py): make it a <test_depend>',
        'fake_pkg/package.xml: <test_depend>python3-torch</test_depend> is imported by no code '
        'of fake_pkg: remove it (or say why in NOT_IMPORTED)',
    ]
    # a reason in NOT_IMPORTED silences exactly that key of that package
    assert unused_dependencies(pkg, {'fake_pkg', 'em_tracker'}, {
        'fake_pkg: python3-serial': 'opened by URL', 'other_pkg: python3-torch': 'elsewhere'},
    ) == unused_dependencies(pkg, {'fake_pkg', 'em_tracker'}, {})[1:]


@pytest.mark.parametrize('testing', ['testing.py', 'testing/__init__.py'])
def test_a_testing_module_is_test_code(tmp_path: Path, testing: str) -> None:
    def package(root: Path, *extra: tuple[str, str]) -> Path:
        pkg = _fake_package(root, _deps((*COMPLETE_DEPS, *extra)))
        (pkg / 'fake_pkg' / testing).parent.mkdir(exist_ok=True)
        (pkg / 'fake_pkg' / testing).write_text('import pytest\nimport torch\n')
        return pkg

    # its imports are the tests': pytest is a <test_depend> already, torch is missing as one
    assert missing_dependencies(package(tmp_path / 'a'), {'fake_pkg', 'em_tracker'}) == [
        'fake_pkg/package.xml: missing <test_depend>python3-torch</test_depend> (torch, '
        f'imported by fake_pkg/fake_pkg/{testing})']
    pkg = package(tmp_path / 'b', ('test_depend', 'python3-torch'))
    assert missing_dependencies(pkg, {'fake_pkg', 'em_tracker'}) == []
    assert unused_dependencies(pkg, {'fake_pkg', 'em_tracker'}, {}) == []

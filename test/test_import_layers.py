"""The workspace's Python import graph has no circles and no upward imports (issue 32).

The graph is read from the sources with ``ast`` (nothing is imported): every module of every
Python package under ``src/`` (``src/<dir>/<package>/**.py``; not ``setup.py``, not the tests),
and every import in it that names a module of these packages:

* at any depth: module level, inside a function or a class, in a ``try``, under
  ``if TYPE_CHECKING:``. A lazy import is still a dependency: the package holding the importer
  needs the imported one installed, and the import runs as soon as that code path does;
* ``importlib.import_module('<a constant name>')``, the same import spelled as a call;
* ``from pkg import name`` is an edge to the module ``pkg.name`` when there is one, else to
  ``pkg``; ``import a.b.c`` is an edge to ``a.b.c``. The parent packages that Python runs first
  (``a`` and ``a.b``) are not edges: a package's ``__init__`` is a container, not a dependency.

Three rules, each failing with the file and line of every import involved:

1. **No circles.** No strongly connected component of more than one module.
2. **No upward imports.** The packages come in :data:`PACKAGE_LEVELS`, lowest first: a module
   may import a package of a lower level, never one of its own level or above. Inside a package
   the top-level subpackages (and top-level modules) come in :data:`LAYERS`, lowest first: a
   module may import its own layer or one below. A package's own ``__init__`` is below all of
   its layers. A module in no layer fails, so a new subpackage is placed on purpose.
3. **Only tests import a testing module.** A package's ``testing`` module (or subpackage),
   :data:`TESTING`, holds the test helpers and fixtures that the tests of this package and of
   the packages above it share (``cgail_sim.testing``, as ``numpy.testing``). It is test code
   (test/test_package_deps.py: its imports may be ``<test_depend>`` s): no product module
   imports one; another testing module may. The testing modules are otherwise placed as any
   module (the two rules above, and test/test_torch_free.py, hold for them).

:data:`KNOWN_EXCEPTIONS` lists the imports that break a rule today and wait for a bigger move,
each with its reason; an exception is left out of both checks, and one that no longer occurs
fails too, so the list only shrinks.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Workspace packages, lowest level first. A package may import packages of lower levels only:
#: the device packages share nothing with each other; the cgail packages follow issue 32's split
#: of the old ``cgail_planner``, bottom up (the planner and the device packages are what a rig PC
#: installs; nothing below ``cgail_learning`` imports torch, test/test_torch_free.py).
PACKAGE_LEVELS: tuple[tuple[str, ...], ...] = (
    # node helpers every node package shares (rclpy only); the simulator (no ROS, no torch)
    ('cgail_node_utils', 'cgail_sim'),
    ('catheter_driver', 'em_tracker', 'pam_controller'),  # one device each
    ('cgail_planner',),  # the ONNX policy, the planner core and its nodes (onnxruntime, numba)
    ('cgail_bags',),  # record, play and read bags; offline metrics from the planner core
    # the guidance displays (rig side, never torch) and learning (torch): neither imports the
    # other
    ('cgail_gui', 'cgail_learning'),
    ('cgail_patient',),  # prepare a patient's anatomy and plan for it (trains through learning)
    ('cgail_rig',),  # the bring-up: phantom, launcher, sessions, identification, `cgail <verb>`
)

#: Each package's layers (top-level subpackages or modules), lowest first; a module may import
#: its own layer and the layers before it. ``()``: the package is one layer. ``'*'``: every
#: top-level module or subpackage not named in the package's layers.
LAYERS: dict[str, tuple[str, ...]] = {
    'cgail_node_utils': (),
    # CONTRIBUTING.md, "Code style": the exception tree, pure logic, device adapters, then the
    # rclpy wrappers.
    'catheter_driver': ('exceptions', 'core', 'hw', 'nodes'),
    'pam_controller': ('errors', 'core', 'hw', 'nodes'),
    # cli: the calibration commands (files around core); sim: the simulated rig that drives
    # the real host path (hw) and runs those commands, as a rig team would.
    'em_tracker': ('core', 'hw', 'cli', 'nodes', 'sim'),
    # cli_help: help text of the cgail tools (stdlib only), under every tool's parser.
    'cgail_sim': ('cli_help', '*'),
    'cgail_planner': ('core', 'nodes'),
    'cgail_bags': (),
    # the Slicer frame (core), the OpenIGTLink server (hw), the GUI's modules, then the nodes.
    'cgail_gui': ('core', 'hw', '*', 'nodes'),
    'cgail_learning': (),
    'cgail_patient': (),
    # the phantom's physics and plant (core), its nodes, the rig tools; `cgail <verb>` (cli)
    # imports every tool's module (by name, when the verb runs).
    'cgail_rig': ('core', 'nodes', '*', 'cli'),
}

#: The name of a package's test-helper module or subpackage (``<package>.testing``): only tests
#: and other testing modules import it (rule 3).
TESTING = 'testing'

#: Imports that break a rule today, waiting for a bigger move:
#: ``(importer, imported): reason``. Each is left out of both checks.
KNOWN_EXCEPTIONS: dict[tuple[str, str], str] = {}


@dataclass(frozen=True)
class Edge:
    """One import: ``source`` imports ``target`` at ``where`` (``path:line``)."""

    source: str
    target: str
    where: str


def find_modules(src: Path) -> dict[str, Path]:
    """Every module of the Python packages under ``src`` (``<dir>/<package>/**.py``) by name."""
    modules: dict[str, Path] = {}
    for project in sorted(p for p in src.iterdir() if p.is_dir()):
        for package in sorted(p for p in project.iterdir() if (p / '__init__.py').is_file()):
            if package.name == 'test':
                continue
            for path in sorted(package.rglob('*.py')):
                parts = list(path.relative_to(project).with_suffix('').parts)
                if parts[-1] == '__init__':
                    parts.pop()
                modules['.'.join(parts)] = path
    return modules


def _imported_names(node: ast.AST, module: str, is_package: bool) -> Iterable[str]:
    """The dotted names one ``import`` statement (or ``importlib.import_module`` call) asks
    for, most specific first per name (``pkg.name`` before ``pkg``)."""
    if isinstance(node, ast.Import):
        for alias in node.names:
            yield alias.name
    elif isinstance(node, ast.ImportFrom):
        if node.level:
            base = module.split('.') if is_package else module.split('.')[:-1]
            base = base[:len(base) - (node.level - 1)]
            parent = '.'.join(base + ([node.module] if node.module else []))
        else:
            parent = node.module or ''
        for alias in node.names:
            yield f'{parent}.{alias.name}'
    elif (isinstance(node, ast.Call) and node.args
          and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
          and ((isinstance(node.func, ast.Attribute) and node.func.attr == 'import_module'
                and isinstance(node.func.value, ast.Name)
                and node.func.value.id == 'importlib')
               or (isinstance(node.func, ast.Name) and node.func.id == 'import_module'))):
        yield node.args[0].value


def import_edges(modules: Mapping[str, Path], root: Path) -> list[Edge]:
    """Every import between ``modules`` (self-imports left out)."""
    edges: list[Edge] = []
    for module, path in modules.items():
        is_package = path.name == '__init__.py'
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            for name in _imported_names(node, module, is_package):
                target = name
                while target and target not in modules:
                    target = target.rpartition('.')[0]
                if target and target != module:
                    where = f'{path.relative_to(root)}:{getattr(node, "lineno", 0)}'
                    edges.append(Edge(module, target, where))
    return edges


def import_circles(edges: Iterable[Edge]) -> list[list[Edge]]:
    """One circle of imports (a closed path of edges) per strongly connected component."""
    graph: dict[str, dict[str, Edge]] = {}
    for e in edges:
        graph.setdefault(e.source, {}).setdefault(e.target, e)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(v: str) -> None:  # Tarjan's algorithm (the graph is small: recursion is fine)
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, {})):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    circles = []
    for component in sorted(components):  # the shortest circle through its first module
        members, start = set(component), component[0]
        paths: dict[str, list[Edge]] = {start: []}
        queue = [start]
        circle: list[Edge] | None = None
        while queue and circle is None:
            v = queue.pop(0)
            for w, e in sorted(graph.get(v, {}).items()):
                if w == start:
                    circle = [*paths[v], e]
                    break
                if w in members and w not in paths:
                    paths[w] = [*paths[v], e]
                    queue.append(w)
        assert circle is not None
        circles.append(circle)
    return circles


class LayerError(ValueError):
    """A module that is in no layer, or a package in no level."""


def layer_of(module: str, layers: Mapping[str, tuple[str, ...]]) -> tuple[str, int]:
    """``(package, layer index)`` of a module; a package's own ``__init__`` is layer -1.

    Raises:
        LayerError: a package or top-level subpackage that :data:`LAYERS` does not place.
    """
    package, _, rest = module.partition('.')
    if package not in layers:
        raise LayerError(f'{module}: expected package {package!r} in LAYERS, found none')
    if not rest:
        return package, -1
    order = layers[package]
    if not order:
        return package, 0
    top = rest.split('.')[0]
    if top not in order and '*' in order:
        top = '*'
    if top not in order:
        raise LayerError(f'{module}: expected {package}.{top} in the layers of {package} '
                         f'{list(order)}, found none: place it in LAYERS')
    return package, order.index(top)


def upward_imports(edges: Iterable[Edge], layers: Mapping[str, tuple[str, ...]],
                   levels: tuple[tuple[str, ...], ...]) -> list[str]:
    """One line per import that goes up (or sideways between packages of one level)."""
    level = {p: k for k, group in enumerate(levels) for p in group}
    found = []
    for e in edges:
        (src_pkg, src_layer), (dst_pkg, dst_layer) = (layer_of(e.source, layers),
                                                      layer_of(e.target, layers))
        if src_pkg != dst_pkg:
            for p in (src_pkg, dst_pkg):
                if p not in level:
                    raise LayerError(f'{p}: expected it in PACKAGE_LEVELS, found none')
            if level[dst_pkg] >= level[src_pkg]:
                found.append(f'{e.where}: {e.source} imports {e.target}: package {src_pkg} '
                             f'(level {level[src_pkg]}) may only import packages of lower '
                             f'levels, found {dst_pkg} (level {level[dst_pkg]})')
        elif dst_layer > src_layer:
            order = layers[src_pkg]
            found.append(f'{e.where}: {e.source} imports {e.target}: layer '
                         f'{order[src_layer] if src_layer >= 0 else "__init__"} may only '
                         f'import layers below it, found {order[dst_layer]} above it '
                         f'({src_pkg}: {" < ".join(order)})')
    return found


def is_testing(module: str) -> bool:
    """Whether a module is (in) a package's :data:`TESTING` module."""
    parts = module.split('.')
    return len(parts) > 1 and parts[1] == TESTING


def imports_of_testing_modules(edges: Iterable[Edge]) -> list[str]:
    """One line per import of a testing module by a module that is not one (rule 3)."""
    return [f'{e.where}: {e.source} imports {e.target}: only tests (and other testing '
            f'modules) may import a testing module' for e in edges
            if is_testing(e.target) and not is_testing(e.source)]


def describe(circle: list[Edge]) -> str:
    return 'import circle:\n' + '\n'.join(f'    {e.source} -> {e.target}  ({e.where})'
                                          for e in circle)


@pytest.fixture(scope='module')
def edges() -> list[Edge]:
    modules = find_modules(ROOT / 'src')
    assert 'cgail_sim.env' in modules, 'expected the packages under src/, found none'
    return import_edges(modules, ROOT)


def _checked(edges: list[Edge]) -> list[Edge]:
    return [e for e in edges if (e.source, e.target) not in KNOWN_EXCEPTIONS]


def test_every_module_is_in_a_layer() -> None:
    errors = []
    for module in find_modules(ROOT / 'src'):
        try:
            layer_of(module, LAYERS)
        except LayerError as err:
            errors.append(str(err))
    placed = {p for group in PACKAGE_LEVELS for p in group}
    errors += [f'{p}: expected it in PACKAGE_LEVELS, found none' for p in LAYERS
               if p not in placed]
    assert not errors, '\n'.join(errors)


def test_no_import_circles(edges: list[Edge]) -> None:
    circles = import_circles(_checked(edges))
    assert not circles, '\n'.join(describe(c) for c in circles)


def test_no_upward_imports(edges: list[Edge]) -> None:
    found = upward_imports(_checked(edges), LAYERS, PACKAGE_LEVELS)
    assert not found, 'upward imports:\n' + '\n'.join(found)


def test_only_tests_import_the_testing_modules(edges: list[Edge]) -> None:
    assert any(is_testing(m) for m in find_modules(ROOT / 'src')), \
        'expected testing modules (cgail_sim.testing, ...), found none'
    found = imports_of_testing_modules(_checked(edges))
    assert not found, 'testing modules imported by product code:\n' + '\n'.join(found)


def test_every_known_exception_still_occurs(edges: list[Edge]) -> None:
    present = {(e.source, e.target) for e in edges}
    stale = [f'{a} -> {b}' for a, b in KNOWN_EXCEPTIONS if (a, b) not in present]
    assert not stale, f'expected each of KNOWN_EXCEPTIONS to occur, found gone: {stale}'


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_the_checks_name_a_circle_and_an_upward_import(tmp_path: Path) -> None:
    _write(tmp_path / 'src', {
        'low/low/__init__.py': '',
        'low/low/core/__init__.py': '',
        'low/low/core/a.py': 'def f():\n    from low.core import b\n',  # lazy: still counts
        'low/low/core/b.py': 'from . import c\n',
        'low/low/core/c.py': 'import importlib\nimportlib.import_module("low.core.a")\n',
        'low/low/core/d.py': 'from typing import TYPE_CHECKING\n'
                             'if TYPE_CHECKING:\n    from low.nodes.n import N\n',
        'low/low/nodes/__init__.py': '',
        'low/low/nodes/n.py': 'from low.core.a import f\nimport high.x\n',
        'low/test/test_n.py': 'import high.x\n',  # tests are not scanned
        'high/high/__init__.py': '',
        'high/high/x.py': 'import low.nodes.n\nimport numpy\n',
    })
    modules = find_modules(tmp_path / 'src')
    assert sorted(modules) == ['high', 'high.x', 'low', 'low.core', 'low.core.a', 'low.core.b',
                               'low.core.c', 'low.core.d', 'low.nodes', 'low.nodes.n']
    edges = import_edges(modules, tmp_path)
    circles = [[(e.source, e.target, e.where) for e in c] for c in import_circles(edges)]
    assert circles == [
        [('high.x', 'low.nodes.n', 'src/high/high/x.py:1'),
         ('low.nodes.n', 'high.x', 'src/low/low/nodes/n.py:2')],
        [('low.core.a', 'low.core.b', 'src/low/low/core/a.py:2'),
         ('low.core.b', 'low.core.c', 'src/low/low/core/b.py:1'),
         ('low.core.c', 'low.core.a', 'src/low/low/core/c.py:2')],
    ]
    layers = {'low': ('core', 'nodes'), 'high': ()}
    assert upward_imports(edges, layers, (('low',), ('high',))) == [
        'src/low/low/core/d.py:3: low.core.d imports low.nodes.n: layer core may only import '
        'layers below it, found nodes above it (low: core < nodes)',
        'src/low/low/nodes/n.py:2: low.nodes.n imports high.x: package low (level 0) may only '
        'import packages of lower levels, found high (level 1)',
    ]
    # '*' places every top-level name the layers do not list (here low.nodes)
    assert upward_imports(edges, {'low': ('core', '*'), 'high': ()},
                          (('low',), ('high',)))[0] == (
        'src/low/low/core/d.py:3: low.core.d imports low.nodes.n: layer core may only import '
        'layers below it, found * above it (low: core < *)')
    with pytest.raises(LayerError, match=r"low.core.a: expected low.core in the layers of low "
                                         r"\['nodes'\], found none: place it in LAYERS"):
        upward_imports(edges, {'low': ('nodes',), 'high': ()}, (('low',), ('high',)))


def test_the_check_names_a_testing_module_that_product_code_imports(tmp_path: Path) -> None:
    _write(tmp_path / 'src', {
        'low/low/__init__.py': '',
        'low/low/core.py': 'def f():\n    from low import testing\n',  # lazy: still counts
        'low/low/testing.py': 'import pytest\n',
        'high/high/__init__.py': '',
        'high/high/x.py': 'from low.testing import helper\n',
        'high/high/testing/__init__.py': 'from low.testing import helper\n',  # testing: fine
        'high/test/test_x.py': 'from low.testing import helper\n',  # tests are not scanned
    })
    edges = import_edges(find_modules(tmp_path / 'src'), tmp_path)
    assert imports_of_testing_modules(edges) == [
        'src/high/high/x.py:1: high.x imports low.testing: only tests (and other testing '
        'modules) may import a testing module',
        'src/low/low/core.py:2: low.core imports low.testing: only tests (and other testing '
        'modules) may import a testing module',
    ]

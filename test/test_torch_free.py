"""What a rig PC installs imports no torch (issue 32, the design card's lean rig install).

The device packages, ``cgail_node_utils``, ``cgail_sim`` and ``cgail_planner`` (and the
interface packages under ``src/interfaces``) must import without torch: the planner node runs
an ONNX policy with onnxruntime. Read from the sources with ``ast`` (nothing is imported), the
same way as test/test_import_layers.py: every import at any depth (a lazy import inside a
function still runs on that code path), followed through every module of the workspace it
reaches, whichever package that module is in. A module of these packages that reaches
``torch`` (directly or through another module) fails, with the chain of imports.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

from test_import_layers import Edge, find_modules, import_edges

ROOT = Path(__file__).resolve().parents[1]

#: The packages of a lean rig install (those under src/interfaces hold no Python modules of
#: ours: their messages are generated).
LEAN_PACKAGES = ('catheter_driver', 'cgail_node_utils', 'cgail_planner', 'cgail_sim',
                 'em_tracker', 'pam_controller')
#: Modules a lean install must never import.
FORBIDDEN = ('torch',)


def external_imports(path: Path) -> set[tuple[str, int]]:
    """``(top-level name, line)`` of every absolute import in a file, at any depth."""
    found: set[tuple[str, int]] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update((a.name.split('.')[0], node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add((node.module.split('.')[0], node.lineno))
    return found


def forbidden_chains(modules: Mapping[str, Path], edges: Iterable[Edge], roots: Iterable[str],
                     forbidden: tuple[str, ...], root: Path) -> list[str]:
    """One line per module of ``roots`` (package names) that reaches a ``forbidden`` import:
    the chain of workspace imports, then the forbidden one with its file and line."""
    graph: dict[str, list[Edge]] = {}
    for e in edges:
        graph.setdefault(e.source, []).append(e)
    direct: dict[str, str] = {}
    for module, path in modules.items():
        for name, line in sorted(external_imports(path)):
            if name in forbidden:
                direct.setdefault(module, f'{name} ({path.relative_to(root)}:{line})')
    problems = []
    for start in sorted(m for m in modules if m.split('.')[0] in set(roots)):
        chains: dict[str, list[Edge]] = {start: []}
        queue = [start]
        while queue:  # breadth first: the shortest chain
            v = queue.pop(0)
            if v in direct:
                steps = ''.join(f' -> {e.target} ({e.where})' for e in chains[v])
                problems.append(f'{start}{steps} imports {direct[v]}')
                break
            for e in graph.get(v, []):
                if e.target not in chains:
                    chains[e.target] = [*chains[v], e]
                    queue.append(e.target)
    return problems


def test_the_lean_rig_packages_import_no_torch() -> None:
    modules = find_modules(ROOT / 'src')
    assert {m.split('.')[0] for m in modules} >= set(LEAN_PACKAGES), \
        f'expected the packages {LEAN_PACKAGES} under src/, found {sorted(modules)[:5]}...'
    problems = forbidden_chains(modules, import_edges(modules, ROOT), LEAN_PACKAGES, FORBIDDEN,
                                ROOT)
    assert not problems, 'torch in a lean rig package:\n' + '\n'.join(problems)


def test_the_check_follows_imports_across_packages(tmp_path: Path) -> None:
    files = {
        'lean/lean/__init__.py': '',
        'lean/lean/a.py': 'def f():\n    from heavy import b\n',  # lazy: still counts
        'lean/lean/c.py': 'import numpy\n',
        'heavy/heavy/__init__.py': '',
        'heavy/heavy/b.py': 'import os\n\n\nimport torch.nn as nn\n',
    }
    for name, text in files.items():
        (tmp_path / 'src' / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / 'src' / name).write_text(text)
    modules = find_modules(tmp_path / 'src')
    edges = import_edges(modules, tmp_path)
    assert forbidden_chains(modules, edges, ('lean',), ('torch',), tmp_path) == [
        'lean.a -> heavy.b (src/lean/lean/a.py:2) imports torch (src/heavy/heavy/b.py:4)']
    assert forbidden_chains(modules, edges, ('heavy',), ('torch',), tmp_path) == [
        'heavy.b imports torch (src/heavy/heavy/b.py:4)']
    assert forbidden_chains(modules, edges, ('lean',), ('scipy',), tmp_path) == []

"""The node helpers live once, in ``cgail_node_utils``, and use rclpy's public API only.

Scanned: the runtime code of every package (``src/<pkg>/<pkg>/**.py``), with ``ast``:

* no access to a lifecycle node's private ``_state_machine`` (an attribute, or the name given
  to ``getattr``/``hasattr``); ``cgail_node_utils.lifecycle.lifecycle_state`` reads the state
  through the node's public ``get_state`` service;
* no module outside ``cgail_node_utils`` defines its own module-level copy of the shared
  helpers (:data:`SHARED_HELPERS`) or holds a ``nodes/params.py``: nodes import them from
  ``cgail_node_utils``.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OWNER = 'cgail_node_utils'
#: Functions that exist once, in cgail_node_utils.
SHARED_HELPERS = frozenset({'spin', 'try_shutdown', 'run_node', 'start_lifecycle',
                            'lifecycle_state', 'configure_time_guard',
                            'configure_time_refusal'})


def runtime_files(root: Path) -> list[Path]:
    """The runtime modules of every package under ``root/src`` (tests and setup.py aside)."""
    return sorted(path for pkg in (root / 'src').glob('*/package.xml')
                  for path in (pkg.parent / pkg.parent.name).rglob('*.py'))


def private_state_machine_uses(path: Path) -> list[int]:
    """Lines of every ``x._state_machine`` and ``getattr(x, '_state_machine')`` in a file."""
    return sorted(node.lineno for node in ast.walk(ast.parse(path.read_text(), str(path)))
                  if (isinstance(node, ast.Attribute) and node.attr == '_state_machine')
                  or (isinstance(node, ast.Constant) and node.value == '_state_machine'))


def helper_definitions(path: Path) -> list[tuple[int, str]]:
    """``(line, name)`` of every shared helper a file defines at module level (a method of
    the same name, such as an executor's ``spin``, is something else)."""
    return sorted((node.lineno, node.name)
                  for node in ast.parse(path.read_text(), str(path)).body
                  if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
                  and node.name in SHARED_HELPERS)


def problems(root: Path) -> list[str]:
    """Every private state-machine access and every copy of a shared helper under ``root``."""
    found = []
    for path in runtime_files(root):
        package = path.relative_to(root / 'src').parts[0]
        where = path.relative_to(root)
        if package != OWNER and path.name == 'params.py' and path.parent.name == 'nodes':
            found.append(f'{where}: a copy of the parameter helpers; use '
                         'cgail_node_utils.parameters')
        found += [f'{where}:{line}: reads the private _state_machine; use '
                  'cgail_node_utils.lifecycle.lifecycle_state'
                  for line in private_state_machine_uses(path)]
        if package != OWNER:
            found += [f'{where}:{line} {name}: a copy of a cgail_node_utils helper; import it '
                      'from cgail_node_utils' for line, name in helper_definitions(path)]
    return found


def test_no_private_state_machine_and_no_copies_of_the_node_helpers() -> None:
    assert runtime_files(ROOT), 'no package found under src/'
    assert any(p.parts[-3:] == ('cgail_node_utils', 'cgail_node_utils', 'lifecycle.py')
               for p in runtime_files(ROOT))
    found = problems(ROOT)
    assert not found, '\n' + '\n'.join(found)


def test_the_check_finds_each_kind_of_problem(tmp_path: Path) -> None:
    def write(rel: str, text: str) -> None:
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)

    for pkg in ('fake_pkg', OWNER):
        write(f'src/{pkg}/package.xml', '<package format="3"/>\n')
    write('src/fake_pkg/fake_pkg/nodes/thing_node.py',
          'def state(node):\n    return node._state_machine.current_state[1]\n\n\n'
          "def peek(node):\n    return getattr(node, '_state_machine')\n\n\n"
          'def spin(node):\n    pass\n\n\nclass Executor:\n    def spin(self):\n        pass\n')
    write('src/fake_pkg/fake_pkg/nodes/params.py', '"""The _state_machine, in words only."""\n')
    write('src/fake_pkg/test/test_thing.py', 'x = node._state_machine\n')  # tests: not scanned
    write(f'src/{OWNER}/{OWNER}/entry_point.py', 'def spin(node):\n    pass\n')
    assert problems(tmp_path) == [
        'src/fake_pkg/fake_pkg/nodes/params.py: a copy of the parameter helpers; use '
        'cgail_node_utils.parameters',
        'src/fake_pkg/fake_pkg/nodes/thing_node.py:2: reads the private _state_machine; use '
        'cgail_node_utils.lifecycle.lifecycle_state',
        'src/fake_pkg/fake_pkg/nodes/thing_node.py:6: reads the private _state_machine; use '
        'cgail_node_utils.lifecycle.lifecycle_state',
        'src/fake_pkg/fake_pkg/nodes/thing_node.py:9 spin: a copy of a cgail_node_utils helper; '
        'import it from cgail_node_utils',
    ]

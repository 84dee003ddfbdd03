"""The bench scripts (``bench/*.py``, not a package) as the modules they import each other as:
``bench_module('sweep')`` is what ``import sweep`` gives inside ``bench/``."""

from __future__ import annotations

import importlib.util
from pathlib import Path
import sys
from types import ModuleType

BENCH = Path(__file__).resolve().parent.parent / 'bench'


def bench_module(name: str) -> ModuleType:
    """``bench/<name>.py``, loaded once (registered in ``sys.modules`` before it runs, as an
    import does, so its dataclasses and its own imports of other bench scripts resolve)."""
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, BENCH / f'{name}.py')
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]

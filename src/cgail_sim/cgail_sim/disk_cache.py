"""Keys and paths of the simulator's disk cache (anatomy meshes, Voronoi centerlines).

A result read back from ``~/.cache/cgail_planner/`` must be the result a fresh build would give
in this process, bit for bit. Three things determine it:

1. **The code that generates it.** Keys hash the source files of the generating modules, so an
   edit invalidates the cache without a hand-bumped version constant.
2. **The inputs** (parameters, or the content of the mesh a centerline is computed from).
3. **The numerical environment.** numpy picks the SIMD implementation of its ufuncs at run
   time from the CPU (``NPY_DISABLE_CPU_FEATURES`` / ``NPY_ENABLE_CPU_FEATURES`` narrow the
   choice), and arctan2, exp, log, power and tan differ in the last bits between, e.g., the
   AVX-512 and the AVX2 paths. The isotropic remeshing and the Voronoi centerline amplify
   those bits into a different mesh: the default aorta has 2,457 vertices on an AVX-512
   machine and 2,460 with ``NPY_DISABLE_CPU_FEATURES=X86_V4``. Keys therefore hash the numpy
   SIMD dispatch targets in effect (:func:`numpy_simd_targets`), the numpy, scipy and trimesh
   versions and the machine architecture (:func:`numerical_environment`).

Keying the cache was chosen over making the mesh pipeline ISA-independent: that would take a
correctly rounded replacement for every transcendental ufunc called in our code and inside
scipy and trimesh, and it would change the meshes every existing user already has. The
consequence, for code that compares results across machines, is that a built-in anatomy is
the same only up to the remeshing's sensitivity (a few vertices, tens of micrometres at the
start): tests and demonstration replays use physical tolerances, and
:attr:`cgail_sim.anatomy.Anatomy.content_hash` tells two meshes apart.

``CGAIL_PLANNER_NO_DISK_CACHE=1`` disables the disk cache (:func:`cache_dir` returns None).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import os
from pathlib import Path
import platform

import numpy as np

__all__ = ["cache_dir", "cache_key", "numerical_environment", "numpy_simd_targets",
           "source_digest"]


@functools.cache
def numpy_simd_targets() -> tuple[str, ...]:
    """The SIMD targets numpy dispatches its ufuncs to in this process.

    The baseline targets numpy was compiled for, then each run-time dispatch target that is
    enabled here (``numpy._core._multiarray_umath.__cpu_features__``, which honours
    ``NPY_DISABLE_CPU_FEATURES``), e.g. ``('X86_V2', 'X86_V3', 'X86_V4', 'AVX512_ICL')`` on an
    AVX-512 machine and ``('X86_V2', 'X86_V3', 'AVX512_ICL')`` there with
    ``NPY_DISABLE_CPU_FEATURES=X86_V4``. ``('unknown',)`` when numpy does not expose them.
    """
    for module in ("numpy._core._multiarray_umath", "numpy.core._multiarray_umath"):
        try:  # (numpy < 2 keeps it under numpy.core)
            umath = importlib.import_module(module)
            break
        except ImportError:
            continue
    else:
        return ("unknown",)
    features = getattr(umath, "__cpu_features__", None)
    dispatch = getattr(umath, "__cpu_dispatch__", None)
    baseline = getattr(umath, "__cpu_baseline__", None)
    if not isinstance(features, dict) or dispatch is None or baseline is None:
        return ("unknown",)
    return tuple(baseline) + tuple(t for t in dispatch if features.get(t))


@functools.cache
def numerical_environment() -> str:
    """What besides code and inputs decides a cached result, as one line.

    numpy, scipy and trimesh versions, the machine architecture and
    :func:`numpy_simd_targets`, e.g.
    ``numpy=2.4.6 scipy=1.17.1 trimesh=5.2.0 machine=x86_64 simd=X86_V2,X86_V3,X86_V4,...``.
    """
    import scipy
    import trimesh

    return (f"numpy={np.__version__} scipy={scipy.__version__} trimesh={trimesh.__version__} "
            f"machine={platform.machine()} simd={','.join(numpy_simd_targets())}")


@functools.cache
def source_digest(*files: str) -> str:
    """SHA-256 of the contents of ``files`` (the modules that generate a cached result)."""
    h = hashlib.sha256()
    for f in files:
        data = Path(f).read_bytes()
        h.update(len(data).to_bytes(8, "little"))
        h.update(data)
    return h.hexdigest()


def cache_key(*, sources: tuple[str, ...], inputs: str, length: int = 20) -> str:
    """Hex key of a cached result: its generating sources, its inputs and
    :func:`numerical_environment`.

    Args:
        sources: source files of the modules that compute the result.
        inputs: a text that identifies the inputs exactly (a parameter repr, a content hash).
        length: number of hex digits kept.
    """
    h = hashlib.sha256()
    for part in (source_digest(*sources), inputs, numerical_environment()):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:length]


def cache_dir() -> Path | None:
    """``~/.cache/cgail_planner``, or None when ``CGAIL_PLANNER_NO_DISK_CACHE`` is set.

    The folder and the variable keep the name of the first release (before the package split)
    so that existing caches, scripts and CI settings keep working."""
    if os.environ.get("CGAIL_PLANNER_NO_DISK_CACHE"):
        return None
    return Path.home() / ".cache" / "cgail_planner"

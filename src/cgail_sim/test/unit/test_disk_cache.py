"""Disk-cache keys cover code, inputs and numpy's SIMD level; anatomies have a content hash."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from cgail_sim import anatomy as anatomy_mod
from cgail_sim import centerline, disk_cache
from cgail_sim.anatomy import Anatomy, anatomy_params, build_anatomy


def _simd_targets_in_subprocess(disable: str) -> list[str]:
    already = os.environ.get('NPY_DISABLE_CPU_FEATURES', '')
    env = {**os.environ, 'NPY_DISABLE_CPU_FEATURES': f'{already} {disable}'.strip()}
    out = subprocess.run(
        [sys.executable, '-c', 'from cgail_sim.disk_cache import numpy_simd_targets; '
         'print(",".join(numpy_simd_targets()))'],
        env=env, capture_output=True, text=True, check=True, timeout=120)
    return out.stdout.strip().split(',')


def test_numpy_simd_targets_follow_npy_disable_cpu_features() -> None:
    """The key sees the SIMD level numpy runs at, which NPY_DISABLE_CPU_FEATURES lowers."""
    from numpy._core import _multiarray_umath as umath

    here = list(disk_cache.numpy_simd_targets())
    assert here[:len(umath.__cpu_baseline__)] == list(umath.__cpu_baseline__)
    dispatched = here[len(umath.__cpu_baseline__):]
    assert set(dispatched) <= set(umath.__cpu_dispatch__)
    if os.environ.get('NPY_DISABLE_CPU_FEATURES'):
        assert disk_cache.numerical_environment().endswith('simd=' + ','.join(here))
    if dispatched:  # a CPU above numpy's baseline: disabling its top target changes the key
        top = dispatched[-1]
        lowered = _simd_targets_in_subprocess(top)
        assert top not in lowered and lowered != here
    else:  # a baseline-only CPU has nothing to disable: the same targets
        assert _simd_targets_in_subprocess('') == here


def test_anatomy_cache_key_covers_parameters_code_and_environment(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv('CGAIL_PLANNER_NO_DISK_CACHE', raising=False)
    params = anatomy_params('default')
    base = anatomy_mod._cache_path('default', params)
    assert base is not None and base.parent == Path.home() / '.cache' / 'cgail_planner'
    assert anatomy_mod._cache_path('default', params) == base
    assert anatomy_mod._cache_path('default', dataclasses.replace(
        params, edge_length=0.0038)) != base
    assert anatomy_mod._cache_path('other', params) != base
    with monkeypatch.context() as m:  # another CPU's numpy (or another numpy/scipy/trimesh)
        m.setattr(disk_cache, 'numerical_environment',
                  lambda: 'numpy=2.4.6 scipy=1.17.1 trimesh=5.2.0 machine=x86_64 simd=X86_V2')
        assert anatomy_mod._cache_path('default', params) != base
    with monkeypatch.context() as m:  # another commit's generator
        m.setattr(disk_cache, 'source_digest', lambda *files: 'edited')
        assert anatomy_mod._cache_path('default', params) != base
    monkeypatch.setenv('CGAIL_PLANNER_NO_DISK_CACHE', '1')
    assert anatomy_mod._cache_path('default', params) is None


def test_source_digest_reads_the_files(tmp_path: Path) -> None:
    a, b = tmp_path / 'a.py', tmp_path / 'b.py'
    a.write_text('x = 1\n')
    b.write_text('y = 2\n')
    d = disk_cache.source_digest(str(a), str(b))
    assert d == disk_cache.source_digest(str(a), str(b)) != disk_cache.source_digest(str(b),
                                                                                    str(a))
    assert d != disk_cache.source_digest(str(a))


def _copy(anatomy: Anatomy, **changes: object) -> Anatomy:
    fields = {f.name: getattr(anatomy, f.name) for f in dataclasses.fields(anatomy)
              if f.name != '_mesh'}
    return Anatomy(**{**fields, **changes})


def test_content_hash_identifies_the_mesh_not_the_name() -> None:
    a = build_anatomy('default')
    assert len(a.content_hash) == 16 and int(a.content_hash, 16) >= 0
    assert _copy(a).content_hash == a.content_hash
    assert _copy(a, name='renamed').content_hash == a.content_hash
    nudged = np.array(a.vertices)
    nudged[100, 2] = np.nextafter(nudged[100, 2], 1.0)  # one vertex, one ulp
    assert _copy(a, vertices=nudged).content_hash != a.content_hash
    start = np.array(a.start_point) + 1e-9
    assert _copy(a, start_point=start).content_hash != a.content_hash
    assert _copy(a, ostium_vertices={**a.ostium_vertices, 'left': 0}).content_hash \
        != a.content_hash
    assert build_anatomy('elongated').content_hash != a.content_hash


def test_centerline_cache_key_covers_the_mesh_code_and_environment(
        monkeypatch: pytest.MonkeyPatch) -> None:
    a = build_anatomy('default')
    key = centerline._mesh_key(a, 100)
    assert centerline._mesh_key(_copy(a, name='x'), 100) == key
    assert centerline._mesh_key(a, 101) != key
    # the start point decides where the path starts: part of the key
    assert centerline._mesh_key(_copy(a, start_point=np.array(a.start_point) + 1e-4),
                                100) != key
    monkeypatch.setattr(disk_cache, 'numerical_environment', lambda: 'another CPU')
    assert centerline._mesh_key(a, 100) != key

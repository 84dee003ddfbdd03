"""Cost and quality of the simulator geometry: anatomy build, centrelines, ``contains``.

Prints, per built-in anatomy, CPU time of this process and wall-clock time (on a shared,
loaded machine the CPU time is the cost) for:

* a cold ``build_anatomy`` (disk cache bypassed);
* ``compute_centerlines`` (Voronoi method, memory and disk caches bypassed);
* ``Anatomy.contains`` on 10,000 random points in the bounding box;

and the mesh figures: vertices, faces, cap faces, edge length (median, 5th/95th percentile)
and the smallest triangle angle (1st/5th percentile, minimum) over faces the PBD can move.

Run: ``scripts/ws python bench/bench_geometry.py [--anatomy default elongated]``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import functools
import os
import time
from typing import Any

import numpy as np

os.environ["CGAIL_PLANNER_NO_DISK_CACHE"] = "1"

from cgail_sim import anatomy as anatomy_mod
from cgail_sim import centerline as centerline_mod


def _timed(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c0, time.perf_counter() - w0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--anatomy", nargs="+", default=list(anatomy_mod.ANATOMY_NAMES))
    args = ap.parse_args()
    for name in args.anatomy:
        params = anatomy_mod.anatomy_params(name)
        anatomy, cpu, wall = _timed(functools.partial(anatomy_mod._build, params, name))
        print(f"[{name}] cold build_anatomy: {cpu:.2f} s CPU, {wall:.2f} s wall")
        mesh = anatomy.mesh
        edges = mesh.edges_unique_length * 1e3
        prescribed = np.zeros(len(anatomy.vertices), dtype=bool)
        prescribed[anatomy.fixed_vertices] = True
        prescribed[anatomy.annulus_vertices] = True
        free = ~prescribed[anatomy.faces].all(axis=1)
        ang = np.degrees(mesh.face_angles[free].min(axis=1))
        print(f"[{name}] {len(anatomy.vertices)} vertices, {len(anatomy.faces)} faces "
              f"({int((~anatomy.wall_face_mask).sum())} cap faces), watertight "
              f"{mesh.is_watertight}, Euler {mesh.euler_number}")
        print(f"[{name}] edge mm: median {np.median(edges):.2f}, p5 {np.percentile(edges, 5):.2f},"
              f" p95 {np.percentile(edges, 95):.2f}; min angle deg: p1 "
              f"{np.percentile(ang, 1):.1f}, p5 {np.percentile(ang, 5):.1f}, min {ang.min():.1f}")
        centerline_mod._MEMORY.clear()
        lines, cpu, wall = _timed(functools.partial(centerline_mod.compute_centerlines, anatomy))
        print(f"[{name}] compute_centerlines: {cpu:.2f} s CPU, {wall:.2f} s wall; lengths "
              + ", ".join(f"{b} {c.length * 1e3:.0f} mm" for b, c in lines.items()))
        rng = np.random.default_rng(0)
        lo, hi = anatomy.vertices.min(axis=0), anatomy.vertices.max(axis=0)
        pts = lo + rng.random((10000, 3)) * (hi - lo)
        inside, cpu, wall = _timed(functools.partial(anatomy.contains, pts))
        print(f"[{name}] contains(10k points): {cpu * 1e3:.0f} ms CPU, {wall * 1e3:.0f} ms "
              f"wall, {inside.mean() * 100:.1f} % inside")


if __name__ == "__main__":
    main()

"""prepare_anatomy on a synthetic CT label map: prepare time, and the env speeds on the result.

Run: ``scripts/ws python bench/bench_prepare.py [--seconds 3] [--target-vertices 2500]``.

Makes a synthetic label map of the default aorta at CT spacing (0.84 x 0.84 x 1.0 mm, LPS voxel
order, left-ventricle map; :mod:`cgail_patient.synthetic`), runs ``prepare_anatomy`` on it
(timed per step), then steps the static and the dynamic environment on the prepared anatomy
(single env, random forward-biased actions with auto-reset, one thread, after a warm-up; the
median CPU time of a step, as ``bench/bench_sim.py`` measures the built-in anatomies).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from pathlib import Path
import tempfile
import time

import numpy as np

from cgail_patient.prepare_cli import prepare_anatomy
from cgail_patient.synthetic import make_synthetic_ct, SyntheticCTConfig
from cgail_sim.anatomy import load_anatomy_mesh
from cgail_sim.centerline import compute_centerlines
from cgail_sim.config import EnvConfig
import cgail_sim.env as env_mod
from cgail_sim.scenarios import build_scenarios, World


def env_rate(world: World, mode: str, seconds: float) -> float:
    """Median-CPU-time steps/s of a single env in ``world``."""
    original = env_mod.load_world
    env_mod.load_world = lambda *args: world  # type: ignore[assignment]
    try:
        env = env_mod.CatheterNavEnv(EnvConfig(mode=mode))
    finally:
        env_mod.load_world = original
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    cpu: list[float] = []
    start = time.perf_counter()
    k = 0
    while time.perf_counter() - start < seconds or len(cpu) < 10:
        a = rng.uniform(-1.0, 1.0, 3).astype(np.float32)
        a[2] = 0.5 + 0.5 * abs(a[2])
        c0 = time.thread_time()
        _, _, te, tr, _ = env.step(a)
        if k >= 100:  # warm-up: the contact kernels load on first use
            cpu.append(time.thread_time() - c0)
        k += 1
        if te or tr:
            env.reset()
    return 1.0 / float(np.median(cpu))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--target-vertices", type=int, default=2500)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        ct = make_synthetic_ct(SyntheticCTConfig())
        paths = ct.write(tmp)
        t_gen = time.perf_counter() - t0
        print(f"synthetic label map {ct.aorta.shape} voxels of 0.84 x 0.84 x 1.0 mm: "
              f"{t_gen:.1f} s")
        result = prepare_anatomy([str(paths["aorta"]), "--lv", str(paths["lv"]), "--out",
                                  str(Path(tmp) / "prepared"), "--target-vertices",
                                  str(args.target_vertices)])
        print(f"prepare_anatomy: {result.prepared.timings['total']:.1f} s "
              f"({'usable' if result.usable else 'NOT usable'})")
        for step, sec in result.prepared.timings.items():
            if step != "total":
                print(f"  {step:20s} {sec:6.2f} s")
        anatomy = load_anatomy_mesh(Path(tmp) / "prepared" / "lumen.stl")
    lines = compute_centerlines(anatomy)
    world = World(anatomy, lines, build_scenarios(anatomy, lines))
    print(f"prepared lumen: {len(anatomy.vertices)} vertices, "
          f"{int(anatomy.wall_face_mask.sum())} wall faces")
    for mode in ("static", "dynamic"):
        print(f"  {mode:8s} env: {env_rate(world, mode, args.seconds):7.0f} steps/s "
              "(median CPU time per step)")


if __name__ == "__main__":
    main()

"""Simulator throughput: env steps/s (static/dynamic, single/batched), raycast and PBD cost.

Run: ``scripts/ws python bench/bench_sim.py [--seconds 2] [--num-envs 64] [--pursuit]``.

Every figure is measured on one process (numba and numpy pinned to one thread with
``NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1`` set below before the imports) after a warm-up, with
random forward-biased actions and auto-reset, so episodes end by collisions/truncations as in
training. Each rate is given three ways: from the median CPU time of one step (the cost on an
idle core; robust on a shared machine), from the total CPU time, and from the wall clock (on a
loaded machine this also counts the time spent waiting for a core). ``--pursuit`` also runs
the scripted sanity policy (pure pursuit of the centerline,
:func:`cgail_sim.env.pursuit_actions`) on every start x target pair and prints how far
it gets.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from collections.abc import Callable
import time
from typing import NamedTuple

import numpy as np

from cgail_sim.config import EnvConfig
from cgail_sim.env import (
    CatheterNavEnv,
    DYNAMIC_PBD_CONFIG,
    pursuit_actions,
    RAY_DIRECTIONS,
)
from cgail_sim.ftl_model import N_RAYS
from cgail_sim.pbd import PBDConfig
from cgail_sim.vec_env import CatheterNavVecEnv
from cgail_sim.wall import DeformableWall, StaticWall, WallError
from cgail_sim.worlds import load_world


def _actions(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.uniform(-1.0, 1.0, size=(n, 3))
    a[:, 2] = 0.5 + 0.5 * np.abs(a[:, 2])  # forward-biased, like a navigating policy
    return a.astype(np.float32)


class Timing(NamedTuple):
    """Cost of a repeated call: medians per call and totals-based rates."""

    calls: int
    cpu_median: float
    """Median CPU time of the calling thread per call, s (the cost; waiting for a core on a
    loaded machine does not count)."""
    cpu_total: float
    """Total CPU time / calls, s."""
    wall_total: float
    """Total wall-clock time / calls, s (includes waiting for a core)."""


def _timed(fn: Callable[[], object], seconds: float, warmup: int = 3) -> Timing:
    """Call ``fn`` repeatedly for ``seconds`` (at least 3 calls) after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    cpu: list[float] = []
    w_start = time.perf_counter()
    c_start = time.thread_time()
    while True:
        c0 = time.thread_time()
        fn()
        cpu.append(time.thread_time() - c0)
        elapsed = time.perf_counter() - w_start
        if elapsed >= seconds and len(cpu) >= 3:
            n = len(cpu)
            return Timing(n, float(np.median(cpu)), (time.thread_time() - c_start) / n,
                          elapsed / n)


def bench_single(mode: str, seconds: float, pbd: PBDConfig | None = None) -> Timing:
    env = CatheterNavEnv(EnvConfig(mode=mode), pbd_config=pbd)
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def step() -> None:
        _, _, te, tr, _ = env.step(_actions(rng, 1)[0])
        if te or tr:
            env.reset()

    return _timed(step, seconds, warmup=100)  # long enough to load the contact kernels


def bench_vec(mode: str, n: int, seconds: float, pbd: PBDConfig | None = None) -> Timing:
    vec = CatheterNavVecEnv(EnvConfig(mode=mode), num_envs=n, pbd_config=pbd)
    vec.reset(seed=0)
    rng = np.random.default_rng(0)
    t = _timed(lambda: vec.step(_actions(rng, n)), seconds, warmup=max(3, 100 // n))
    # per env step
    return Timing(t.calls * n, t.cpu_median / n, t.cpu_total / n, t.wall_total / n)


def bench_components(seconds: float, n: int) -> dict[str, Timing]:
    world = load_world("default")
    anatomy = world.anatomy
    start = world.scenarios.starts[1]
    rot = start.rotation
    dirs = RAY_DIRECTIONS @ rot.T
    origins = np.repeat(start.position[None], N_RAYS, axis=0)
    static = StaticWall(anatomy)
    dyn = DeformableWall(anatomy, DYNAMIC_PBD_CONFIG)
    out: dict[str, Timing] = {}
    out["raycast static, 25 rays"] = _timed(
        lambda: static.raycast(origins, dirs, 0.04), seconds / 4)
    big_o = np.tile(origins, (n, 1))
    big_d = np.tile(dirs, (n, 1))
    out[f"raycast static, {n} x 25 rays (one call)"] = _timed(
        lambda: static.raycast(big_o, big_d, 0.04), seconds / 4)
    out["tip_contact static"] = _timed(
        lambda: static.tip_contact(start.position, 0.0035, 0.1), seconds / 4)
    body = np.array([start.introducer_tail, start.position])
    # Dynamic wall, as the env calls it every step: PBD step (which also refits the BVH to the
    # new shape), then the rays, then the tip contact (closest point + Newton force).
    clock = [0.0]
    for name, cfg in ((f"{PBDConfig().iterations} sweeps, PBDConfig()", PBDConfig()),
                      (f"{DYNAMIC_PBD_CONFIG.iterations} Chebyshev sweeps, env default",
                       DYNAMIC_PBD_CONFIG)):
        wall = DeformableWall(anatomy, cfg)

        def pbd_step(wall: DeformableWall = wall) -> None:
            clock[0] += 0.1
            wall.step(clock[0], 0.1, body, 0.0035)

        out[f"PBD step incl. BVH refit ({name})"] = _timed(pbd_step, seconds)
    # The catheter body shifted towards the wall until its tip sphere lies 1 mm beyond the
    # surface: the straight body then presses ~1 mm along the 50 mm of descending wall it lies
    # by, down to the fixed ring at the descending cut (contact pairs, local settling sweeps,
    # Newton force); also loads every contact kernel before the env timings.
    sd, _, normal, _ = static._bvh.closest_point(start.position)
    press = body + (0.001 - 0.0035 - sd) * normal  # tip sphere 1 mm beyond the surface
    name = f"PBD step, body pressing the wall 1 mm ({DYNAMIC_PBD_CONFIG.iterations} sweeps)"
    try:
        out[name] = _timed(lambda: dyn.step(clock[0], 0.1, press, 0.0035), seconds / 2)
        out["tip_contact deformable, pressing (incl. Newton force)"] = _timed(
            lambda: dyn.tip_contact(press[-1], 0.0035, 0.1), seconds / 4)
        print(f"  pressing: largest particle displacement {dyn.max_displacement * 1e3:.1f} mm "
              "(heartbeat and the 1 mm dent)")
    except WallError as err:  # a benchmark reports a wall fault and goes on
        print(f"  pressing: simulation fault, not timed: {err}")
    dyn.reset()
    for k in range(3):
        dyn.step(0.1 * (k + 1), 0.1, body, 0.0035)
    out["raycast deformable, 25 rays"] = _timed(
        lambda: dyn.raycast(origins, dirs, 0.04), seconds / 4)
    out["tip_contact deformable"] = _timed(
        lambda: dyn.tip_contact(start.position, 0.0035, 0.1), seconds / 4)
    return out


def run_pursuit(mode: str) -> None:
    env = CatheterNavEnv(EnvConfig(mode=mode))
    sc = env.scenarios
    results = []
    for s in range(len(sc.starts)):
        for g in range(len(sc.targets)):
            env.reset(seed=0, options={"start": s, "target": g})
            ret = 0.0
            while True:
                _, r, te, tr, info = env.step(pursuit_actions(env.engine)[0])
                ret += r
                if te or tr:
                    break
            results.append(info["success"])
            end = ("success" if info["success"] else "collision" if info["collision"]
                   else "exit" if info["exited"] else "truncated")
            print(f"  start {s} target {g}: {end:9s} T_s {info['timesteps']:4d}  "
                  f"T_a {info['targeting_error'] * 1e3:5.1f} mm  waypoints "
                  f"{info['waypoints_reached']:3d}  return {ret:6.3f}")
    print(f"  pursuit success rate ({mode}): {np.mean(results):.2f} over {len(results)} trials")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="time per measurement, s")
    parser.add_argument("--num-envs", type=int, default=64, help="batch size of the vec env")
    parser.add_argument("--dyn-envs", type=int, default=4, help="batch size, dynamic vec env")
    parser.add_argument("--pursuit", action="store_true", help="also run the sanity policy")
    args = parser.parse_args()
    load = os.getloadavg()
    print(f"nproc {os.cpu_count()}  load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    world = load_world("default")  # built/cached outside the timings
    print(f"wall mesh: {len(world.anatomy.vertices)} vertices, "
          f"{int(np.sum(world.anatomy.wall_face_mask))} wall triangles")
    comp = bench_components(args.seconds, args.num_envs)
    print(f"  {'component, ms per call':60s} {'median CPU':>10s} {'mean CPU':>10s} "
          f"{'wall-clock':>10s}")
    for name, t in comp.items():
        print(f"  {name:60s} {t.cpu_median * 1e3:10.3f} {t.cpu_total * 1e3:10.3f} "
              f"{t.wall_total * 1e3:10.3f}")
    rows = [
        ("static  single env", bench_single("static", args.seconds)),
        (f"static  batched (N={args.num_envs})",
         bench_vec("static", args.num_envs, args.seconds)),
        (f"dynamic single env ({DYNAMIC_PBD_CONFIG.iterations} acc. sweeps)",
         bench_single("dynamic", args.seconds)),
        (f"dynamic batched (N={args.dyn_envs})",
         bench_vec("dynamic", args.dyn_envs, args.seconds)),
        (f"dynamic single env ({PBDConfig().iterations} sweeps)",
         bench_single("dynamic", args.seconds, PBDConfig())),
    ]
    print("env steps per second (one process): from the median CPU time per step (the cost on "
          "an idle core), the total CPU time, and the wall clock (includes waiting for a core "
          "on a loaded machine)")
    print(f"  {'':34s} {'median CPU':>10s} {'total CPU':>10s} {'wall-clock':>10s}")
    for name, t in rows:
        print(f"  {name:34s} {1.0 / t.cpu_median:10.0f} {1.0 / t.cpu_total:10.0f} "
              f"{1.0 / t.wall_total:10.0f}")
    load = os.getloadavg()
    print(f"load average at the end {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if args.pursuit:
        for mode in ("static", "dynamic"):
            print(f"scripted pursuit sanity policy, {mode}:")
            run_pursuit(mode)


if __name__ == "__main__":
    main()

"""Simulator throughput: env steps/s (static/dynamic, single/batched), raycast and PBD cost.

Run: ``scripts/ws python bench/bench_sim.py [--seconds 2] [--num-envs 64] [--pursuit]``.

Every figure is measured on one process (numba and numpy pinned to one thread with
``NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1`` set below before the imports) after a warm-up, with
random forward-biased actions and auto-reset, so episodes end by collisions/truncations as in
training. ``--pursuit`` also runs the scripted sanity policy (pure pursuit of the centerline,
:func:`cgail_planner.sim.env.pursuit_actions`) on every start x target pair and prints how far
it gets.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time

import numpy as np

from cgail_planner.sim.config import EnvConfig
from cgail_planner.sim.env import (
    CatheterNavEnv,
    N_RAYS,
    pursuit_actions,
    RAY_DIRECTIONS,
)
from cgail_planner.sim.scenarios import load_world
from cgail_planner.sim.vec_env import CatheterNavVecEnv
from cgail_planner.sim.wall import DeformableWall, StaticWall


def _actions(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.uniform(-1.0, 1.0, size=(n, 3))
    a[:, 2] = 0.5 + 0.5 * np.abs(a[:, 2])  # forward-biased, like a navigating policy
    return a.astype(np.float32)


def _timed(fn, seconds: float, warmup: int = 3) -> tuple[float, int]:
    """Call ``fn`` repeatedly for ``seconds``; return (seconds per call, calls)."""
    for _ in range(warmup):
        fn()
    n = 0
    t0 = time.perf_counter()
    while True:
        fn()
        n += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds:
            return elapsed / n, n


def bench_single(mode: str, seconds: float) -> float:
    env = CatheterNavEnv(EnvConfig(mode=mode))
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def step() -> None:
        _, _, te, tr, _ = env.step(_actions(rng, 1)[0])
        if te or tr:
            env.reset()

    per, _ = _timed(step, seconds)
    return 1.0 / per


def bench_vec(mode: str, n: int, seconds: float) -> float:
    vec = CatheterNavVecEnv(EnvConfig(mode=mode), num_envs=n)
    vec.reset(seed=0)
    rng = np.random.default_rng(0)
    per, _ = _timed(lambda: vec.step(_actions(rng, n)), seconds)
    return n / per


def bench_components(seconds: float, n: int) -> dict[str, float]:
    world = load_world("default")
    anatomy = world.anatomy
    start = world.scenarios.starts[1]
    rot = start.rotation
    dirs = RAY_DIRECTIONS @ rot.T
    origins = np.repeat(start.position[None], N_RAYS, axis=0)
    static = StaticWall(anatomy)
    dyn = DeformableWall(anatomy)
    out: dict[str, float] = {}
    out["raycast static, 25 rays"], _ = _timed(
        lambda: static.raycast(origins, dirs, 0.04), seconds / 4)
    big_o = np.tile(origins, (n, 1))
    big_d = np.tile(dirs, (n, 1))
    out[f"raycast static, {n} x 25 rays (one call)"], _ = _timed(
        lambda: static.raycast(big_o, big_d, 0.04), seconds / 4)
    out["tip_contact static"], _ = _timed(
        lambda: static.tip_contact(start.position, 0.0035, 0.1), seconds / 4)
    body = np.array([start.introducer_tail, start.position])
    # Dynamic wall, as the env calls it every step: PBD step, then rays (after the step the BVH
    # is refit lazily), then the tip contact (closest point + Newton force on the new shape).
    dyn.reset()
    for k in range(3):
        dyn.step(0.1 * (k + 1), 0.1, body, 0.0035)
    cost = np.zeros(3)
    t = 0.3
    calls = 0
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end or calls < 3:
        t += 0.1
        t0 = time.perf_counter()
        dyn.step(t, 0.1, body, 0.0035)
        t1 = time.perf_counter()
        dyn.raycast(origins, dirs, 0.04)
        t2 = time.perf_counter()
        dyn.tip_contact(start.position, 0.0035, 0.1)
        t3 = time.perf_counter()
        cost += (t1 - t0, t2 - t1, t3 - t2)
        calls += 1
    cost /= calls
    out["PBD step (DeformableWall.step, dt 0.1 s)"] = cost[0]
    out["raycast deformable after a step (incl. BVH refit), 25 rays"] = cost[1]
    out["tip_contact deformable after a step"] = cost[2]
    out["_n_vertices"] = float(len(anatomy.vertices))
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
    load_world("default")  # build/cached outside the timings
    comp = bench_components(args.seconds, args.num_envs)
    print(f"wall mesh: {int(comp.pop('_n_vertices'))} vertices")
    for name, per in comp.items():
        print(f"  {name:60s} {per * 1e3:8.3f} ms")
    rows = [
        ("static  single env", bench_single("static", args.seconds)),
        (f"static  batched (N={args.num_envs})",
         bench_vec("static", args.num_envs, args.seconds)),
        ("dynamic single env", bench_single("dynamic", args.seconds)),
        (f"dynamic batched (N={args.dyn_envs})",
         bench_vec("dynamic", args.dyn_envs, args.seconds)),
    ]
    print("env steps per second (one process):")
    for name, rate in rows:
        print(f"  {name:30s} {rate:10.0f}")
    if args.pursuit:
        for mode in ("static", "dynamic"):
            print(f"scripted pursuit sanity policy, {mode}:")
            run_pursuit(mode)


if __name__ == "__main__":
    main()

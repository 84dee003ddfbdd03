"""Planner speed: whole-path planning (rollout + B-spline fit) and guidance per tracker frame.

Targets (issue 6): a full path in <= 50 ms, a guidance update in <= 2 ms per tracker frame.

For every start x target of the anatomy's scenario set it plans with the ONNX policy loaded as
the node loads it (:class:`OnnxPolicy`: the numba ``mlp`` backend when the graph allows it, the
rollout then running as one numba call, :mod:`cgail_planner.core.rollout_kernel`) and with the
centerline baseline, then replays the planned path as a noisy tracker stream (0.5 mm EM noise)
through the guidance (projection, next waypoint, suggested bend). Prints wall and CPU time per
plan (median, max), rollout steps and time per step, the per-step components, the planner
construction (numba kernel load) and first plan, and guidance time per frame (median, 99th
percentile). On a shared, loaded machine the CPU time is the cost; the wall time includes waiting
for a core.
``--compare`` adds the previous implementation: the Python rollout loop
(``Planner.rollout_reference``) with the policy on onnxruntime.

Run: ``scripts/ws python bench/bench_planner.py [--policy model.onnx] [--anatomy default]
[--compare]`` (default policy: the committed C-GAIL model
``cgail_planner/models/cgail_default_static.onnx``).
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
import sys
import time

import numpy as np

from cgail_planner.core.errors import NoPathError
from cgail_planner.core.guidance import PathFollower
from cgail_planner.core.onnx_policy import OnnxPolicy
from cgail_planner.core.planner import model_world_from_sim, Planner, PlannerConfig
from cgail_sim.env import RAY_DIRECTIONS
from cgail_sim.ftl_model import frame_from_heading
from cgail_sim.wall import StaticWall
from cgail_sim.worlds import load_world

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_POLICY = (ROOT / 'src' / 'cgail_planner' / 'cgail_planner' / 'models'
                  / 'cgail_default_static.onnx')


def _stats(values: list[float]) -> str:
    a = np.asarray(values) * 1e3
    return f'median {np.median(a):7.2f} ms, max {a.max():7.2f} ms'


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--policy', type=Path, default=DEFAULT_POLICY)
    ap.add_argument('--anatomy', default='default')
    ap.add_argument('--repeats', type=int, default=2, help='plans per scenario (first is warm-up)')
    ap.add_argument('--compare', action='store_true',
                    help='also time the Python rollout loop with the policy on onnxruntime')
    args = ap.parse_args()
    world = load_world(args.anatomy)
    model = model_world_from_sim(world)
    wall = StaticWall(world.anatomy)
    policy = OnnxPolicy(args.policy, expected_obs_dim=41)
    sc = world.scenarios
    print(f'bench_planner: anatomy {args.anatomy}, policy {args.policy.name} '
          f'({policy.metadata.get("preset", "?")}, {policy.backend} backend), {len(sc.starts)} '
          f'starts x {len(sc.targets)} targets; torch imported: {"torch" in sys.modules}')
    w0, c0 = time.perf_counter(), time.process_time()
    planner = Planner(PlannerConfig(), model, wall, policy, RAY_DIRECTIONS)
    w1, c1 = time.perf_counter(), time.process_time()
    start, target = sc.starts[0], sc.targets[0]
    with contextlib.suppress(NoPathError):
        planner.plan(start.position, start.rotation, target.position)
    print(f'planner construction (loads the numba kernel): wall {(w1 - w0) * 1e3:.0f} ms, CPU '
          f'{(c1 - c0) * 1e3:.0f} ms; first plan: wall {(time.perf_counter() - w1) * 1e3:.0f} '
          f'ms, CPU {(time.process_time() - c1) * 1e3:.0f} ms; rollout as one numba call: '
          f'{planner.uses_kernel}')
    methods: list[tuple[str, str, OnnxPolicy | None]] = [('cgail', 'cgail', policy),
                                              ('centerline', 'centerline', None)]
    if args.compare:
        methods.append(('cgail (Python loop + onnxruntime)', 'cgail',
                        OnnxPolicy(args.policy, expected_obs_dim=41, backend='onnxruntime')))
    paths = []
    for label, kind, pol in methods:
        planner = Planner(PlannerConfig(planner_type=kind), model, wall, pol, RAY_DIRECTIONS)
        walls, cpus, steps, failures = [], [], [], 0
        for start in sc.starts:
            for target in sc.targets:
                for rep in range(args.repeats):
                    w0, c0 = time.perf_counter(), time.process_time()
                    try:
                        res = planner.plan(start.position, start.rotation, target.position)
                    except NoPathError:
                        failures += 1
                        break
                    if rep == args.repeats - 1 or args.repeats == 1:
                        walls.append(time.perf_counter() - w0)
                        cpus.append(time.process_time() - c0)
                        steps.append(res.steps)
                        if label == kind:
                            paths.append(res.path)
        n = len(sc.starts) * len(sc.targets)
        print(f'{label:10s} full path: wall {_stats(walls)} | CPU {_stats(cpus)} | '
              f'{n - failures}/{n} planned' + (
                  f' | rollout {np.mean(steps):.0f} steps (max {max(steps)}), CPU '
                  f'{np.median(np.array(cpus) / np.array(steps)) * 1e6:.0f} us/step'
                  if kind == 'cgail' and steps else ''))
    # per-step components of the rollout, each called from Python here (inside the kernel the
    # policy program and the ray kernel run without the call overhead)
    obs = np.zeros(41, dtype=np.float32)
    origins = np.repeat(start.position[None], len(RAY_DIRECTIONS), axis=0)
    dirs = RAY_DIRECTIONS @ start.rotation.T
    ort_policy = OnnxPolicy(args.policy, expected_obs_dim=41, backend='onnxruntime')
    components = [(f'policy ({policy.backend} backend)', lambda: policy(obs)),
                  ('policy (onnxruntime)', lambda: ort_policy(obs)),
                  ('25-ray cast', lambda: wall.raycast(origins, dirs, 0.04))]
    for label, fn in components:
        fn()
        c0 = time.process_time()
        for _ in range(2000):
            fn()
        print(f'  rollout component {label:22s}: CPU {(time.process_time() - c0) * 500:.1f} us '
              'per call')
    rng = np.random.default_rng(0)
    walls, cpus = [], []
    for path in paths:
        follower = PathFollower(path)
        tangents = np.gradient(path, axis=0)
        for k in range(0, len(path), 2):
            p = path[k] + rng.normal(0.0, 0.0005 / np.sqrt(3.0), 3)
            r = frame_from_heading(tangents[k])
            w0, c0 = time.perf_counter(), time.process_time()
            follower.guide(p, r)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
    w, c = np.asarray(walls) * 1e3, np.asarray(cpus) * 1e3
    print(f'guidance per tracker frame ({len(w)} frames): wall median {np.median(w):.3f} ms, '
          f'p99 {np.percentile(w, 99):.3f} ms | CPU median {np.median(c):.3f} ms, '
          f'p99 {np.percentile(c, 99):.3f} ms')
    print('targets: full path <= 50 ms, guidance <= 2 ms per frame')
    return 0


if __name__ == '__main__':
    sys.exit(main())

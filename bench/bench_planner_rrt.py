"""Planning time of the curvature-constrained RRT (``planner_type: rrt``) over the scenario sets.

Target (issue 14): the planner node plans with ``planner_type: rrt`` within 1 s, on one core.

For each anatomy (default: both built-in ones) and each of ``--seeds`` seeds it plans from every
start to every target (3 x 5) through :class:`cgail_planner.core.planner.Planner` as the node
does (the RRT's time limit ``--time-limit``, default the node's 1 s), and prints per anatomy the
success count and the wall and CPU time per plan (median, 90th percentile, max; successful plans
and all plans). The RRT is single-threaded; on a shared machine the CPU time is the cost and the
wall time includes waiting for a core.

Run: ``scripts/ws python bench/bench_planner_rrt.py [--anatomy default elongated] [--seeds 1]
[--time-limit 1.0]``.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from cgail_planner.core.errors import NoPathError
from cgail_planner.core.planner import model_world_from_sim, Planner, PlannerConfig
from cgail_planner.core.rrt_planner import RrtConfig
from cgail_planner.sim.scenarios import load_world
from cgail_planner.sim.wall import StaticWall


def _stats(values: list[float]) -> str:
    if not values:
        return 'none'
    a = np.asarray(values) * 1e3
    return (f'median {np.median(a):6.0f} ms, p90 {np.percentile(a, 90):6.0f} ms, '
            f'max {a.max():6.0f} ms')


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--anatomy', nargs='+', default=['default', 'elongated'])
    ap.add_argument('--seeds', type=int, default=1, help='seeds 0..N-1 per scenario')
    ap.add_argument('--time-limit', type=float, default=RrtConfig().time_limit_s)
    args = ap.parse_args()
    for anatomy in args.anatomy:
        world = load_world(anatomy)
        model, wall = model_world_from_sim(world), StaticWall(world.anatomy)
        sc = world.scenarios
        walls, cpus, all_walls = [], [], []
        failures: list[str] = []
        for seed in range(args.seeds):
            config = PlannerConfig(planner_type='rrt',
                                   rrt=RrtConfig(seed=seed, time_limit_s=args.time_limit))
            planner = Planner(config, model, wall, None)
            for i, start in enumerate(sc.starts):
                for j, target in enumerate(sc.targets):
                    w0, c0 = time.perf_counter(), time.process_time()
                    try:
                        planner.plan(start.position, start.rotation, target.position)
                    except NoPathError:
                        failures.append(f'start {i} x target {j} (seed {seed})')
                    else:
                        walls.append(time.perf_counter() - w0)
                        cpus.append(time.process_time() - c0)
                    all_walls.append(time.perf_counter() - w0)
        n = len(all_walls)
        print(f'{anatomy:10s} rrt: {n - len(failures)}/{n} planned within '
              f'{args.time_limit:g} s | planned: wall {_stats(walls)} | CPU {_stats(cpus)} | '
              f'all plans: wall {_stats(all_walls)}')
        if failures:
            print(f'{"":10s} no path: {", ".join(failures)}')
    print('target: a plan within 1 s')
    return 0


if __name__ == '__main__':
    sys.exit(main())

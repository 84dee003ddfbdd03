"""Success and planning time of the curvature-constrained RRT (``planner_type: rrt``) over the
scenario sets, under its deterministic iteration budget.

Target (issue 14): the planner node plans with ``planner_type: rrt`` within 1 s, on one core.

For each anatomy (default: both built-in ones) and each of ``--seeds`` seeds it plans from every
start to every target (3 x 5) through :class:`cgail_planner.core.planner.Planner` as the node
does, with the RRT's iteration budget ``--max-iterations`` (default the config's) and a
generous time limit ``--time-limit`` (default 60 s), so that the success count is a function of
the seeds and the settings, not of the machine. It prints per anatomy the success count, the
iterations a found path used, the plans that ran out (and which limit), and the wall and CPU
time per plan (median, 90th percentile, max; found paths and all plans). The RRT is
single-threaded; on a shared machine the CPU time is the cost and the wall time includes waiting
for a core. ``--time-limit 1`` measures the node's real-time bound instead (host-dependent).

Run: ``scripts/ws python bench/bench_planner_rrt.py [--anatomy default elongated] [--seeds 1]
[--max-iterations 1000] [--time-limit 60]``.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from cgail_planner.core.errors import NoPathError
from cgail_planner.core.planner import model_world_from_sim, Planner, PlannerConfig
from cgail_planner.core.rrt_planner import RrtConfig
from cgail_sim.wall import StaticWall
from cgail_sim.worlds import load_world


def _stats(values: list[float]) -> str:
    if not values:
        return 'none'
    a = np.asarray(values) * 1e3
    return (f'median {np.median(a):5.0f} ms, p90 {np.percentile(a, 90):5.0f} ms, '
            f'max {a.max():5.0f} ms')


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--anatomy', nargs='+', default=['default', 'elongated'])
    ap.add_argument('--seeds', type=int, default=1, help='seeds 0..N-1 per scenario')
    ap.add_argument('--max-iterations', type=int, default=RrtConfig().max_iterations)
    ap.add_argument('--time-limit', type=float, default=60.0)
    args = ap.parse_args()
    for anatomy in args.anatomy:
        world = load_world(anatomy)
        model, wall = model_world_from_sim(world), StaticWall(world.anatomy)
        sc = world.scenarios
        walls, cpus, all_walls, all_cpus, iterations = [], [], [], [], []
        failures: list[str] = []
        for seed in range(args.seeds):
            rrt = RrtConfig(seed=seed, max_iterations=args.max_iterations,
                            time_limit_s=args.time_limit)
            planner = Planner(PlannerConfig(planner_type='rrt', rrt=rrt), model, wall, None)
            for i, start in enumerate(sc.starts):
                for j, target in enumerate(sc.targets):
                    w0, c0 = time.perf_counter(), time.process_time()
                    try:
                        result = planner.plan(start.position, start.rotation, target.position)
                    except NoPathError as exc:
                        failures.append(f'start {i} x target {j} (seed {seed}, {exc.reason})')
                    else:
                        walls.append(time.perf_counter() - w0)
                        cpus.append(time.process_time() - c0)
                        iterations.append(result.iterations)
                    all_walls.append(time.perf_counter() - w0)
                    all_cpus.append(time.process_time() - c0)
        n = len(all_walls)
        it = (f'median {np.median(iterations):.0f}, max {max(iterations)}' if iterations
              else 'none')
        print(f'{anatomy:10s} rrt: {n - len(failures)}/{n} planned within max_iterations '
              f'{args.max_iterations} (time limit {args.time_limit:g} s) | iterations {it}')
        print(f'{"":10s} found: wall {_stats(walls)} | CPU {_stats(cpus)}')
        print(f'{"":10s} all:   wall {_stats(all_walls)} | CPU {_stats(all_cpus)}')
        if failures:
            print(f'{"":10s} no path: {", ".join(failures)}')
    print('target: a plan within 1 s on one core')
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""The scripted expert's speed on a real aorta: what demonstrations and DAgger labels cost.

Run: ``scripts/ws python bench/bench_expert.py [--anatomy DIR] [--set 3] [--dynamic-episodes 6]``.

Records expert episodes (:func:`cgail_learning.demos_cli.record_episodes`, as
``plan_patient`` and ``make_demos`` do) on one target set of a prepared anatomy (default: AVT
D18, shipped as ``avt-D18``): every start x target pair in the rigid
aorta, and the first ``--dynamic-episodes`` pairs in the beating one. Prints wall seconds per
episode, simulated steps per wall second (the expert's planning included), the share of the
time the expert spends planning, and the success rate. One thread, after one warm-up episode
(numba's kernels load from the disk cache).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from pathlib import Path
import time

from cgail_learning.demos_cli import record_episodes
from cgail_learning.expert import ScriptedExpert
from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv

D18 = "avt-D18"


def measure(anatomy: str, mode: str, scenario_seed: int, episodes: int) -> dict[str, float]:
    """Wall time of ``episodes`` expert episodes and the part spent in the expert's planning."""
    env = CatheterNavEnv(EnvConfig(mode=mode, anatomy=anatomy, scenario_seed=scenario_seed))
    record_episodes(env, 1, 0)  # warm-up
    planning = [0.0]
    act = ScriptedExpert.act

    def timed(self: ScriptedExpert):  # type: ignore[no-untyped-def]
        t0 = time.perf_counter()
        try:
            return act(self)
        finally:
            planning[0] += time.perf_counter() - t0

    ScriptedExpert.act = timed  # type: ignore[method-assign]
    try:
        t0 = time.perf_counter()
        _, stats = record_episodes(env, episodes, 0)
        wall = time.perf_counter() - t0
    finally:
        ScriptedExpert.act = act  # type: ignore[method-assign]
    steps = stats["mean_steps"] * episodes
    return {"episodes": episodes, "wall_s": wall, "s_per_episode": wall / episodes,
            "steps_per_s": steps / wall, "planning_share": planning[0] / wall,
            "success": stats["success_rate"]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--anatomy", default=D18,
                   help="anatomy: a name or a prepared directory (default: AVT D18)")
    p.add_argument("--set", type=int, default=3, help="target set (EnvConfig.scenario_seed)")
    p.add_argument("--dynamic-episodes", type=int, default=6,
                   help="episodes in the beating aorta (the first pairs of the set)")
    args = p.parse_args()
    print(f"bench_expert: {Path(args.anatomy).name}, target set {args.set}")
    print("| mode | episodes | wall (s) | s / episode | steps / s | expert planning | success |")
    print("|---|---|---|---|---|---|---|")
    for mode, n in (("static", 15), ("dynamic", args.dynamic_episodes)):
        r = measure(args.anatomy, mode, args.set, n)
        print(f"| {mode} | {n} | {r['wall_s']:.1f} | {r['s_per_episode']:.2f} | "
              f"{r['steps_per_s']:.0f} | {100 * r['planning_share']:.0f}% | "
              f"{100 * r['success']:.0f}% |", flush=True)


if __name__ == "__main__":
    main()

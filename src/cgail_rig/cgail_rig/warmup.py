"""Fill the on-disk caches once after a build: numba kernels and the built-in anatomies.

The simulator and the planner compile their numba kernels on first use (``cache=True`` keeps
them next to the sources afterwards) and build each anatomy once (kept under
``~/.cache/cgail_planner``). On a fresh clone that first use costs ~30-60 s of CPU and would fall
inside whatever runs first: a node test with a 15 s deadline, the first trial of the main job.
``scripts/setup.sh`` runs this module after ``colcon build`` so that cost is paid during setup;
with warm caches it takes a few seconds.

Run: ``scripts/ws python -m cgail_rig.warmup [--anatomies default elongated]``.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
import sys
import time

import numpy as np


def warm(anatomies: list[str], log: bool = True) -> float:
    """Build each anatomy, step a static and a dynamic env with contact, plan one path.

    Returns:
        Seconds of wall time it took.
    """
    import cgail_planner
    from cgail_planner.core.errors import NoPathError
    from cgail_planner.core.onnx_policy import OnnxPolicy
    from cgail_planner.core.planner import model_world_from_sim, Planner, PlannerConfig
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv, RAY_DIRECTIONS
    from cgail_sim.wall import DeformableWall, StaticWall
    from cgail_sim.worlds import load_world

    t0 = time.monotonic()

    def say(text: str) -> None:
        if log:
            print(f'[warmup] {text} ({time.monotonic() - t0:.0f} s)', flush=True)

    for name in anatomies:
        world = load_world(name)
        say(f'anatomy {name!r} and its centerlines')
    for mode in ('static', 'dynamic'):
        env = CatheterNavEnv(EnvConfig(mode=mode))
        env.reset(seed=0, options={'start': 0, 'target': 0})
        for _ in range(60):  # straight in: the body meets the arch wall (contact kernels)
            _, _, term, trunc, _ = env.step(np.array([0.0, 0.0, 1.0], dtype=np.float32))
            if term or trunc:
                env.reset(seed=0)
        say(f'{mode} environment kernels')
    world = load_world('default')
    policy_path = (Path(cgail_planner.__file__).resolve().parent / 'models'
                   / 'cgail_default_static.onnx')
    policy = OnnxPolicy(policy_path, expected_obs_dim=RAY_DIRECTIONS.shape[0] + 16)
    model = model_world_from_sim(world)
    start, target = world.scenarios.starts[0], world.scenarios.targets[0]
    for wall in (StaticWall(world.anatomy), DeformableWall(world.anatomy)):
        planner = Planner(PlannerConfig(), model, wall, policy, RAY_DIRECTIONS)
        with contextlib.suppress(NoPathError):
            planner.plan(start.position, start.rotation, target.position)
    say('planner rollout kernel and policy program')
    return time.monotonic() - t0


def main(argv: list[str] | None = None) -> int:
    """Entry point: ``python -m cgail_rig.warmup``."""
    p = argparse.ArgumentParser(prog='warmup', description=__doc__.split('\n')[0])
    p.add_argument('--anatomies', nargs='+', default=['default', 'elongated'],
                   help='built-in anatomies to build and cache')
    args = p.parse_args(argv)
    seconds = warm(args.anatomies)
    print(f'[warmup] caches ready in {seconds:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())

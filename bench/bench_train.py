"""Training throughput of a preset in the simulator: steps/s and projected wall time.

    scripts/ws python bench/bench_train.py --preset cgail --mode static --iterations 2 \
        --demos bags/demos/default

Runs ``--iterations`` trainer iterations (each: one buffer of rollouts + the update) and prints
the rollout and update times, the overall env steps/s and the projected wall time of the preset's
``max_steps``. Use ``--threads`` to compare torch thread counts.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import time

import numpy as np
import torch

from cgail_learning.config import load_config
from cgail_learning.demos import load_demos
from cgail_learning.train import make_envs
from cgail_learning.trainer import Trainer


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--preset', default='cgail')
    p.add_argument('--mode', default='static', choices=('static', 'dynamic'))
    p.add_argument('--iterations', type=int, default=2)
    p.add_argument('--threads', type=int, default=1)
    p.add_argument('--demos', nargs='*', default=['bags/demos/default'])
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(args.preset)
    t = time.monotonic()
    env, _, _ = make_envs(args.mode, 'default', cfg.num_envs)
    demo_obs, demo_act, demo_episodes = (load_demos([Path(d) for d in args.demos])
                                         if cfg.needs_demos else (None, None, None))
    print(f'setup (simulator build + demo load): {time.monotonic() - t:.1f} s')
    trainer = Trainer(cfg, env, demo_obs=demo_obs, demo_act=demo_act, seed=0,
                      demo_episodes=demo_episodes)
    t_roll, t_upd = [], []
    for _ in range(args.iterations):
        t0 = time.monotonic()
        trainer.collect()
        t1 = time.monotonic()
        trainer.compute_rewards()
        trainer.update()
        t2 = time.monotonic()
        t_roll.append(t1 - t0)
        t_upd.append(t2 - t1)
    steps = trainer.steps_per_rollout * cfg.num_envs
    per_iter = float(np.mean(t_roll) + np.mean(t_upd))
    sps = steps / per_iter
    print(f'preset {cfg.name}, mode {args.mode}, num_envs {cfg.num_envs}, threads '
          f'{args.threads}, buffer {steps} steps')
    print(f'rollout: {np.mean(t_roll):.2f} s/iter ({steps / np.mean(t_roll):.0f} env steps/s)')
    print(f'update:  {np.mean(t_upd):.2f} s/iter')
    print(f'overall: {sps:.0f} env steps/s; projected wall time for {cfg.max_steps} steps: '
          f'{cfg.max_steps / sps / 60:.1f} min')


if __name__ == '__main__':
    main()

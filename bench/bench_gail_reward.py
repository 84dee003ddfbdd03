"""GAIL reward forms on a corridor toy where ending early is always possible.

Run: ``scripts/ws python bench/bench_gail_reward.py [--seeds 0 1 2 3 4] [--steps 24576]``.

The toy (pure GAIL: no extrinsic reward, no BC): a point starts at x in [0, 0.05] and moves by
``0.1 a0`` per step; ``a1 > 0.5`` aborts the episode at once (a "collision" that is always
within reach), x < -0.3 ends it too, x >= 3 is the goal (30 full steps), 100 steps truncate.
The observation is ``(x, t / 100)``. The expert walks to the goal at full speed and never
aborts. Three rewards are trained with the same PPO, seeds and budget:

* ``absorbing``: this project's (``-log(1 - D) - r_abs``, DAC; :mod:`cgail_learning.gail`);
* ``standard``: ML-Agents' ``-log(1 - D)`` (never negative: going on always pays);
* ``shifted``: ``-log(1 - D) - log 2``, this project's until 2026-12 (negative wherever the
  discriminator tells the policy apart: ending pays).

Prints, per form, the deterministic policy's success and episode length over 20 episodes for
each seed, and the training episodes' success and length at the end, as a markdown table. An
expert episode is 30 steps. PPO on 24k steps of a toy is noisy from seed to seed: read the
table across seeds.
"""

from __future__ import annotations

import argparse
import math
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import numpy as np
import torch

from cgail_learning.config import config_from_dict
from cgail_learning.envs import SyncVecEnv
from cgail_learning.trainer import evaluate_policy, Trainer

GOAL, WALL, LIMIT = 3.0, 0.3, 100


class AbortCorridor(gym.Env):
    """The corridor of the module docstring."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-4.0, 4.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.theta_max = 1.0
        self.x, self.t = 0.0, 0

    def set_theta_max(self, theta_max: float) -> None:
        """(The trainer's curriculum hook; unused.)"""

    def _obs(self) -> np.ndarray:
        return np.array([self.x, self.t / LIMIT], np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.x, self.t = float(self.np_random.uniform(0.0, 0.05)), 0
        return self._obs(), {}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.x += 0.1 * float(a[0])
        self.t += 1
        if a[1] > 0.5 or self.x < -WALL:
            return self._obs(), 0.0, True, False, {'is_success': False}
        if self.x >= GOAL:
            return self._obs(), 0.0, True, False, {'is_success': True}
        return self._obs(), 0.0, False, self.t >= LIMIT, {'is_success': False}


def expert_demos(episodes: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """(obs, act) of the expert: full speed ahead, never abort."""
    env, obs_l, act_l = AbortCorridor(), [], []
    for k in range(episodes):
        obs, _ = env.reset(seed=k)
        while True:
            obs_l.append(obs)
            act_l.append([1.0, -1.0])
            obs, _, te, tr, _ = env.step([1.0, -1.0])
            if te or tr:
                break
    return np.asarray(obs_l, np.float32), np.asarray(act_l, np.float32)


def run(form: str, seed: int, steps: int) -> dict[str, float]:
    """Train pure GAIL with one reward form; return the final statistics."""
    torch.set_num_threads(1)
    cfg = config_from_dict({
        'name': f'corridor_{form}', 'max_steps': steps, 'num_envs': 8,
        'network': {'hidden_units': 32, 'init_log_std': 0.0},
        'ppo': {'learning_rate': 1e-3, 'batch_size': 256, 'buffer_size': 1024,
                'schedule': 'constant'},
        'extrinsic': {'strength': 0.0}, 'gail': {'strength': 1.0, 'hidden_units': 32},
        'bc': {'strength': 0.0}, 'curiosity': {'strength': 0.0}, 'curriculum': {}})
    obs, act = expert_demos()
    trainer = Trainer(cfg, SyncVecEnv([AbortCorridor] * cfg.num_envs), demo_obs=obs,
                      demo_act=act, seed=seed, demo_episodes=20)
    gail = trainer.gail
    assert gail is not None
    if form != 'absorbing':  # the closed forms: a constant in place of the learned r_abs
        shift = np.float32(math.log(2.0) if form == 'shifted' else 0.0)
        gail.step_reward = lambda o, a, r_abs=None: gail.reward(o, a) - shift  # type: ignore[assignment,method-assign]
    scalars: dict[str, float] = {}
    while trainer.step < steps:
        scalars = trainer.train_iteration()
    ev = evaluate_policy(trainer.act_deterministic, AbortCorridor(), 20, seed=500)
    return {'success': ev['eval/success_rate'], 'length': ev['eval/episode_length'],
            'train_success': scalars.get('environment/success_rate', math.nan),
            'train_length': scalars.get('environment/episode_length', math.nan)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2, 3, 4])
    p.add_argument('--steps', type=int, default=24_576)
    args = p.parse_args()
    print(f'pure GAIL on the abort corridor, {args.steps} steps per run; expert episode 30 steps')
    print('| reward | ' + ' | '.join(f'seed {s}' for s in args.seeds)
          + ' | successful seeds | mean length |')
    print('|---|' + '---|' * (len(args.seeds) + 2))
    for form in ('absorbing', 'standard', 'shifted'):
        res = [run(form, s, args.steps) for s in args.seeds]
        cells = [f"{100 * r['success']:.0f}% / {r['length']:.0f} st (train "
                 f"{100 * r['train_success']:.0f}%, {r['train_length']:.0f} st)" for r in res]
        ok = sum(r['success'] >= 0.9 for r in res)
        print(f'| {form} | ' + ' | '.join(cells)
              + f" | {ok}/{len(res)} | {np.mean([r['length'] for r in res]):.0f} |", flush=True)


if __name__ == '__main__':
    main()

"""Test helpers of the learning tests (like ``numpy.testing``): tests only.

A tiny 2-D point-reaching gymnasium env (:class:`PointReach`) and its scripted expert
(:func:`expert_action`, :func:`expert_demos`), on which the learners are checked quickly
(``from cgail_learning.testing import PointReach``).

Test code (test/test_package_deps.py): its imports may be ``<test_depend>`` s of this package,
and no product module imports it (test/test_import_layers.py).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np


class PointReach(gym.Env):
    """A point in [-1, 1]^2 moves by 0.1 * action per step towards a random goal.

    Observation: [x, y, gx - x, gy - y]. Reward: +1 and success when within 0.1 of the goal,
    -1 when leaving the box, else 0.1 * (distance decrease). Truncated after 40 steps.
    """

    metadata: dict[str, Any] = {'render_modes': []}  # noqa: RUF012

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-4.0, 4.0, (4,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.theta_max = 1.0
        self._p = np.zeros(2)
        self._g = np.zeros(2)
        self._t = 0

    def set_theta_max(self, theta_max: float) -> None:
        self.theta_max = theta_max

    def _obs(self) -> np.ndarray:
        return np.concatenate([self._p, self._g - self._p]).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._p = self.np_random.uniform(-0.5, 0.5, 2)
        ang = self.np_random.uniform(0, 2 * np.pi)
        self._g = self._p + 0.6 * np.array([np.cos(ang), np.sin(ang)])
        self._g = np.clip(self._g, -0.9, 0.9)
        self._t = 0
        return self._obs(), {}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1, 1)
        d0 = np.linalg.norm(self._g - self._p)
        self._p = self._p + 0.1 * a
        self._t += 1
        d1 = np.linalg.norm(self._g - self._p)
        if np.any(np.abs(self._p) > 1):
            return self._obs(), -1.0, True, False, {'is_success': False}
        if d1 < 0.1:
            return self._obs(), 1.0, True, False, {'is_success': True}
        return self._obs(), 0.1 * (d0 - d1), False, self._t >= 40, {'is_success': False}


def expert_action(obs: np.ndarray) -> np.ndarray:
    """Head straight for the goal at full speed."""
    d = obs[2:4]
    return np.clip(d / max(np.linalg.norm(d), 1e-9), -1, 1).astype(np.float32)


def expert_demos(n_episodes: int = 20, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(obs, act) arrays of expert episodes."""
    env = PointReach()
    obs_l, act_l = [], []
    for k in range(n_episodes):
        obs, _ = env.reset(seed=seed + k)
        while True:
            a = expert_action(obs)
            obs_l.append(obs)
            act_l.append(a)
            obs, _, te, tr, _ = env.step(a)
            if te or tr:
                break
    return np.stack(obs_l), np.stack(act_l)

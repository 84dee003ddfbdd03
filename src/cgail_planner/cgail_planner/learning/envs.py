"""The batched-environment protocol the trainer uses, and a synchronous adapter for gym envs.

The trainer needs ``step`` with *same-step* auto-reset: when env i ends at step t, ``obs[i]`` is
already the first observation of its next episode and ``infos[i]['final_obs']`` holds the last
observation of the ended one (used to bootstrap truncated episodes).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

import gymnasium as gym
import numpy as np

StepResult = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]


class VecEnv(Protocol):
    """What the trainer needs from a batched environment."""

    num_envs: int
    single_observation_space: gym.spaces.Box
    single_action_space: gym.spaces.Box

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset every env; env i is seeded ``seed + i``. Returns (N, obs_dim) float32."""
        ...

    def step(self, actions: np.ndarray) -> StepResult:
        """Step all envs with (N, act_dim) actions in [-1, 1]; same-step auto-reset."""
        ...

    def set_theta_max(self, theta_max: float) -> None:
        """Set the maximum bending angle (rad) of every env (curriculum)."""
        ...


def is_success(info: dict[str, Any]) -> bool:
    """Success flag of a final-step info dict (``is_success``, gymnasium's convention)."""
    return bool(info.get('is_success', info.get('success', False)))


class SyncVecEnv:
    """Runs N gymnasium envs one after the other in this process, with same-step auto-reset."""

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]]) -> None:
        if not env_fns:
            raise ValueError('env_fns must hold at least one env factory, found none')
        self.envs = [fn() for fn in env_fns]
        self.num_envs = len(self.envs)
        obs_space = self.envs[0].observation_space
        act_space = self.envs[0].action_space
        if not isinstance(obs_space, gym.spaces.Box) or not isinstance(act_space, gym.spaces.Box):
            raise ValueError(f'expected Box observation and action spaces, found {obs_space} '
                             f'and {act_space}')
        self.single_observation_space = obs_space
        self.single_action_space = act_space

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset all envs (env i gets ``seed + i`` when a seed is given)."""
        obs = [env.reset(seed=None if seed is None else seed + i)[0]
               for i, env in enumerate(self.envs)]
        return np.stack(obs).astype(np.float32)

    def step(self, actions: np.ndarray) -> StepResult:
        """Step every env; an ended env is reset at once and reports ``final_obs``."""
        n = self.num_envs
        obs_out = np.zeros((n, *self.single_observation_space.shape), np.float32)
        rew = np.zeros(n, np.float32)
        term = np.zeros(n, bool)
        trunc = np.zeros(n, bool)
        infos: list[dict[str, Any]] = []
        for i, env in enumerate(self.envs):
            o, r, te, tr, info = env.step(actions[i])
            info = dict(info)
            if te or tr:
                info['final_obs'] = np.asarray(o, np.float32)
                o, _ = env.reset()
            obs_out[i], rew[i], term[i], trunc[i] = o, r, te, tr
            infos.append(info)
        return obs_out, rew, term, trunc, infos

    def set_theta_max(self, theta_max: float) -> None:
        """Forward to every env that supports it (the catheter simulator does)."""
        for env in self.envs:
            fn = getattr(env.unwrapped, 'set_theta_max', None)
            if fn is not None:
                fn(theta_max)

    def close(self) -> None:
        """Close every env."""
        for env in self.envs:
            env.close()


class ConcatVecEnv:
    """Several batched envs stepped as one: env ``i`` of the whole is env ``i - offset`` of its
    part, in order. Used to train over several target sets of one anatomy at once (one
    :class:`~cgail_planner.sim.vec_env.CatheterNavVecEnv` per scenario seed).

    ``reset(seed)`` seeds the whole's env ``i`` with ``seed + i``, as one batched env would.
    """

    def __init__(self, parts: Sequence[Any]) -> None:
        if not parts:
            raise ValueError('parts must hold at least one batched env, found none')
        self.parts = list(parts)
        first = self.parts[0]
        for p in self.parts[1:]:
            if (p.single_observation_space.shape != first.single_observation_space.shape
                    or p.single_action_space.shape != first.single_action_space.shape):
                raise ValueError('expected parts with equal observation and action spaces, '
                                 f'found {first.single_observation_space} and '
                                 f'{p.single_observation_space}')
        self.single_observation_space = first.single_observation_space
        self.single_action_space = first.single_action_space
        self._bounds = np.cumsum([0] + [p.num_envs for p in self.parts])
        self.num_envs = int(self._bounds[-1])

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset every part (the whole's env i gets ``seed + i``)."""
        return np.concatenate([
            p.reset(seed=None if seed is None else seed + int(lo))
            for p, lo in zip(self.parts, self._bounds[:-1], strict=False)]).astype(np.float32)

    def step(self, actions: np.ndarray) -> StepResult:
        """Step every part with its slice of ``actions``."""
        outs = [p.step(actions[lo:hi]) for p, lo, hi in
                zip(self.parts, self._bounds[:-1], self._bounds[1:], strict=True)]
        infos: list[dict[str, Any]] = [i for o in outs for i in o[4]]
        return (np.concatenate([o[0] for o in outs]).astype(np.float32),
                np.concatenate([o[1] for o in outs]).astype(np.float32),
                np.concatenate([o[2] for o in outs]), np.concatenate([o[3] for o in outs]),
                infos)

    def set_theta_max(self, theta_max: float) -> None:
        """Set theta_max of every part."""
        for p in self.parts:
            p.set_theta_max(theta_max)

    def close(self) -> None:
        """Close every part."""
        for p in self.parts:
            getattr(p, 'close', lambda: None)()

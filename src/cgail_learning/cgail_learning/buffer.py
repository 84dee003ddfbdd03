"""Rollout storage and per-signal generalised advantage estimation (numpy only)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import NamedTuple

import numpy as np


def compute_gae(rewards: np.ndarray, values: np.ndarray, next_values: np.ndarray,
                terminated: np.ndarray, ended: np.ndarray, gamma: float,
                lam: float) -> tuple[np.ndarray, np.ndarray]:
    """GAE(gamma, lambda) for one reward signal over a (T, N) rollout.

    Args:
        rewards: (T, N) rewards of this signal (already scaled by its strength).
        values: (T, N) V(s_t) from this signal's value head.
        next_values: (T, N) V(s_{t+1}); for a truncated step the value of the final observation.
        terminated: (T, N) true terminal (no bootstrap: next value counts as 0).
        ended: (T, N) episode ended at t (terminated or truncated): the advantage recursion
            does not cross it.
        gamma: discount of this signal.
        lam: GAE lambda.

    Returns:
        advantages (T, N) and returns = advantages + values (the value targets).
    """
    T = rewards.shape[0]
    adv = np.zeros_like(rewards, dtype=np.float64)
    last = np.zeros(rewards.shape[1:], dtype=np.float64)
    not_term = 1.0 - terminated.astype(np.float64)
    not_end = 1.0 - ended.astype(np.float64)
    for t in reversed(range(T)):
        delta = rewards[t] + gamma * not_term[t] * next_values[t] - values[t]
        last = delta + gamma * lam * not_end[t] * last
        adv[t] = last
    return adv.astype(np.float32), (adv + values).astype(np.float32)


class Batch(NamedTuple):
    """A minibatch of flattened transitions (numpy arrays)."""

    obs: np.ndarray
    act: np.ndarray
    next_obs: np.ndarray
    logp: np.ndarray
    advantages: np.ndarray
    returns: dict[str, np.ndarray]
    old_values: dict[str, np.ndarray]
    terminated: np.ndarray
    """Whether each transition terminated (its next state is GAIL's absorbing state)."""


class RolloutBuffer:
    """Fixed-size (T, N) rollout of a batched environment with one reward row per signal."""

    def __init__(self, steps: int, num_envs: int, obs_dim: int, act_dim: int,
                 signals: Sequence[str]) -> None:
        self.T, self.N = steps, num_envs
        self.signals = list(signals)
        self.obs = np.zeros((steps, num_envs, obs_dim), np.float32)
        self.next_obs = np.zeros((steps, num_envs, obs_dim), np.float32)
        self.act = np.zeros((steps, num_envs, act_dim), np.float32)
        self.logp = np.zeros((steps, num_envs), np.float32)
        self.env_rewards = np.zeros((steps, num_envs), np.float32)
        self.terminated = np.zeros((steps, num_envs), bool)
        self.ended = np.zeros((steps, num_envs), bool)
        self.rewards = {s: np.zeros((steps, num_envs), np.float32) for s in self.signals}
        self.values = {s: np.zeros((steps, num_envs), np.float32) for s in self.signals}
        self.next_values = {s: np.zeros((steps, num_envs), np.float32) for s in self.signals}
        self.advantages = np.zeros((steps, num_envs), np.float32)
        self.returns = {s: np.zeros((steps, num_envs), np.float32) for s in self.signals}
        self.pos = 0

    @property
    def full(self) -> bool:
        """Whether all T steps are filled."""
        return self.pos >= self.T

    def add(self, obs: np.ndarray, act: np.ndarray, logp: np.ndarray, env_reward: np.ndarray,
            next_obs: np.ndarray, terminated: np.ndarray, ended: np.ndarray,
            values: dict[str, np.ndarray]) -> None:
        """Store one batched step. ``next_obs`` is the final observation where an episode ended."""
        t = self.pos
        self.obs[t], self.act[t], self.logp[t] = obs, act, logp
        self.env_rewards[t] = env_reward
        self.next_obs[t] = next_obs
        self.terminated[t], self.ended[t] = terminated, ended
        for s in self.signals:
            self.values[s][t] = values[s]
        self.pos += 1

    def finish(self, gammas: dict[str, float], lam: float) -> None:
        """Per-signal GAE, mean over signals, normalised over the buffer (ML-Agents)."""
        advs = []
        for s in self.signals:
            a, r = compute_gae(self.rewards[s], self.values[s], self.next_values[s],
                               self.terminated, self.ended, gammas[s], lam)
            self.returns[s] = r
            advs.append(a)
        mean_adv = np.mean(np.stack(advs), axis=0)
        self.advantages = ((mean_adv - mean_adv.mean()) / (mean_adv.std() + 1e-10)).astype(
            np.float32)

    def minibatches(self, batch_size: int, rng: np.random.Generator) -> Iterator[Batch]:
        """One shuffled pass over the flattened buffer in minibatches of ``batch_size``."""
        n = self.T * self.N
        idx = rng.permutation(n)

        def flat(x: np.ndarray) -> np.ndarray:
            return x.reshape(n, *x.shape[2:])

        obs, act, nobs, logp = flat(self.obs), flat(self.act), flat(self.next_obs), \
            flat(self.logp)
        adv, term = flat(self.advantages), flat(self.terminated)
        rets = {s: flat(v) for s, v in self.returns.items()}
        vals = {s: flat(v) for s, v in self.values.items()}
        for start in range(0, n - batch_size + 1, batch_size):
            b = idx[start:start + batch_size]
            yield Batch(obs[b], act[b], nobs[b], logp[b], adv[b],
                        {s: r[b] for s, r in rets.items()}, {s: v[b] for s, v in vals.items()},
                        term[b])

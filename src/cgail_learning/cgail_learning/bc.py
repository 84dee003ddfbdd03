"""Behavioural cloning step on the demonstrations (ML-Agents ``behavioral_cloning``).

Two schedules (:attr:`~cgail_learning.config.BCConfig.schedule`): ``ours``, where the learning
rate is the policy's current one times the decaying strength and each pass takes at most
``ppo.buffer_size`` demo samples, and ``ml-agents``, the schedule of ML-Agents' ``BCModule``
that the authors trained with: ``strength`` x the initial policy learning rate, decayed once,
linearly to 1e-10 over ``bc.steps``, each pass over the whole demo buffer. ML-Agents computes
an update's decayed rate before its passes and applies it after them (the passes run at the
previous update's rate); here an update runs at its own step's rate, one update (10,240 of
8,000,000 steps) earlier on the same line.
"""

from __future__ import annotations

import numpy as np
import torch

from cgail_learning.config import BCConfig
from cgail_learning.networks import Actor
from cgail_learning.ppo import linear_schedule


def bc_loss(actor: Actor, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    """Mean squared error between the deterministic policy action and the expert action.

    Expert actions are in the env's [-1, 1]^3 action space; the deterministic action is the
    clipped Gaussian mean, exactly what the exported policy outputs.
    """
    return ((actor.deterministic(obs) - act) ** 2).sum(-1).mean()


def bc_passes(actor: Actor, obs: torch.Tensor, act: torch.Tensor, opt: torch.optim.Optimizer,
              epochs: int, batch_size: int, rng: np.random.Generator,
              max_samples: int | None = None) -> list[float]:
    """``epochs`` shuffled passes of :func:`bc_loss` steps over (at most ``max_samples`` of)
    the demonstrations; returns each pass's mean loss."""
    n = obs.shape[0]
    means = []
    for _ in range(epochs):
        idx = rng.permutation(n)[:max_samples]
        bs = min(batch_size, len(idx))
        losses = []
        for start in range(0, len(idx) - bs + 1, bs):
            b = torch.as_tensor(idx[start:start + bs])
            loss = bc_loss(actor, obs[b], act[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
        means.append(float(np.mean(losses)))
    return means


#: ML-Agents' floor of the decayed BC learning rate (``DecayedValue(..., 1e-10, steps)``).
MLAGENTS_BC_LR_FLOOR = 1e-10


class BehavioralCloning:
    """Supervised pass over the demos after each PPO update (module docstring for the
    learning rate of each :attr:`~cgail_learning.config.BCConfig.schedule`)."""

    def __init__(self, actor: Actor, demo_obs: np.ndarray, demo_act: np.ndarray,
                 cfg: BCConfig, learning_rate: float) -> None:
        self.actor, self.cfg = actor, cfg
        self.obs = torch.as_tensor(demo_obs, dtype=torch.float32)
        self.act = torch.as_tensor(demo_act, dtype=torch.float32)
        self.base_lr = learning_rate
        self.opt = torch.optim.Adam(actor.parameters(), lr=learning_rate * cfg.strength)

    def strength(self, step: int) -> float:
        """BC strength at ``step`` (linear decay to 0 over cfg.steps; constant if steps == 0)."""
        if self.cfg.steps == 0:
            return self.cfg.strength
        return self.cfg.strength * max(0.0, 1.0 - step / self.cfg.steps)

    def learning_rate(self, step: int, policy_lr: float) -> float:
        """The BC learning rate at ``step``: ``ours``, ``policy_lr`` (the policy's current
        rate) times :meth:`strength`; ``ml-agents``, ``strength`` x the initial policy rate,
        linear to 1e-10 over ``steps`` (constant when 0), as ML-Agents' ``BCModule``."""
        if self.cfg.schedule == 'ours':
            return policy_lr * self.strength(step)
        return linear_schedule(self.cfg.strength * self.base_lr, MLAGENTS_BC_LR_FLOOR, step,
                               self.cfg.steps, 'linear' if self.cfg.steps else 'constant')

    def update(self, step: int, policy_lr: float, max_samples: int,
               rng: np.random.Generator) -> dict[str, float]:
        """``num_epoch`` passes over (at most ``max_samples``; ``ml-agents``: all) shuffled demo
        samples."""
        lr = self.learning_rate(step, policy_lr)
        if lr <= 0:
            return {}
        if self.cfg.schedule == 'ml-agents':
            max_samples = self.obs.shape[0]
        for g in self.opt.param_groups:
            g['lr'] = lr
        losses = bc_passes(self.actor, self.obs, self.act, self.opt, self.cfg.num_epoch,
                           self.cfg.batch_size, rng, max_samples)
        return {'losses/bc_loss': float(np.mean(losses)), 'policy/bc_learning_rate': lr}

"""GAIL discriminator with gradient penalty, and an absorbing state for episode ends (DAC).

Why an absorbing state
----------------------
Our episodes end on success, on a non-minor collision, on exit (*termination*) or at the step
limit (*truncation*, bootstrapped). How a GAIL reward treats termination decides what ending
an episode is worth, and both closed forms get it wrong:

* ML-Agents' ``r = -log(1 - D(s))`` is never negative, so every extra step earns reward and
  termination forfeits it: a policy prefers not to end, the target included. On a 1-D corridor
  toy (pure GAIL, the expert walks to the goal; ``test_learning_smoke``) the policy learns to
  dawdle until the step limit: 0% success.
* The shifted ``-log(1 - D) - log 2`` (this module until 2026-12) is negative wherever the
  discriminator can tell the policy from the expert (D < 1/2), which is most of training, so
  ending the episode early, by a collision, is paid: an independent cross-check (``imitation``
  GAIL on the same env, issue 13) found our GAIL preset collapsing to ~46-step collision
  episodes at any budget.

The fix of Kostrikov et al. (DAC, ICLR 2019) makes termination a learned event rather than a
constant: a terminal transition leads to an **absorbing state** that loops to itself. The
discriminator sees it as one more input (zero observation, zero action, flag 1) and learns its
reward from how often expert and policy episodes end: the expert data holds one absorbing
sample per demonstration episode, the policy data one per terminated transition.

How it is paid. With ``r_abs = -log(1 - D(absorbing))``, every episode continues forever in
the absorbing state, so subtracting ``r_abs`` from every reward, the absorbing loop's included,
shifts every return by the same ``-r_abs / (1 - gamma)`` and changes no preference. After the
subtraction the absorbing state is worth exactly 0, so a terminal step needs no bootstrap and
the GAE stays as it is; the policy is paid ``-log(1 - D(s)) - r_abs`` per step
(:meth:`Gail.step_reward`). (Bootstrapping terminal steps with ``r_abs / (1 - gamma)`` instead
is the same optimum, but it makes a terminal step's target ~100x larger than anything the
critic has learned yet: on the corridor toy of ``bench/bench_gail_reward.py`` every policy then
learned to abort at once.) This is the shifted form with a learned shift in place of ``log 2``:
when the policy ends its episodes more often than the expert, D(absorbing) < 1/2 and the step
reward rises, so ending early stops paying; when it ends less often (dawdling), the step reward
falls and finishing pays. ``bench/bench_gail_reward.py`` compares the three forms on that toy.
Truncation is bootstrapped with the value of the last observation, as before.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional

from cgail_learning.config import GailConfig
from cgail_learning.networks import RunningNormalizer

EPS = 1e-7


class Discriminator(nn.Module):
    """D(s) or D(s, a) in (0, 1): the probability that the input comes from the expert.

    The input carries one more column, the absorbing flag: 0 for a real state, 1 (with a zero
    observation and action) for the absorbing state after a terminal transition.
    """

    def __init__(self, obs_dim: int, act_dim: int, cfg: GailConfig) -> None:
        super().__init__()
        self.use_actions = cfg.use_actions
        self.obs_dim, self.act_dim = obs_dim, act_dim
        in_dim = obs_dim + (act_dim if cfg.use_actions else 0) + 1
        self.in_dim = in_dim
        h = cfg.hidden_units
        self.net = nn.Sequential(nn.Linear(in_dim, h), nn.SiLU(), nn.Linear(h, h), nn.SiLU(),
                                 nn.Linear(h, 1))
        self.normalizer = RunningNormalizer(in_dim - 1, clip=math.inf) \
            if cfg.own_normalizer else None

    def observe(self, obs: torch.Tensor, act: torch.Tensor | None) -> None:
        """Fold a training batch into the input statistics (``gail.own_normalizer``)."""
        if self.normalizer is not None:
            assert act is not None or not self.use_actions
            x = torch.cat([obs, act], dim=-1) if act is not None and self.use_actions else obs
            self.normalizer.update(x.detach().numpy())

    def inputs(self, obs: torch.Tensor, act: torch.Tensor | None,
               absorbing: int = 0) -> torch.Tensor:
        """Prepared inputs: (s[, a], 0) for the B real states, then ``absorbing`` rows of the
        absorbing state (0[, 0], 1)."""
        parts = [obs]
        if self.use_actions:
            assert act is not None
            parts.append(act)
        x = torch.cat(parts, dim=-1)
        if self.normalizer is not None:
            x = self.normalizer(x)
        x = torch.cat([x, torch.zeros(obs.shape[0], 1, dtype=obs.dtype)], dim=-1)
        if absorbing:
            x = torch.cat([x, self.absorbing_input(absorbing, obs.dtype)])
        return x

    def absorbing_input(self, n: int = 1, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(n, in_dim) rows of the absorbing state."""
        x = torch.zeros(n, self.in_dim, dtype=dtype)
        x[:, -1] = 1.0
        return x

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        """Logit of D for prepared inputs (B, in_dim)."""
        return self.net(x).squeeze(-1)


def gail_reward(d: torch.Tensor | np.ndarray) -> np.ndarray:
    """GAIL reward ``-log(1 - D)`` for discriminator outputs D (>= 0; module docstring)."""
    d_np = np.asarray(d.detach().cpu().numpy() if isinstance(d, torch.Tensor) else d,
                      dtype=np.float64)
    return (-np.log(np.clip(1.0 - d_np, EPS, 1.0))).astype(np.float32)


def gradient_penalty(disc: Discriminator, expert_x: torch.Tensor,
                     policy_x: torch.Tensor, generator: torch.Generator | None = None
                     ) -> torch.Tensor:
    """``mean((||grad_x logit D(x_hat)||_2 - 1)^2)`` on random expert/policy interpolates.

    The WGAN-GP form used by DAC (Kostrikov et al. 2019) for GAIL, on the discriminator logit.
    ML-Agents applies it to the sigmoid output with weight 10; measured on a toy problem that
    variant cannot separate expert from policy (a sigmoid's slope is at most 1/4, so a unit
    gradient norm forces a steep, saturating D), hence the logit form and weight 1.0 here.
    """
    alpha = torch.rand(expert_x.shape[0], 1, generator=generator)
    x_hat = (alpha * expert_x + (1 - alpha) * policy_x).requires_grad_(True)
    d = disc.logits(x_hat)
    (grad,) = torch.autograd.grad(d.sum(), x_hat, create_graph=True)
    return ((grad.norm(2, dim=1) - 1.0) ** 2).mean()


class Gail:
    """Discriminator, its optimiser, its loss, and the reward it gives the policy."""

    def __init__(self, obs_dim: int, act_dim: int, cfg: GailConfig) -> None:
        self.cfg = cfg
        self.disc = Discriminator(obs_dim, act_dim, cfg)
        self.opt = torch.optim.Adam(self.disc.parameters(), lr=cfg.learning_rate)

    def loss(self, expert_obs: torch.Tensor, expert_act: torch.Tensor | None,
             policy_obs: torch.Tensor, policy_act: torch.Tensor | None,
             expert_absorbing: int = 0, policy_absorbing: int = 0
             ) -> tuple[torch.Tensor, dict[str, float]]:
        """BCE (expert -> 1, policy -> 0; each side's mean) plus the weighted gradient penalty.

        ``expert_absorbing`` / ``policy_absorbing`` absorbing-state rows join each side.
        """
        ex = self.disc.inputs(expert_obs, expert_act, expert_absorbing)
        px = self.disc.inputs(policy_obs, policy_act, policy_absorbing)
        le, lp = self.disc.logits(ex), self.disc.logits(px)
        bce = (functional.binary_cross_entropy_with_logits(le, torch.ones_like(le))
               + functional.binary_cross_entropy_with_logits(lp, torch.zeros_like(lp)))
        n = min(len(ex), len(px))  # (interpolates pair the first n rows of each side)
        gp = gradient_penalty(self.disc, ex[:n].detach(), px[:n].detach())
        total = bce + self.cfg.gradient_penalty * gp
        return total, {'losses/gail_loss': bce.item(), 'losses/gail_grad_penalty': gp.item(),
                       'policy/gail_expert_estimate': torch.sigmoid(le).mean().item(),
                       'policy/gail_policy_estimate': torch.sigmoid(lp).mean().item()}

    def update(self, expert_obs: torch.Tensor, expert_act: torch.Tensor | None,
               policy_obs: torch.Tensor, policy_act: torch.Tensor | None,
               expert_absorbing: int = 0, policy_absorbing: int = 0) -> dict[str, float]:
        """One discriminator gradient step (see :meth:`loss`); with its own normaliser, both
        batches join its statistics first (``imitation``'s ``RunningNorm`` in training mode)."""
        if self.disc.normalizer is not None:
            both_act = None if expert_act is None or policy_act is None \
                else torch.cat([expert_act, policy_act])
            self.disc.observe(torch.cat([expert_obs, policy_obs]), both_act)
        loss, stats = self.loss(expert_obs, expert_act, policy_obs, policy_act,
                                expert_absorbing, policy_absorbing)
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        return stats

    @torch.no_grad()
    def reward(self, obs: torch.Tensor, act: torch.Tensor | None) -> np.ndarray:
        """Unscaled reward ``-log(1 - D)`` for (B, obs_dim) normalised observations."""
        d = torch.sigmoid(self.disc.logits(self.disc.inputs(obs, act)))
        return gail_reward(d)

    @torch.no_grad()
    def absorbing_reward(self) -> float:
        """Unscaled reward of the absorbing state."""
        d = torch.sigmoid(self.disc.logits(self.disc.absorbing_input()))
        return float(gail_reward(d)[0])

    def step_reward(self, obs: torch.Tensor, act: torch.Tensor | None,
                    r_abs: float | None = None) -> np.ndarray:
        """What the policy is paid per step: :meth:`reward` minus :meth:`absorbing_reward`
        (``r_abs`` when the caller has it; module docstring: DAC's absorbing state with its
        reward moved into every step)."""
        return self.reward(obs, act) - np.float32(
            self.absorbing_reward() if r_abs is None else r_abs)

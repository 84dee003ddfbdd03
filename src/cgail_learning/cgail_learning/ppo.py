"""PPO losses (clipped surrogate, clipped per-signal value loss, entropy) and schedules."""

from __future__ import annotations

from typing import NamedTuple

import torch

from cgail_learning.networks import Actor, Critic


def linear_schedule(initial: float, floor: float, step: int, max_steps: int,
                    kind: str = 'linear') -> float:
    """ML-Agents' ``DecayedValue``: linear from ``initial`` to ``floor`` over max_steps."""
    if kind == 'constant':
        return initial
    frac = min(max(step / max_steps, 0.0), 1.0)
    return initial + (floor - initial) * frac


def clipped_surrogate(logp: torch.Tensor, old_logp: torch.Tensor, advantages: torch.Tensor,
                      epsilon: float) -> torch.Tensor:
    """PPO policy loss ``-mean(min(r A, clip(r, 1-eps, 1+eps) A))``, ``r = exp(logp - old)``."""
    ratio = torch.exp(logp - old_logp)
    unclipped = ratio * advantages
    clipped = torch.clamp(ratio, 1.0 - epsilon, 1.0 + epsilon) * advantages
    return -torch.min(unclipped, clipped).mean()


def clipped_value_loss(values: torch.Tensor, old_values: torch.Tensor, returns: torch.Tensor,
                       epsilon: float | None) -> torch.Tensor:
    """ML-Agents value loss: ``mean(max((R - V)^2, (R - V_clip)^2))``; ``epsilon`` None: the
    plain ``mean((R - V)^2)`` (stable-baselines3's default)."""
    if epsilon is None:
        return ((returns - values) ** 2).mean()
    v_clip = old_values + torch.clamp(values - old_values, -epsilon, epsilon)
    return torch.max((returns - values) ** 2, (returns - v_clip) ** 2).mean()


class PPOStats(NamedTuple):
    """Scalars of one PPO minibatch step."""

    policy_loss: float
    value_loss: float
    entropy: float
    approx_kl: float
    clip_fraction: float


def ppo_loss(actor: Actor, critic: Critic, obs: torch.Tensor, act: torch.Tensor,
             old_logp: torch.Tensor, advantages: torch.Tensor,
             returns: dict[str, torch.Tensor], old_values: dict[str, torch.Tensor],
             epsilon: float, beta: float, value_coef: float, clip_value: bool = True,
             normalize_advantages: bool = False) -> tuple[torch.Tensor, PPOStats]:
    """Total loss ``L_clip + value_coef * mean_signals(L_value) - beta * entropy``.

    ``clip_value`` False: the value loss is not clipped; ``normalize_advantages``: the
    minibatch's advantages are normalised first (``PPOConfig.clip_value_loss`` and
    ``advantage_normalization``)."""
    if normalize_advantages and len(advantages) > 1:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    dist = actor.distribution(obs)
    logp = dist.log_prob(act).sum(-1)
    entropy = dist.entropy().sum(-1).mean()
    policy_loss = clipped_surrogate(logp, old_logp, advantages, epsilon)
    values = critic(obs)
    v_eps = epsilon if clip_value else None
    value_loss = torch.stack([clipped_value_loss(values[s], old_values[s], returns[s], v_eps)
                              for s in returns]).mean()
    loss = policy_loss + value_coef * value_loss - beta * entropy
    with torch.no_grad():
        log_ratio = logp - old_logp
        kl = ((log_ratio.exp() - 1) - log_ratio).mean().item()
        clip_frac = ((log_ratio.exp() - 1).abs() > epsilon).float().mean().item()
    return loss, PPOStats(policy_loss.item(), value_loss.item(), entropy.item(), kl, clip_frac)

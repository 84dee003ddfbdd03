"""Policy, value heads and the running observation normaliser."""

from __future__ import annotations

from collections.abc import Sequence
import math

import numpy as np
import torch
from torch import nn

from cgail_learning.config import NetworkConfig

LOG_STD_MIN = -5.0
LOG_STD_MAX = 2.0


def activation(name: str) -> nn.Module:
    """Hidden-layer activation by name (``swish`` = SiLU, as in ML-Agents)."""
    return {'swish': nn.SiLU, 'tanh': nn.Tanh, 'relu': nn.ReLU}[name]()


def mlp(in_dim: int, hidden: int, layers: int, act: str) -> nn.Sequential:
    """``layers`` hidden layers of ``hidden`` units, orthogonal-ish default init."""
    mods: list[nn.Module] = []
    d = in_dim
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), activation(act)]
        d = hidden
    return nn.Sequential(*mods)


def orthogonal_(module: nn.Module, gain: float) -> None:
    """Orthogonal weights with ``gain`` and zero biases for every linear layer of ``module``
    (stable-baselines3's ``ortho_init``; ``NetworkConfig.orthogonal_init``)."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.orthogonal_(m.weight, gain=gain)
            nn.init.zeros_(m.bias)


class RunningNormalizer(nn.Module):
    """Running mean / variance of observations (Chan's parallel update), clipped to +-5 sigma.

    The statistics are buffers, so they are saved in checkpoints and baked into the ONNX graph.
    """

    mean: torch.Tensor
    var: torch.Tensor
    count: torch.Tensor

    def __init__(self, dim: int, clip: float = 5.0) -> None:
        super().__init__()
        self.register_buffer('mean', torch.zeros(dim, dtype=torch.float64))
        self.register_buffer('var', torch.ones(dim, dtype=torch.float64))
        self.register_buffer('count', torch.tensor(1e-4, dtype=torch.float64))
        self.clip = clip

    def update(self, x: np.ndarray) -> None:
        """Fold a batch (B, dim) of raw observations into the statistics."""
        batch = torch.as_tensor(np.asarray(x, dtype=np.float64).reshape(-1, self.mean.shape[0]))
        b_mean = batch.mean(0)
        b_var = batch.var(0, unbiased=False)
        b_n = batch.shape[0]
        delta = b_mean - self.mean
        tot = self.count + b_n
        new_mean = self.mean + delta * b_n / tot
        m2 = self.var * self.count + b_var * b_n + delta.pow(2) * self.count * b_n / tot
        self.mean.copy_(new_mean)
        self.var.copy_(m2 / tot)
        self.count.copy_(tot)

    @torch.no_grad()
    def fit(self, x: np.ndarray | torch.Tensor) -> None:
        """Replace the statistics by those of a batch (B, dim) of raw observations."""
        batch = torch.as_tensor(x).to(torch.float64).reshape(-1, self.mean.shape[0])
        self.mean.copy_(batch.mean(0))
        self.var.copy_(batch.var(0, unbiased=False))
        self.count.fill_(float(batch.shape[0]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = self.mean.to(x.dtype)
        std = torch.sqrt(self.var.to(x.dtype) + 1e-8)
        return torch.clamp((x - mean) / std, -self.clip, self.clip)


class Actor(nn.Module):
    """Gaussian policy with a state-independent log-std (ML-Agents continuous actions).

    The environment receives ``clip(action, -1, 1)``; the log-probability is of the unclipped
    sample, as in ML-Agents. The deterministic policy is ``clip(mean, -1, 1)``.
    """

    def __init__(self, obs_dim: int, act_dim: int, cfg: NetworkConfig,
                 normalizer: RunningNormalizer | None) -> None:
        super().__init__()
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.normalizer = normalizer
        self.body = mlp(obs_dim, cfg.hidden_units, cfg.num_layers, cfg.activation)
        if cfg.orthogonal_init:
            orthogonal_(self.body, math.sqrt(2.0))
        self.mu = nn.Linear(cfg.hidden_units, act_dim)
        nn.init.orthogonal_(self.mu.weight, gain=0.01)
        nn.init.zeros_(self.mu.bias)
        self.log_std = nn.Parameter(torch.full((act_dim,), float(cfg.init_log_std)))

    def norm(self, obs: torch.Tensor) -> torch.Tensor:
        """Normalised observation (identity without a normaliser)."""
        return obs if self.normalizer is None else self.normalizer(obs)

    def distribution(self, obs: torch.Tensor) -> torch.distributions.Normal:
        """Action distribution for raw observations (B, obs_dim)."""
        mean = self.mu(self.body(self.norm(obs)))
        std = torch.clamp(self.log_std, LOG_STD_MIN, LOG_STD_MAX).exp().expand_as(mean)
        return torch.distributions.Normal(mean, std)

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        """Deterministic action in [-1, 1] (what is exported to ONNX)."""
        return torch.clamp(self.mu(self.body(self.norm(obs))), -1.0, 1.0)


class Critic(nn.Module):
    """Shared value trunk with one linear head per reward signal."""

    def __init__(self, obs_dim: int, signals: Sequence[str], cfg: NetworkConfig,
                 normalizer: RunningNormalizer | None) -> None:
        super().__init__()
        self.normalizer = normalizer
        self.signals = list(signals)
        self.body = mlp(obs_dim, cfg.hidden_units, cfg.num_layers, cfg.activation)
        self.heads = nn.ModuleDict({s: nn.Linear(cfg.hidden_units, 1) for s in self.signals})
        if cfg.orthogonal_init:
            orthogonal_(self.body, math.sqrt(2.0))
            orthogonal_(self.heads, 1.0)

    def forward(self, obs: torch.Tensor) -> dict[str, torch.Tensor]:
        x = obs if self.normalizer is None else self.normalizer(obs)
        h = self.body(x)
        return {s: head(h).squeeze(-1) for s, head in self.heads.items()}


class DeterministicPolicy(nn.Module):
    """Raw observation -> deterministic action; the module exported to ONNX."""

    def __init__(self, actor: Actor) -> None:
        super().__init__()
        self.actor = actor

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.actor.deterministic(obs)

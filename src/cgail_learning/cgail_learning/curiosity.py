"""Intrinsic curiosity module (Pathak et al. 2017) as in ML-Agents ``reward_signals.curiosity``."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from cgail_learning.config import CuriosityConfig


class ICM(nn.Module):
    """Encoder phi, inverse model (phi(s), phi(s')) -> a, forward model (phi(s), a) -> phi(s')."""

    def __init__(self, obs_dim: int, act_dim: int, cfg: CuriosityConfig) -> None:
        super().__init__()
        e = cfg.encoding_size
        self.encoder = nn.Sequential(nn.Linear(obs_dim, 2 * e), nn.SiLU(), nn.Linear(2 * e, e),
                                     nn.SiLU())
        self.inverse = nn.Sequential(nn.Linear(2 * e, 2 * e), nn.SiLU(), nn.Linear(2 * e, act_dim))
        self.forward_model = nn.Sequential(nn.Linear(e + act_dim, 2 * e), nn.SiLU(),
                                           nn.Linear(2 * e, e))

    def prediction_error(self, obs: torch.Tensor, act: torch.Tensor,
                         next_obs: torch.Tensor) -> torch.Tensor:
        """``0.5 * ||f(phi(s), a) - phi(s')||^2`` per sample (B,)."""
        phi, phi_next = self.encoder(obs), self.encoder(next_obs)
        pred = self.forward_model(torch.cat([phi, act], -1))
        return 0.5 * ((pred - phi_next) ** 2).sum(-1)

    def losses(self, obs: torch.Tensor, act: torch.Tensor,
               next_obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Forward loss (encoder target detached) and inverse loss (MSE on actions)."""
        phi, phi_next = self.encoder(obs), self.encoder(next_obs)
        pred = self.forward_model(torch.cat([phi, act], -1))
        fwd = 0.5 * ((pred - phi_next.detach()) ** 2).sum(-1).mean()
        inv = ((self.inverse(torch.cat([phi, phi_next], -1)) - act) ** 2).sum(-1).mean()
        return fwd, inv


def capped_reward(error: np.ndarray, strength: float) -> np.ndarray:
    """ML-Agents' cap: ``min(error, 1 / strength)``, so the scaled reward is at most 1."""
    return np.minimum(np.asarray(error, dtype=np.float32), 1.0 / strength).astype(np.float32)


class Curiosity:
    """ICM, its optimiser and its (unscaled, capped) reward."""

    def __init__(self, obs_dim: int, act_dim: int, cfg: CuriosityConfig) -> None:
        self.cfg = cfg
        self.icm = ICM(obs_dim, act_dim, cfg)
        self.opt = torch.optim.Adam(self.icm.parameters(), lr=cfg.learning_rate)
        self.updated = False

    @torch.no_grad()
    def reward(self, obs: torch.Tensor, act: torch.Tensor, next_obs: torch.Tensor) -> np.ndarray:
        """Capped forward error; 0 before the first update (ML-Agents ``_has_updated_once``)."""
        if not self.updated:
            return np.zeros(obs.shape[0], np.float32)
        err = self.icm.prediction_error(obs, act, next_obs).numpy()
        return capped_reward(err, self.cfg.strength)

    def update(self, obs: torch.Tensor, act: torch.Tensor,
               next_obs: torch.Tensor) -> dict[str, float]:
        """One gradient step on ``w * L_forward + (1 - w) * L_inverse``."""
        fwd, inv = self.icm.losses(obs, act, torch.clamp(next_obs, -5, 5))
        w = self.cfg.forward_weight
        loss = w * fwd + (1 - w) * inv
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        self.updated = True
        return {'losses/curiosity_forward_loss': fwd.item(),
                'losses/curiosity_inverse_loss': inv.item()}

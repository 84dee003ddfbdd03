"""Training checkpoints on disk: read one back, and rebuild the policy it holds.

:meth:`cgail_learning.trainer.Trainer.save` writes a checkpoint (``best.pt``,
``final.pt``, ``round_<k>.pt``): a ``torch.save`` of the trainer's state with at least
``actor``, ``obs_dim``, ``act_dim`` and ``config``. The trainer (``--init-from``, ``--resume``),
the ONNX export (:mod:`cgail_learning.export`), ``train`` and ``refine`` read it here.
"""

from __future__ import annotations

from pathlib import Path
import pickle
from typing import Any

import torch

from cgail_learning.config import config_from_dict
from cgail_learning.errors import PolicyLoadError
from cgail_learning.networks import Actor, RunningNormalizer

__all__ = ['actor_from_checkpoint', 'load_checkpoint']


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by
    :meth:`~cgail_learning.trainer.Trainer.save`, with clear errors."""
    if not Path(path).is_file():
        raise PolicyLoadError(f'checkpoint not found: expected a file at {path}')
    try:
        ckpt: dict[str, Any] = torch.load(path, map_location='cpu', weights_only=False)
    except (RuntimeError, EOFError, OSError, ValueError, pickle.UnpicklingError) as exc:
        raise PolicyLoadError(f'{path}: not a readable checkpoint ({exc})') from None
    for key in ('actor', 'obs_dim', 'act_dim', 'config'):
        if key not in ckpt:
            raise PolicyLoadError(f'{path}: expected key {key!r} in the checkpoint, found '
                                  f'{sorted(ckpt)}')
    return ckpt


def actor_from_checkpoint(ckpt: dict[str, Any]) -> Actor:
    """Rebuild the actor (with its normaliser) of a checkpoint, in eval mode."""
    cfg = config_from_dict(ckpt['config'])
    norm = RunningNormalizer(ckpt['obs_dim']) if ckpt.get('normalizer') is not None else None
    actor = Actor(ckpt['obs_dim'], ckpt['act_dim'], cfg.network, norm)
    actor.load_state_dict(ckpt['actor'])
    actor.eval()
    return actor

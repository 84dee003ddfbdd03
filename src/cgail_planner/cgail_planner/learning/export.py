"""``export_onnx``: the deterministic policy (normaliser baked in) as an ONNX model.

The graph maps ``obs`` (B, obs_dim) float32 raw observations to ``action`` (B, 3) float32 in
[-1, 1]. ``metadata_props`` carry JSON strings: ``observation_layout``, ``action_scaling``,
``theta_max_rad``, ``preset``, ``anatomy``, ``mode``, ``obs_dim``, ``act_dim``, ``train_steps``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
from typing import Any

import onnx
import torch

from cgail_planner.learning.errors import LearningError
from cgail_planner.learning.networks import Actor, DeterministicPolicy
from cgail_planner.learning.trainer import actor_from_checkpoint, load_checkpoint

OPSET = 17


def export_actor(actor: Actor, path: Path, metadata: dict[str, Any]) -> Path:
    """Write ``actor``'s deterministic policy to ``path`` with JSON metadata_props."""
    obs_dim = actor.obs_dim
    policy = DeterministicPolicy(actor).eval()
    path.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, obs_dim)
    torch.onnx.export(policy, (dummy,), str(path), input_names=['obs'], output_names=['action'],
                      dynamic_axes={'obs': {0: 'batch'}, 'action': {0: 'batch'}},
                      opset_version=OPSET, dynamo=False)
    model = onnx.load(str(path))
    meta = dict(metadata)
    meta.setdefault('obs_dim', obs_dim)
    meta.setdefault('act_dim', actor.act_dim)
    for key, value in meta.items():
        prop = model.metadata_props.add()
        prop.key = key
        prop.value = json.dumps(value)
    model.producer_name = 'cgail_planner.learning.export'
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def export_checkpoint(ckpt_path: Path, out: Path) -> Path:
    """Export a training checkpoint (``final.pt``) to ONNX."""
    ckpt = load_checkpoint(ckpt_path)
    actor = actor_from_checkpoint(ckpt)
    meta = dict(ckpt.get('metadata', {}))
    meta.setdefault('preset', ckpt['config'].get('name', 'custom'))
    meta['train_steps'] = int(ckpt.get('step', 0))
    return export_actor(actor, out, meta)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``export_onnx``."""
    p = argparse.ArgumentParser(prog='export_onnx', description=__doc__.split('\n')[0])
    p.add_argument('checkpoint', type=Path, help='checkpoint written by train (final.pt)')
    p.add_argument('--out', type=Path, default=None, help='output .onnx (default: next to it)')
    args = p.parse_args(argv)
    try:
        out = export_checkpoint(args.checkpoint, args.out or args.checkpoint.with_suffix('.onnx'))
    except LearningError as exc:
        print(f'export_onnx: error: {exc}', file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == '__main__':
    sys.exit(main())

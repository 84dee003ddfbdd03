"""``cgail export-onnx``: the deterministic policy (normaliser baked in) as an ONNX model.

Examples::

    cgail export-onnx runs/cgail_static/best.pt --out runs/cgail_static/policy.onnx
    cgail export-onnx old_policy.onnx --add-contract --anatomy runs/patients/p07

The graph maps ``obs`` (B, obs_dim) float32 raw observations to ``action`` (B, 3) float32 in
[-1, 1]. ``metadata_props`` carry JSON strings: ``catheter_contract`` (the whole contract the
planner builds itself from: catheter model, bend convention, retraction rule, action scaling,
observation spec with its kind, origin, scales and rays (or probes), anatomy, mode, env option
set, and training notes including the
curriculum lesson of the exported checkpoint; :class:`cgail_sim.ftl_model.
PolicyContract`), ``preset``, ``anatomy``, ``mode``, ``obs_dim``, ``act_dim``, ``train_steps``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import json
import math
from pathlib import Path
import sys
from typing import Any

import onnx
import torch

from cgail_learning.checkpoint import actor_from_checkpoint, load_checkpoint
from cgail_learning.errors import LearningError
from cgail_learning.networks import Actor, DeterministicPolicy
from cgail_sim.cli_help import tool_parser
from cgail_sim.ftl_model import CONTRACT_KEY, PolicyContract

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
    model.producer_name = 'cgail_learning.export'
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def training_notes(ckpt: dict[str, Any]) -> dict[str, Any]:
    """The contract's ``training`` entry of a checkpoint: preset, steps and curriculum, and
    ``refinement`` when :mod:`cgail_learning.refine` refined it.

    ``final_theta_max_rad`` is theta_max of the curriculum lesson the checkpoint was trained at
    (None without a curriculum); the policy still runs at the contract's ``theta_max``, the
    evaluation env's, at which the checkpoint was selected.
    """
    lessons = list(ckpt['config'].get('curriculum', {}).get('theta_max_deg', []))
    lesson = ckpt.get('curriculum_lesson')
    final = math.radians(lessons[int(lesson)]) if lessons and lesson is not None else None
    notes = {'preset': ckpt['config'].get('name', 'custom'),
             'train_steps': int(ckpt.get('step', 0)), 'curriculum_theta_max_deg': lessons,
             'curriculum_lesson': lesson, 'final_theta_max_rad': final}
    refinement = ckpt.get('metadata', {}).get('refinement')
    if refinement is not None:
        notes['refinement'] = dict(refinement)
    return notes


def export_checkpoint(ckpt_path: Path, out: Path) -> Path:
    """Export a training checkpoint (``best.pt``, ``final.pt``) to ONNX."""
    ckpt = load_checkpoint(ckpt_path)
    actor = actor_from_checkpoint(ckpt)
    meta = dict(ckpt.get('metadata', {}))
    meta.setdefault('preset', ckpt['config'].get('name', 'custom'))
    meta['train_steps'] = int(ckpt.get('step', 0))
    if CONTRACT_KEY in meta:
        contract = PolicyContract.from_dict(meta[CONTRACT_KEY])
    else:  # a checkpoint of an older train: the default model in its anatomy and mode
        contract = default_contract(str(meta.get('anatomy', 'default')),
                                    str(meta.get('mode', 'static')))
    if 'population' in meta:  # (a population run's checkpoint from before the contract said so)
        contract = replace(contract, anatomies='population')
    meta[CONTRACT_KEY] = replace(contract, training=training_notes(ckpt)).to_dict()
    for key in LEGACY_KEYS:
        meta.pop(key, None)
    return export_actor(actor, out, meta)


def actor_state_from_onnx(path: Path) -> dict[str, torch.Tensor]:
    """The actor state of a policy exported by :func:`export_actor`: the inverse of the export,
    for fine-tuning from a committed ``.onnx`` (no checkpoint is committed).

    The export keeps the actor's parameter names (``actor.body.0.weight``, ``actor.mu.bias``...)
    as initializers, and bakes the normaliser in as ``(obs - mean) / sqrt(var + 1e-8)``; both are
    read back (the normaliser's ``count`` is the model's ``train_steps``, so fine-tuning moves
    its statistics as slowly as further training would have). ``log_std`` is not exported (the
    deterministic policy has none): the caller's initial value stays.

    Raises:
        PolicyLoadError: not an ONNX model of :func:`export_actor`'s layout (names what is
            missing).
    """
    from onnx import numpy_helper

    from cgail_learning.errors import PolicyLoadError

    try:
        model = onnx.load(str(path))
    except Exception as exc:  # protobuf's DecodeError and friends: no common base class
        raise PolicyLoadError(f'{path}: not a readable ONNX model ({exc})') from None
    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    state = {k[len('actor.'):]: torch.as_tensor(v.copy()) for k, v in inits.items()
             if k.startswith('actor.') and k != 'actor.log_std'}
    if 'mu.weight' not in state:
        raise PolicyLoadError(f'{path}: expected the actor initializers of cgail export-onnx '
                              f'(actor.body.*, actor.mu.*), found {sorted(inits)}')
    nodes = {n.op_type: n for n in model.graph.node if n.op_type in ('Sub', 'Div')}
    if 'Sub' in nodes and 'Div' in nodes:  # the baked-in normaliser
        mean = inits.get(nodes['Sub'].input[1])
        std = inits.get(nodes['Div'].input[1])
        if mean is None or std is None:
            raise PolicyLoadError(f'{path}: expected the normaliser mean and std as '
                                  'initializers, found computed operands')
        meta = {p.key: p.value for p in model.metadata_props}
        count = float(json.loads(meta.get('train_steps', '1')) or 1)
        state['normalizer.mean'] = torch.as_tensor(mean.astype('float64'))
        state['normalizer.var'] = torch.as_tensor(
            (std.astype('float64') ** 2 - 1e-8).clip(min=0.0))
        state['normalizer.count'] = torch.tensor(count, dtype=torch.float64)
    return state


#: Metadata keys of exports before the contract; the contract holds what they said.
LEGACY_KEYS = ('observation_layout', 'action_scaling', 'theta_max_rad')


def default_contract(anatomy: Any, mode: str,
                     training: dict[str, Any] | None = None) -> PolicyContract:
    """The contract of the simulator's default configuration in ``anatomy`` (a built-in name,
    a prepared anatomy directory, a mesh file or an ``Anatomy``) and ``mode``; a path anatomy
    is recorded by its label and content hash
    (:func:`cgail_sim.anatomy_spec.anatomy_identity`)."""
    from cgail_sim.anatomy_spec import anatomy_identity
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import observation_spec

    cfg = EnvConfig(anatomy=anatomy, mode=mode)
    label, content_hash = anatomy_identity(anatomy)
    return PolicyContract(catheter=cfg.catheter, observation=observation_spec(cfg),
                          anatomy=label, mode=mode, training=dict(training or {}),
                          anatomy_hash=content_hash)


def write_contract(model_path: Path, contract: PolicyContract, out: Path | None = None) -> Path:
    """Write ``contract`` into an ONNX file's metadata, the graph unchanged.

    Replaces any earlier contract and drops the :data:`LEGACY_KEYS`; for policies exported
    before the contract existed (the committed ones were re-contracted this way).
    """
    model = onnx.load(str(model_path))
    kept = [(p.key, p.value) for p in model.metadata_props
            if p.key not in (CONTRACT_KEY, *LEGACY_KEYS)]
    del model.metadata_props[:]
    for key, value in [*kept, (CONTRACT_KEY, contract.to_json())]:
        prop = model.metadata_props.add()
        prop.key = key
        prop.value = value
    onnx.checker.check_model(model)
    target = out or model_path
    onnx.save(model, str(target))
    return target


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``cgail export-onnx``."""
    p = tool_parser('export-onnx', __doc__, details=True)
    p.add_argument('checkpoint', type=Path,
                   help='checkpoint written by cgail train (best.pt, final.pt); with '
                        '--add-contract an exported .onnx')
    p.add_argument('--out', type=Path, default=None, help='output .onnx (default: next to it; '
                   'with --add-contract: the input file)')
    p.add_argument('--add-contract', action='store_true',
                   help='write the catheter contract of the default model in the anatomy and '
                        'mode of its metadata into an exported .onnx (graph unchanged)')
    p.add_argument('--training-json', default='{}',
                   help="with --add-contract: the contract's training notes, a JSON object")
    p.add_argument('--anatomy', default=None,
                   help="with --add-contract: the anatomy the policy was trained on, a built-in "
                        "name, prepared anatomy directory or mesh file (default: the model's "
                        "metadata, which names a built-in anatomy or a path anatomy's label)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cgail export-onnx``."""
    args = build_parser().parse_args(argv)
    try:
        if args.anatomy is not None and not args.add_contract:
            raise LearningError('--anatomy: expected with --add-contract (a checkpoint carries '
                                'its contract), found it alone')
        if args.add_contract:
            from cgail_sim.anatomy_spec import check_anatomy_spec, is_named

            if args.anatomy is not None:
                check_anatomy_spec(args.anatomy)  # (before the model is read)
            meta = {p.key: json.loads(p.value) for p in onnx.load(str(args.checkpoint))
                    .metadata_props}
            anatomy = args.anatomy or str(meta.get('anatomy', 'default'))
            if not is_named(anatomy) and args.anatomy is None:
                raise LearningError(f'--add-contract: the metadata of {args.checkpoint} names '
                                    f'anatomy {anatomy!r}, not a named one: give its '
                                    'prepared directory with --anatomy')
            training = json.loads(args.training_json)
            if not isinstance(training, dict):
                raise LearningError(f'--training-json: expected a JSON object, found '
                                    f'{args.training_json!r}')
            contract = default_contract(anatomy, str(meta.get('mode', 'static')), training)
            out = write_contract(args.checkpoint, contract, args.out)
        else:
            out = export_checkpoint(args.checkpoint,
                                    args.out or args.checkpoint.with_suffix('.onnx'))
    except (LearningError, ValueError) as exc:
        print(f'cgail export-onnx: error: {exc}', file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""``cgail train``: train a policy (C-GAIL, GAIL or an ablation) in the catheter simulator.

Examples::

    cgail train --preset cgail --mode static --demos bags/demos/default --out runs/cgail_static
    cgail train --preset cgail --mode dynamic --demos bags/demos/default \\
        --init-from runs/cgail_static/final.pt --out runs/cgail_dynamic
    cgail train --preset generalist --demos bags/demos/population --out runs/generalist

A preset with ``population.anatomies`` > 0 (``generalist``) trains across that many population
anatomies (:mod:`cgail_sim.population`, training seeds only) instead of ``--anatomy``,
with targets drawn per episode when its ``env_options`` say so (``sphere_targets``), and picks
``best.pt`` on the next training seeds' anatomies.

Writes ``<out>/config.yaml``, ``scalars.csv`` + a TensorBoard event file (flat names such as
``losses/value_loss``, ``eval/success_rate``), ``checkpoints/step_<n>.pt``, ``best.pt`` (highest
periodic evaluation success rate, latest on ties) and ``final.pt``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import math
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np
import torch
from tqdm import tqdm
import yaml

from cgail_learning.config import (
    config_from_dict,
    config_to_dict,
    load_config,
    PopulationConfig,
)
from cgail_learning.errors import LearningError
from cgail_learning.logger import ScalarLogger
from cgail_learning.trainer import evaluate_policy, Trainer
from cgail_sim.cli_help import tool_parser


def sim_metadata(env_cfg: Any, anatomies: str = 'one') -> dict[str, Any]:
    """The catheter contract of a simulator config (checkpoint/ONNX metadata); ``anatomies``:
    the contract's (:attr:`~cgail_sim.ftl_model.PolicyContract.anatomies`).

    The contract's ``theta_max`` is the evaluation env's (``env_cfg.theta_max``): the periodic
    evaluation that picks ``best.pt`` runs there, whatever the training curriculum did to the
    training envs. :func:`cgail_learning.export.export_checkpoint` adds the curriculum
    lesson the exported checkpoint was trained at.
    """
    from cgail_sim.anatomy_spec import anatomy_identity
    from cgail_sim.env import observation_spec
    from cgail_sim.ftl_model import CONTRACT_KEY, PolicyContract

    label, content_hash = anatomy_identity(env_cfg.anatomy)
    contract = PolicyContract(catheter=env_cfg.catheter, observation=observation_spec(env_cfg),
                              anatomy=label, mode=env_cfg.mode, anatomy_hash=content_hash,
                              env_options=env_cfg.options, anatomies=anatomies)
    meta = {CONTRACT_KEY: contract.to_dict(), 'anatomy': label, 'mode': env_cfg.mode}
    if content_hash:
        meta['anatomy_hash'] = content_hash
    return meta


def make_envs(mode: str, anatomy: Any, num_envs: int, env_options: str = 'ours',
              population: PopulationConfig | None = None,
              report: Callable[[str], None] | None = None) -> tuple[Any, Any, dict[str, Any]]:
    """Batched training env, single evaluation env and metadata for the simulator, in the env
    option set ``env_options`` (:data:`cgail_sim.config.OPTION_SETS`).

    With ``population`` enabled (:class:`~cgail_learning.config.PopulationConfig`),
    ``anatomy`` is not used: the training env is a :class:`~cgail_learning.envs.
    PopulationVecEnv` over the population's training anatomies (built once, ~5 s each the
    first time, then from the disk cache; ``report`` is told the progress), and the evaluation
    env an :class:`~cgail_learning.envs.AnatomyCycleEnv` over the next training seeds.
    The contract is then a population one (``anatomies: population``: a planner takes
    ``origin`` and ``d_max`` from the anatomy it runs in); its anatomy, ``origin`` and
    ``d_max`` are the first evaluation anatomy's; ``population`` in the metadata names the
    seeds.
    """
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv
    from cgail_sim.vec_env import CatheterNavVecEnv

    if population is None or not population.enabled:
        env_cfg = EnvConfig.from_options(env_options, mode=mode, anatomy=anatomy)
        return (CatheterNavVecEnv(env_cfg, num_envs), CatheterNavEnv(env_cfg),
                sim_metadata(env_cfg))
    from cgail_learning.envs import AnatomyCycleEnv, PopulationVecEnv
    from cgail_sim.anatomy_spec import resolve_anatomy
    from cgail_sim.population import sample_anatomy

    train_seeds, eval_seeds = population.seeds()
    t0 = time.monotonic()
    pool = [sample_anatomy(s) for s in train_seeds] + [
        resolve_anatomy(name) for name in population.include]
    evals = [sample_anatomy(s) for s in eval_seeds] + (
        pool[len(train_seeds):] if population.eval_include else [])
    if report is not None:
        also = f' and {", ".join(population.include)}' if population.include else ''
        report(f'{len(pool)} training anatomies (population seeds {train_seeds[0]}-'
               f'{train_seeds[-1]}{also}) and {len(evals)} evaluation anatomies (seeds '
               f'{eval_seeds[0]}-{eval_seeds[-1]}{also if population.eval_include else ""})'
               f' ready in {time.monotonic() - t0:.0f} s')

    def config(a: Any) -> EnvConfig:
        return EnvConfig.from_options(env_options, mode=mode, anatomy=a)

    weights = None if population.include_weight == 1.0 else (
        [1.0] * len(train_seeds) + [population.include_weight] * len(population.include))
    env = PopulationVecEnv(lambda a: CatheterNavVecEnv(config(a), 1), pool, num_envs,
                           population.redraw_every, weights)
    eval_env = AnatomyCycleEnv([CatheterNavEnv(config(a)) for a in evals])
    meta = sim_metadata(config(evals[0]), anatomies='population')
    meta['population'] = {'train_seeds': [train_seeds[0], train_seeds[-1] + 1],
                          'eval_seeds': [eval_seeds[0], eval_seeds[-1] + 1],
                          'redraw_every': population.redraw_every,
                          'include': list(population.include),
                          'include_weight': population.include_weight,
                          'eval_include': population.eval_include}
    return env, eval_env, meta


def load_training_demos(cfg: Any, demos: list[str] | list[Path], anatomy: Any = None,
                        prog: str = 'cgail train') -> tuple[Any, Any, Any, list[dict[str, Any]]]:
    """The demonstrations a preset learns from (``None``s when it uses neither GAIL nor BC):
    ``(obs, act, episodes, sources)``, each bag's re-simulation and the episodes per source
    reported on stderr after ``prog:``; ``anatomy``: the one-anatomy run's non-built-in anatomy
    the bags must have been recorded in (None: any)."""
    from cgail_learning.demos import load_demos

    sources: list[dict[str, Any]] = []
    if not cfg.needs_demos:
        return None, None, None, sources
    demo_obs, demo_act, demo_episodes = load_demos(
        [Path(d) for d in demos],
        report=lambda line: print(f'{prog}: demonstrations: {line}', file=sys.stderr),
        anatomy=anatomy, env_options=cfg.env_options, sources=sources)
    by_source: dict[str, int] = {}
    for src in sources:
        by_source[src['source']] = by_source.get(src['source'], 0) + (src['episodes'] or 0)
    print(f'{prog}: demonstrations by source: ' + '; '.join(
        f'{k}: {v} episodes' for k, v in by_source.items()), file=sys.stderr)
    return demo_obs, demo_act, demo_episodes, sources


def run_training(trainer: Trainer, eval_env: Any, out: Path, progress: bool = True,
                 seed: int = 0, run_state: dict[str, Any] | None = None) -> dict[str, float]:
    """The training loop: iterations, logging, periodic evaluation and checkpoints.

    ``run_state``: the loop's state stored in the checkpoint a run resumes from (its ``run``;
    :func:`latest_checkpoint`), after :meth:`Trainer.resume`: the best evaluation so far, the
    next evaluation and checkpoint steps and the wall time spent.
    """
    cfg = trainer.cfg
    out.mkdir(parents=True, exist_ok=True)
    (out / 'config.yaml').write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
    rs = run_state or {}
    logger = ScalarLogger(out, resume_step=trainer.step if run_state is not None else None)
    next_eval = rs.get('next_eval', cfg.eval_every or math.inf)
    # (a resumed run given a shorter interval keeps to it from now; 0: no periodic checkpoint)
    next_ckpt = (min(rs.get('next_ckpt', math.inf), trainer.step + cfg.checkpoint_every)
                 if cfg.checkpoint_every else math.inf)
    last: dict[str, float] = {}
    best = rs.get('best', -1.0)
    t0, step0, spent = time.monotonic(), trainer.step, float(rs.get('wall_s', 0.0))

    def loop_state() -> dict[str, Any]:
        return {'best': best, 'next_eval': next_eval, 'next_ckpt': next_ckpt,
                'wall_s': spent + time.monotonic() - t0}

    with tqdm(total=cfg.max_steps, initial=trainer.step, disable=not progress, unit='step',
              dynamic_ncols=True) as bar:
        while trainer.step < cfg.max_steps:
            before = trainer.step
            scalars = trainer.train_iteration()
            scalars['time/steps_per_s'] = (trainer.step - step0) / max(time.monotonic() - t0,
                                                                       1e-9)
            if trainer.step >= next_eval:
                ev = evaluate_policy(trainer.act_deterministic, eval_env, cfg.eval_episodes,
                                     seed=10_000 + seed)
                scalars.update(ev)
                next_eval += cfg.eval_every
                if ev['eval/success_rate'] >= best:
                    # PPO on this task is not monotone: keep the best evaluated policy too
                    best = ev['eval/success_rate']
                    trainer.save(out / 'best.pt')
                    scalars['eval/best_success_rate'] = best
            if trainer.step >= next_ckpt:
                next_ckpt += cfg.checkpoint_every
                trainer.save(out / 'checkpoints' / f'step_{trainer.step}.pt', loop_state())
            logger.log(trainer.step, scalars)
            last.update(scalars)
            bar.update(trainer.step - before)
            bar.set_postfix(
                reward=f"{scalars.get('environment/episode_reward', math.nan):.3f}",
                success=f"{scalars.get('environment/success_rate', math.nan):.2f}")
    trainer.save(out / 'final.pt', loop_state())
    final = evaluate_policy(trainer.act_deterministic, eval_env, cfg.eval_episodes,
                            seed=10_000 + seed)
    logger.log(trainer.step, final)
    logger.close()
    last.update(final)
    last['time/wall_s'] = loop_state()['wall_s']
    return last


def latest_checkpoint(run: Path) -> Path:
    """The checkpoint a run resumes from: the highest-step one of ``run/checkpoints/step_<n>.pt``
    and ``run/final.pt``.

    Raises:
        PolicyLoadError: no checkpoint in ``run``.
    """
    from cgail_learning.checkpoint import load_checkpoint
    from cgail_learning.errors import PolicyLoadError

    found = [(int(p.stem.split('_')[1]), p) for p in (run / 'checkpoints').glob('step_*.pt')
             if p.stem.split('_')[1].isdigit()]
    if (run / 'final.pt').is_file():
        found.append((int(load_checkpoint(run / 'final.pt').get('step', -1)), run / 'final.pt'))
    if not found:
        raise PolicyLoadError(f'--resume {run}: expected a run directory with '
                              'checkpoints/step_<n>.pt or final.pt, found none')
    return max(found, key=lambda t: t[0])[1]


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``cgail train``."""
    p = tool_parser('train', __doc__, details=True)
    p.add_argument('--preset', default='cgail',
                   help='preset name (cgail, gail, mu0, lambda0, nu0, smoke, paper_code_cgail, '
                        '...: config/presets/) or a YAML path; its env_options (ours, '
                        'paper_code) select the simulator option set')
    p.add_argument('--mode', choices=('static', 'dynamic'), default='static',
                   help='rigid aorta (static) or deformable beating wall with a moving target '
                        '(dynamic)')
    p.add_argument('--anatomy', default='default',
                   help='built-in anatomy name (default, elongated), prepared anatomy directory '
                        'or mesh file with its <stem>.yaml landmarks (not with a population '
                        'preset such as generalist, which trains on population anatomies)')
    p.add_argument('--demos', nargs='*', default=[], metavar='DEMO',
                   help='demonstration bag directories / .mcap files / .npz (GAIL, BC); with '
                        'a path --anatomy, demo bags are re-simulated in that anatomy')
    p.add_argument('--init-from', type=Path, default=None,
                   help='checkpoint to start from (pre-train static, re-train dynamic)')
    p.add_argument('--seed', type=int, default=0, help='seed; the same seed reproduces the run')
    p.add_argument('--resume', type=Path, default=None, metavar='RUN',
                   help="continue the run in RUN from its latest checkpoint, with its preset "
                        "and seed (--max-steps may extend it; give the run's --mode, --anatomy "
                        "and --demos); episodes in progress restart, so it continues the run "
                        "rather than replaying it bit for bit")
    p.add_argument('--max-steps', type=int, default=None, help='override the preset max_steps')
    p.add_argument('--num-envs', type=int, default=None, help='override the preset num_envs')
    p.add_argument('--checkpoint-every', type=int, default=None, metavar='STEPS',
                   help='override the preset checkpoint_every: how many steps a stopped run '
                        'can lose (checkpoints change nothing in the training)')
    p.add_argument('--threads', type=int, default=1, help='torch CPU threads (1-2; default 1)')
    p.add_argument('--out', type=Path, default=None,
                   help='run directory (default runs/<preset>_<mode>)')
    p.add_argument('--no-progress', action='store_true', help='hide the progress bar')
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cgail train``."""
    args = build_parser().parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    try:
        from cgail_sim.anatomy_spec import is_builtin, resolve_anatomy

        resolve_anatomy(args.anatomy)  # a bad anatomy fails before the demonstrations load
        ckpt: dict[str, Any] | None = None
        if args.resume is not None:
            from cgail_learning.checkpoint import load_checkpoint

            if args.init_from is not None:
                raise ValueError('--resume continues a run; --init-from starts a new one from '
                                 'weights: expected one of them, found both')
            ckpt = load_checkpoint(latest_checkpoint(args.resume))
            cfg = config_from_dict(ckpt['config'])
            args.seed = int(ckpt['seed'])
            args.out = args.out or args.resume
        else:
            cfg = load_config(args.preset)
        if (args.max_steps is not None or args.num_envs is not None
                or args.checkpoint_every is not None):
            d = config_to_dict(cfg)
            d['max_steps'] = args.max_steps or cfg.max_steps
            d['num_envs'] = args.num_envs or cfg.num_envs
            if args.checkpoint_every is not None:
                d['checkpoint_every'] = args.checkpoint_every
            cfg = config_from_dict(d)
        if cfg.population.enabled and args.anatomy != 'default':
            also = ''.join(f' and {n}' for n in cfg.population.include)
            raise ValueError(f'--anatomy: preset {cfg.name!r} trains on '
                             f'{cfg.population.anatomies} population anatomies{also}: expected '
                             f'no --anatomy, found {args.anatomy!r}')
        demo_obs, demo_act, demo_episodes, sources = load_training_demos(
            cfg, args.demos, None if is_builtin(args.anatomy) or cfg.population.enabled
            else args.anatomy)
        env, eval_env, meta = make_envs(
            args.mode, args.anatomy, cfg.num_envs, cfg.env_options, cfg.population,
            report=lambda line: print(f'cgail train: population: {line}', file=sys.stderr))
        meta['preset'] = cfg.name
        if sources:
            meta['demonstrations'] = sources
        trainer = Trainer(cfg, env, demo_obs=demo_obs, demo_act=demo_act, seed=args.seed,
                          metadata=meta, demo_episodes=demo_episodes)
        if args.init_from is not None:
            trainer.load_weights(args.init_from)
        if cfg.bc.pretrain_epochs and ckpt is None:
            warm = trainer.pretrain_bc(cfg.bc.pretrain_epochs)
            print(f'cgail train: BC warm start: {cfg.bc.pretrain_epochs} epochs, last loss '
                  f'{warm["losses/bc_pretrain_loss"]:.4g}', file=sys.stderr)
        if ckpt is not None:
            was = {k: ckpt['metadata'].get(k) for k in ('mode', 'anatomy', 'anatomy_hash')}
            now = {k: meta.get(k) for k in was}
            if was != now:
                raise ValueError(f'--resume {args.resume}: expected the run\'s simulator '
                                 f'{was}, found {now} (give its --mode and --anatomy)')
            trainer.resume(ckpt, args.resume)
            print(f'cgail train: resuming {args.resume} at step {trainer.step} of '
                  f'{cfg.max_steps}', file=sys.stderr)
        out = args.out or Path('runs') / f'{cfg.name}_{args.mode}'
        result = run_training(trainer, eval_env, out, progress=not args.no_progress,
                              seed=args.seed, run_state=None if ckpt is None else
                              ckpt.get('run', {}))
    except (LearningError, ValueError) as exc:
        print(f'cgail train: error: {exc}', file=sys.stderr)
        return 2
    print(yaml.safe_dump({k: round(float(v), 5) for k, v in sorted(result.items())
                          if isinstance(v, float | int) and np.isfinite(v)}))
    return 0


if __name__ == '__main__':
    sys.exit(main())

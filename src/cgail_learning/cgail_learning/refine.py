"""``cgail refine``: DAgger refinement of a trained population policy on its own training
distribution.

Usage::

    cgail refine runs/generalist/best.pt --demos bags/demos/population bags/demos/elongated \\
        --out runs/generalist_refined
    cgail export-onnx runs/generalist_refined/refined.pt --out generalist.onnx
    # fine-tuning: the committed generalist refined in one new anatomy
    cgail make-demos --anatomy population-10007 --episodes 15 --out runs/ft/demos
    cgail refine generalist.onnx --anatomy population-10007 --episodes 60 \\
        --demos runs/ft/demos --out runs/ft

**What it does.** The policy of a ``train`` checkpoint of a population preset (``generalist``)
drives static episodes in the run's own training anatomies, with targets drawn anew per episode
as the run drew them; the scripted expert (:mod:`cgail_learning.expert`) labels every
``--every``-th state the policy reached with the action it would take there
(:func:`~cgail_learning.dagger.expert_labels`); then the actor is cloned from the
checkpoint's weights on the run's demonstrations plus those labels
(:meth:`~cgail_learning.trainer.Trainer.pretrain_bc`, ``--epochs`` passes, the run's
observation normaliser kept). With ``--rounds`` > 1 the next round's episodes are driven by the
refined policy and the cloning runs on every label so far (DAgger's aggregate, Ross et al.,
AISTATS 2011). Each round's policy is validated like ``train`` validates its checkpoints (the
run's selection anatomies, ``eval_episodes`` episodes, the same seeds); ``refined.pt`` is the
best of the checkpoint and the rounds (latest on ties, as ``train`` keeps ``best.pt``).

**Worker processes.** ``--jobs N`` (0: one per CPU core) drives and labels the episodes in N
spawned processes, an anatomy's episodes cut into chunks of ten; each episode's seed, start and
target depend on its anatomy and index only, and the chunks are put back in order, so the labels
and the refined weights equal those of ``--jobs 1`` (a test compares them). The cloning and the
validations run in this process.

**Which anatomies.** ``--anatomies`` of the run's training seeds, evenly spaced, ``--episodes``
episodes each, and each named anatomy the run includes (built-in, or a real training aorta
``avt-<case>``) ``include_weight`` times as many (the share the training gave it). Never a
held-out seed or real aorta, never a selection seed.

**An exported population policy** (a ``.onnx`` without ``--anatomy``, e.g. the committed
generalist, whose run checkpoint is not at hand) is refined the same way in the population of
``--preset`` (default ``generalist``): its actor and normaliser are taken as ``train
--init-from`` takes them, and the preset gives the anatomies, the included ones and the
validation; ``refined.pt`` is a checkpoint of that preset with a population contract.

**One anatomy (fine-tuning).** With ``--anatomy A`` the policy (a ``train`` checkpoint or an
exported ``.onnx``, whose actor and normaliser are taken as ``train --init-from`` takes them) is
refined in ``A`` alone: ``--episodes`` episodes there, targets drawn anew per episode in its
30 mm sphere (``--preset``'s ``env_options``, ``finetune`` by default: the generalist's), the
demonstrations of ``A``, validation on ``eval_episodes`` (or ``--validation-episodes``) drawn
targets of ``A`` (seeds apart from the labelled episodes'), and ``refined.pt`` is a
one-anatomy checkpoint of ``A`` (its contract names ``A`` and its content hash), as ``train
--preset finetune --anatomy A`` writes one.

**Why** (not part of the paper's method, which trains C-GAIL only). The fourth generalist run
(C-GAIL, 100 min) missed targets that lie off to the side low in the aortic root: it kept the
heading of the ascending aorta, turned when 15-20 mm away and hit the wall (87-89 % of targets
drawn anew in ``default`` and ``elongated``; 83 % on ``elongated``'s unseen target set). GAIL's
reward pulls the policy towards the demonstrations' state distribution but teaches nothing on
the states the policy drifts into; the expert's labels there do. Measured on 2026-12-03 with
the defaults on the fourth run's ``best.pt`` (216 episodes in 34 anatomies, 25,983 labels,
6 min 13 s on one core): validation 92.9 % -> 100 %; unseen ``elongated`` targets 83 % -> 100 %
and 20 held-out anatomies 93 % -> 97 % (static, simulated tracker); held out dynamic 94 %
before and after. A second round, in a first trial of the recipe, gave 94 % on the held-out
ones against its first round's 97 %. The refined checkpoint keeps the run's contract, and its
``refinement`` metadata (written into the exported model's training notes) says how it was
refined.

Writes ``<out>/round_<k>.pt`` (k = 1..rounds), ``refined.pt`` and ``refine.yaml`` (per round:
episodes, labels, the policy's success while labelling per anatomy group, the validation and the
wall time). Exit status 0, or 2 with one line on stderr for input it cannot use.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
import os
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np
import torch
from tqdm import tqdm
import yaml

from cgail_learning.errors import LearningError
from cgail_sim.cli_help import tool_parser

__all__ = ['RefineOptions', 'build_parser', 'label_anatomies', 'main', 'refine']


@dataclass(frozen=True)
class RefineOptions:
    """Settings of one ``refine`` run (each one a command-line option)."""

    rounds: int = 1
    """DAgger rounds (1-10)."""
    anatomies: int = 32
    """Training seeds whose anatomies the policy drives in, evenly spaced over the run's."""
    episodes: int = 3
    """Episodes per population anatomy; each included built-in gets ``include_weight`` times
    as many."""
    every: int = 4
    """Label every ``every``-th state of an episode (``plan_patient``'s stride)."""
    epochs: int = 30
    """Passes of the cloning over demonstrations plus labels (``plan_patient``'s warm start)."""
    seed: int = 0
    """Seed of the episodes (anatomy j of round r: ``seed + 100000 r + 1000 j + k``)."""
    validation_episodes: int = 0
    """Episodes of each validation; 0: the preset's ``eval_episodes`` (``train``'s)."""
    dynamic_episodes: int = 0
    """Episodes in the beating aorta (the deformable wall) per named anatomy the run includes
    (built-in or real; with ``--anatomy``, that one), labelled beside the static ones: the
    expert's answer where the wall moves into the policy's way (0: static only)."""
    jobs: int = 1
    """Worker processes that drive and label the episodes (0: one per CPU core). The labels
    do not depend on it: each episode's seed, start and target are fixed by its anatomy and
    its index, and the chunks are put back in order."""

    def __post_init__(self) -> None:
        for name, lo, hi in (('rounds', 1, 10), ('anatomies', 0, 10_000), ('episodes', 1, 1000),
                             ('every', 1, 1000), ('epochs', 1, 1000), ('seed', 0, 2**31),
                             ('validation_episodes', 0, 10_000), ('dynamic_episodes', 0, 1000),
                             ('jobs', 0, 256)):
            v = getattr(self, name)
            if not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f'{name} must be an int in [{lo}, {hi}], found {v!r}')


def label_anatomies(population: Any, options: RefineOptions) -> list[tuple[Any, int]]:
    """``(anatomy spec, episodes)`` for each anatomy the policy drives in: ``options.anatomies``
    training seeds of ``population`` (a :class:`~cgail_learning.config.
    PopulationConfig`), evenly spaced, then the run's included built-ins."""
    from cgail_sim.population import sample_anatomy

    train_seeds, _ = population.seeds()
    n = min(options.anatomies, len(train_seeds))
    picks = [train_seeds[int(i * len(train_seeds) / n)] for i in range(n)] if n else []
    out: list[tuple[Any, int]] = [(sample_anatomy(s), options.episodes) for s in picks]
    weight = max(1, round(population.include_weight))
    out += [(name, weight * options.episodes) for name in population.include]
    return out


def _group(spec: Any) -> str:
    return spec if isinstance(spec, str) else 'population'


_CHUNK = 10
"""Episodes per worker task: small enough to balance 60-episode anatomies against
3-episode ones over the workers."""


@dataclass(frozen=True)
class _LabelJob:
    """One anatomy's episodes of a round (``--jobs``: cut into chunks of :data:`_CHUNK`)."""

    spec: Any
    """What the env is built from: a name or path, or an :class:`~cgail_sim.anatomy.Anatomy`."""
    mode: str
    episodes: int
    group: str


def _portable(spec: Any) -> Any:
    """``spec`` as a worker process can rebuild it: a population sample by its name
    (``population-<seed>``, rebuilt from the seed; 1.7 MB less to send), else as it is."""
    from cgail_sim.population import population_seed

    name = getattr(spec, 'name', None)
    if isinstance(spec, str) or not isinstance(name, str):
        return spec
    return name if population_seed(name) is not None else spec


_worker: dict[str, Any] = {}
"""A worker process's envs (by options, spec and mode) and the round's policy."""


def _worker_init() -> None:
    torch.set_num_threads(1)


def _label_chunk(env_options: str, spec: Any, mode: str, round_: int, actor: bytes,
                 episodes: int, first: int, seed: int, every: int
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Worker task: episodes ``first ..`` of one anatomy driven by the round's actor (sent as
    pickled bytes once per round and worker) and labelled by the expert."""
    import pickle

    from cgail_learning.dagger import expert_labels
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    key = (env_options, spec if isinstance(spec, str) else spec.content_hash, mode)
    env = _worker.setdefault('envs', {}).get(key)
    if env is None:
        env = CatheterNavEnv(EnvConfig.from_options(env_options, mode=mode, anatomy=spec))
        _worker['envs'][key] = env
    if _worker.get('round') != round_:
        _worker['round'], _worker['actor'] = round_, pickle.loads(actor).eval()
    net = _worker['actor']

    @torch.no_grad()
    def policy(obs: np.ndarray) -> np.ndarray:
        return net.deterministic(torch.as_tensor(np.asarray(obs, np.float32))).numpy()

    return expert_labels(env, policy, episodes, seed, every, first=first)


def _jobs(options: RefineOptions) -> int:
    if options.jobs:
        return options.jobs
    return len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else \
        (os.cpu_count() or 1)


def refine(checkpoint: Path, demos: list[str] | list[Path], out: Path,
           options: RefineOptions | None = None, progress: bool = True,
           log: Any = None, anatomy: str | None = None,
           preset: str | None = None) -> dict[str, Any]:
    """Refine ``checkpoint`` (module docstring); ``anatomy``: refine in that one anatomy with
    ``preset``'s settings (default ``finetune``) instead of in the run's population. An
    exported ``.onnx`` without ``anatomy`` is refined in the population of ``preset`` (default
    ``generalist``), which then also gives the run's settings. Returns what ``refine.yaml``
    holds.

    Raises:
        LearningError: a checkpoint that is not a static population run's (without
            ``anatomy``), a preset that does not fit, or unusable demonstrations (one line
            each).
    """
    from cgail_learning.checkpoint import load_checkpoint
    from cgail_learning.config import config_from_dict, load_config
    from cgail_learning.dagger import expert_labels
    from cgail_learning.train import load_training_demos, make_envs
    from cgail_learning.trainer import evaluate_policy, Trainer
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    options = options or RefineOptions()
    say = log or (lambda line: print(f'cgail refine: {line}', file=sys.stderr))
    t0 = time.monotonic()
    checkpoint = Path(checkpoint)
    ckpt: dict[str, Any] | None = None
    if anatomy is None and checkpoint.suffix == '.onnx':  # an exported population policy
        if not checkpoint.is_file():
            raise LearningError(f'policy not found: expected an exported .onnx at {checkpoint}')
        cfg = load_config(preset or 'generalist')
        if not cfg.population.enabled:
            raise LearningError(f'--preset: expected a population preset (generalist) to refine '
                                f'{checkpoint} without --anatomy, found {cfg.name!r} on one '
                                'anatomy')
        meta = {}
    elif anatomy is None:
        ckpt = load_checkpoint(checkpoint)
        cfg = config_from_dict(ckpt['config'])
        meta = dict(ckpt.get('metadata', {}))
        if not cfg.population.enabled:
            raise LearningError(f'{checkpoint}: expected a checkpoint of a population preset '
                                f'(generalist), found preset {cfg.name!r} on one anatomy '
                                '(give --anatomy to refine it in one anatomy)')
        if meta.get('mode', 'static') != 'static':
            raise LearningError(f'{checkpoint}: expected a static run\'s checkpoint (the '
                                'labels are drawn in the rigid aorta), found mode '
                                f'{meta.get("mode")!r}')
    else:
        from cgail_sim.anatomy_spec import resolve_anatomy

        resolve_anatomy(anatomy)  # (a bad anatomy fails before the demonstrations load)
        if checkpoint.suffix != '.onnx':
            load_checkpoint(checkpoint)  # (a missing or unreadable one: one line, early)
        elif not checkpoint.is_file():
            raise LearningError(f'policy not found: expected an exported .onnx at {checkpoint}')
        cfg = load_config(preset or 'finetune')
        if cfg.population.enabled:
            raise LearningError(f'--preset: expected a one-anatomy preset with --anatomy '
                                f'(finetune), found {cfg.name!r} on a population')
    if not cfg.needs_demos:
        raise LearningError(f'expected a preset that learns from demonstrations, found preset '
                            f'{cfg.name!r} without GAIL or BC')
    if not demos:
        raise LearningError('--demos: expected the demonstration sources, found none')
    if anatomy is None:
        demo_obs, demo_act, demo_episodes, sources = load_training_demos(
            cfg, demos, prog='cgail refine')
        env, eval_env, env_meta = make_envs('static', 'default', cfg.num_envs,
                                            cfg.env_options, cfg.population, report=say)
        run_seed = options.seed if ckpt is None else int(ckpt['seed'])
        if ckpt is None:  # (the contract and notes of a run of this preset, as train's)
            meta = {**env_meta, 'preset': cfg.name}
            if sources:
                meta['demonstrations'] = sources
        trainer = Trainer(cfg, env, demo_obs=demo_obs, demo_act=demo_act,
                          seed=run_seed, metadata=meta, demo_episodes=demo_episodes)
        eval_seed = 10_000 + run_seed  # (train's periodic evaluation)
        specs = label_anatomies(cfg.population, options)

        def restore() -> None:  # (networks, normaliser, step, curriculum, rng)
            if ckpt is None:
                trainer.load_weights(checkpoint)
            else:
                trainer.resume(ckpt, checkpoint)
    else:
        from cgail_sim.anatomy_spec import is_builtin

        demo_obs, demo_act, demo_episodes, _ = load_training_demos(
            cfg, demos, None if is_builtin(anatomy) else anatomy, prog='cgail refine')
        env, eval_env, meta = make_envs('static', anatomy, cfg.num_envs, cfg.env_options)
        meta['preset'] = cfg.name
        trainer = Trainer(cfg, env, demo_obs=demo_obs, demo_act=demo_act, seed=options.seed,
                          metadata=meta, demo_episodes=demo_episodes)
        eval_seed = 10_000 + options.seed
        specs = [(anatomy, options.episodes)]

        def restore() -> None:
            trainer.load_weights(checkpoint)
    restore()

    n_val = options.validation_episodes or cfg.eval_episodes

    def validate() -> float:
        return evaluate_policy(trainer.act_deterministic, eval_env, n_val,
                               seed=eval_seed)['eval/success_rate']

    work = [_LabelJob(spec, 'static', n, _group(spec)) for spec, n in specs]
    if options.dynamic_episodes:  # (the named ones: the built-ins and the real aortas)
        work += [_LabelJob(spec, 'dynamic', options.dynamic_episodes, f'{_group(spec)} dynamic')
                 for spec, _ in specs if isinstance(spec, str)]
    jobs = _jobs(options)
    pool: Any = None
    if jobs == 1:  # (in this process, each env built once)
        envs = [CatheterNavEnv(EnvConfig.from_options(cfg.env_options, mode=w.mode,
                                                      anatomy=w.spec)) for w in work]
    else:
        import concurrent.futures
        import multiprocessing

        pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=jobs, mp_context=multiprocessing.get_context('spawn'),
            initializer=_worker_init)

    def label_round(r: int, bar: Any) -> list[tuple[np.ndarray, np.ndarray, dict[str, float]]]:
        """Every job's (obs, labels, stats) of round ``r``, in the order of ``work``."""
        seeds = [options.seed + 100_000 * (r - 1) + 1000 * j for j in range(len(work))]
        if pool is None:
            out = []
            for j, w in enumerate(work):
                out.append(expert_labels(envs[j], trainer.act_deterministic, w.episodes,
                                         seeds[j], options.every))
                bar.update(w.episodes)
            return out
        import concurrent.futures
        import pickle

        actor = pickle.dumps(trainer.actor)
        futures = [[pool.submit(_label_chunk, cfg.env_options, _portable(w.spec), w.mode, r,
                                actor, min(_CHUNK, w.episodes - k), k, seeds[j],
                                options.every)
                    for k in range(0, w.episodes, _CHUNK)] for j, w in enumerate(work)]
        for f in concurrent.futures.as_completed([f for fs in futures for f in fs]):
            bar.update(int(f.result()[2]['episodes']))
        out = []
        for fs in futures:
            parts = [f.result() for f in fs]
            n = sum(st['episodes'] for _, _, st in parts)
            out.append((np.concatenate([o for o, _, _ in parts]),
                        np.concatenate([a for _, a, _ in parts]),
                        {'episodes': n, 'labels': float(sum(len(o) for o, _, _ in parts)),
                         'policy_success': sum(st['policy_success'] * st['episodes']
                                               for _, _, st in parts) / max(n, 1)}))
        return out

    base = validate()
    say(f'{checkpoint}: step {trainer.step}, validation {100 * base:.1f}% on '
        f'{n_val} episodes; {sum(w.episodes for w in work)} episodes a round in '
        f'{len(work)} anatomies, {jobs} worker process{"es" if jobs > 1 else ""} '
        f'({time.monotonic() - t0:.0f} s)')
    summary: dict[str, Any] = {'checkpoint': str(checkpoint), 'options': asdict(options),
                               'base_validation': base, 'rounds': []}
    best = (base, 0)
    obs_all: list[np.ndarray] = []
    act_all: list[np.ndarray] = []
    out.mkdir(parents=True, exist_ok=True)
    try:
        for r in range(1, options.rounds + 1):
            t_round = time.monotonic()
            groups: dict[str, list[float]] = {}
            with tqdm(total=sum(w.episodes for w in work), disable=not progress, unit='episode',
                      desc=f'cgail refine: round {r} labels', dynamic_ncols=True) as bar:
                for w, (o, a, st) in zip(work, label_round(r, bar), strict=True):
                    obs_all.append(o)
                    act_all.append(a)
                    g = groups.setdefault(w.group, [0.0, 0.0])
                    g[0] += st['policy_success'] * st['episodes']
                    g[1] += st['episodes']
            t_label = time.monotonic() - t_round
            restore()  # (DAgger clones the aggregate from the start)
            stats = trainer.pretrain_bc(options.epochs, extra=(np.concatenate(obs_all),
                                                               np.concatenate(act_all)),
                                        refit_normalizer=False)
            rate = validate()
            labels = int(sum(len(o) for o in obs_all))
            row = {'round': r, 'labels': labels,
                   'policy_success': {k: round(v[0] / v[1], 4) for k, v in groups.items()},
                   'bc_loss': round(float(stats['losses/bc_pretrain_loss']), 5),
                   'validation': rate, 'label_s': round(t_label, 1),
                   'wall_s': round(time.monotonic() - t_round, 1)}
            summary['rounds'].append(row)
            trainer.metadata['refinement'] = {
                'method': 'dagger', 'round': r, 'labels': labels, 'every': options.every,
                'epochs': options.epochs, 'anatomies': len(work), 'base_step': trainer.step,
                'base_validation': base, 'validation': rate}
            trainer.save(out / f'round_{r}.pt')
            if rate >= best[0]:
                best = (rate, r)
            say(f'round {r}: the policy reached ' + ', '.join(
                f'{k} {100 * v[0] / v[1]:.0f}%' for k, v in groups.items()) +
                f' of its episodes; {labels} labels; cloned {options.epochs} epochs (loss '
                f'{row["bc_loss"]:.4f}); validation {100 * rate:.1f}% ({row["wall_s"]:.0f} s)')
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    if best[1] == 0:  # no round validated better: the policy as it came, as a checkpoint
        restore()
        trainer.metadata.pop('refinement', None)
        trainer.save(out / 'refined.pt')
    else:
        (out / 'refined.pt').write_bytes((out / f'round_{best[1]}.pt').read_bytes())
    summary.update(chosen=best[1], validation=best[0],
                   wall_s=round(time.monotonic() - t0, 1))
    (out / 'refine.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    say(f'refined.pt: {"the checkpoint itself" if best[1] == 0 else f"round {best[1]}"} '
        f'(validation {100 * best[0]:.1f}%), {summary["wall_s"]:.0f} s in all')
    return summary


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``cgail refine``."""
    p = tool_parser('refine', __doc__)
    p.add_argument('checkpoint', type=Path,
                   help="a population run's checkpoint of cgail train (best.pt, final.pt) or an "
                        'exported .onnx (refined in --preset\'s population, or in --anatomy)')
    p.add_argument('--anatomy', default=None,
                   help='refine in this one anatomy (fine-tuning: a built-in name, '
                        'population-<seed> or a prepared anatomy directory)')
    p.add_argument('--preset', default=None,
                   help="the preset whose settings apply: with --anatomy (default finetune), "
                        'or to an exported .onnx without it (default generalist: its '
                        'population, included anatomies and demonstrations)')
    p.add_argument('--demos', nargs='+', default=[], metavar='DEMO',
                   help="the run's demonstration sources (bag directories, .mcap, .npz)")
    p.add_argument('--out', type=Path, required=True, help='directory to write')
    d = RefineOptions()
    for name, help_ in (('rounds', 'DAgger rounds'),
                        ('anatomies', 'training anatomies to drive in (evenly spaced)'),
                        ('episodes', 'episodes per population anatomy (built-ins: '
                                     'include_weight times as many)'),
                        ('every', 'label every n-th state'),
                        ('epochs', 'cloning passes over demonstrations + labels'),
                        ('seed', 'seed of the episodes'),
                        ('dynamic_episodes', 'episodes in the beating aorta per named '
                                             'anatomy included (0: static only)'),
                        ('validation_episodes', "episodes of each validation (0: the preset's "
                                                'eval_episodes)'),
                        ('jobs', 'worker processes that drive and label the episodes (0: one '
                                 'per CPU core; the labels do not depend on it)')):
        p.add_argument(f'--{name.replace("_", "-")}', type=int, default=getattr(d, name),
                       help=f'{help_} (default {getattr(d, name)})')
    p.add_argument('--threads', type=int, default=1, help='torch CPU threads')
    p.add_argument('--no-progress', action='store_true', help='hide the progress bar')
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cgail refine``."""
    args = build_parser().parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    try:
        opts = RefineOptions(rounds=args.rounds, anatomies=args.anatomies,
                             episodes=args.episodes, every=args.every, epochs=args.epochs,
                             seed=args.seed, validation_episodes=args.validation_episodes,
                             dynamic_episodes=args.dynamic_episodes, jobs=args.jobs)
        refine(args.checkpoint, args.demos, args.out, opts, progress=not args.no_progress,
               anatomy=args.anatomy, preset=args.preset)
    except (LearningError, ValueError) as exc:
        print(f'cgail refine: error: {exc}', file=sys.stderr)
        return 2
    print(args.out / 'refined.pt')
    return 0


if __name__ == '__main__':
    sys.exit(main())

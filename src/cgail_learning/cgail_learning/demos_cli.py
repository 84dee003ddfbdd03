"""``cgail make-demos``: record scripted-expert demonstrations into rosbag2 MCAP bags.

Example::

    cgail make-demos --anatomy default --episodes 70 --out bags/demos/default

Episode k uses start ``k % 3`` and target ``(k // 3) % 5`` (every start x target pair, then
again), seeded by ``--seed``; the expert's success rate is printed and stored in the bag, with
the content hash of the anatomy the episodes were recorded in. ``--env-options paper_code``
records in the authors' option set (:data:`cgail_sim.config.OPTION_SETS`); the bag holds
poses and commands, not observations, so ``cgail train`` replays it in its preset's option set
either way.

Population form (``--population N``): the episodes are spread over the first ``N`` population
training anatomies (:data:`cgail_sim.population.TRAINING_SEEDS`): episode k runs in
anatomy ``k % N`` with the start, target and seed above (so the anatomies see different
targets of their own sets), grouped by anatomy in the bag. Each episode's ``demo/episode``
JSON names its anatomy (``population-<seed>``) and content hash, so ``load_demos``
re-simulates each in its own anatomy::

    cgail make-demos --population 32 --episodes 96 --out bags/demos/population

``--include default elongated`` adds built-in anatomies after the population's (episode k runs
in anatomy ``k % (N + 2)``), named by their built-in names in the episodes' JSON.

From session bags (``--from-bags``): teleoperated trial bags (the simulated in-vitro session's,
``cgail session``, or a rig's) become demonstrations of ``--anatomy`` (the one they were
recorded in), one episode per goal, with actions inferred from the tip motion by closed-loop
inverse kinematics of the catheter model (:mod:`cgail_learning.teleop_demos`)::

    cgail make-demos --from-bags runs/invitro/bags/centerline --out bags/demos/teleop

A BAG is a trial bag or a directory of them. One line per episode (steps, how it ended,
clipped steps, deviation from the recorded tip) and per input that could not be converted
goes to stderr, then the JSON report to stdout; the bag is replayed as ``cgail train`` will
(:func:`~cgail_learning.demo_bags.replay_demo_bag`) before the command succeeds.
Exit status 2 when no episode could be converted or the replay fails.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import json
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np

from cgail_learning.demo_bags import DemoEpisode, write_demo_bag
from cgail_learning.errors import LearningError
from cgail_learning.expert import ScriptedExpert
from cgail_planner.core.rotations import matrix_to_quaternion
from cgail_sim.cli_help import tool_parser

Pairs = list[tuple[np.ndarray, np.ndarray]]


def _progress(args: argparse.Namespace, total: int) -> Any:
    """A progress bar of the expert's episodes on stderr, with the time left (hidden by
    ``--no-progress``)."""
    from tqdm import tqdm

    return tqdm(total=total, disable=args.no_progress, unit='episode',
                desc='cgail make-demos', dynamic_ncols=True)


def record_episodes(env, n: int, seed: int = 0, pairs: Pairs | None = None, *,
                    indices: Sequence[int] | None = None,
                    done: Callable[[int], object] | None = None
                    ) -> tuple[list[DemoEpisode], dict[str, float]]:
    """Run the expert for ``n`` episodes; returns the episodes and summary statistics.

    Args:
        env: a static :class:`~cgail_sim.env.CatheterNavEnv`.
        n: episodes; episode k uses start ``k % n_starts``, target ``(k // n_starts) %
            n_targets`` and seed ``seed + k``.
        seed: base seed.
        pairs: when given, the (obs, act) arrays of every *successful* episode are appended to
            it as they were simulated (what a replay of the bag on this machine gives), so a
            caller that trains at once needs no replay.
        indices: the episode numbers k to run (default ``range(n)``; ``n`` is then unused).
        done: called with 1 after each episode (a progress bar's ``update``).
    """
    expert = ScriptedExpert(env)
    eng = env.unwrapped.engine
    n_s, n_t = len(eng.scenarios.starts), len(eng.scenarios.targets)
    episodes, steps, t_a = [], [], []
    ks = list(range(n)) if indices is None else [int(k) for k in indices]
    for k in ks:
        obs, _ = env.reset(seed=seed + k,
                           options={'start': k % n_s, 'target': (k // n_s) % n_t})
        expert.reset(seed + k)
        rows: dict[str, list] = {'al': [], 'ga': [], 'dl': [], 'p': [], 'q': [], 'g': []}
        seen: list[np.ndarray] = []
        acts: list[np.ndarray] = []
        while True:
            a = expert.act()
            seen.append(obs)
            acts.append(np.asarray(a, np.float32))
            obs, _, te, tr, info = env.step(a)
            rows['al'].append(info['bend'][0])
            rows['ga'].append(info['bend'][1])
            rows['dl'].append(info['insertion'])
            rows['p'].append(eng.catheter.tip_position[0].copy())
            rows['q'].append(matrix_to_quaternion(eng.catheter.tip_rotation[0]))
            rows['g'].append(np.asarray(info['target_position'], float))
            if te or tr:
                break
        episodes.append(DemoEpisode(
            k % n_s, (k // n_s) % n_t, np.asarray(rows['al']), np.asarray(rows['ga']),
            np.asarray(rows['dl']), np.asarray(rows['p']), np.asarray(rows['q']),
            np.asarray(rows['g']), bool(info['success'])))
        if pairs is not None and info['success']:
            pairs.append((np.asarray(seen, np.float32), np.asarray(acts, np.float32)))
        steps.append(len(rows['al']))
        t_a.append(info['targeting_error'])
        if done is not None:
            done(1)
    succ = [e.success for e in episodes]
    return episodes, {'episodes': len(ks), 'success_rate': float(np.mean(succ)),
                      'mean_steps': float(np.mean(steps)),
                      'mean_targeting_error_mm': 1e3 * float(np.mean(t_a))}


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``cgail make-demos``."""
    p = tool_parser('make-demos', __doc__, details=True)
    p.add_argument('--anatomy', default='default',
                   help='built-in anatomy name (default, elongated), prepared anatomy directory '
                        'or mesh file with its <stem>.yaml landmarks')
    p.add_argument('--episodes', type=int, default=70,
                   help='episodes to record; episode k: start k %% 3, target (k // 3) %% 5')
    p.add_argument('--seed', type=int, default=0,
                   help='seed of episode 0 (episode k: seed + k)')
    p.add_argument('--scenario-seed', type=int, default=0,
                   help="the anatomy's target set (EnvConfig.scenario_seed; 0: the standard "
                        'one the rig uses), recorded in the bag for its replay')
    p.add_argument('--env-options', default='ours',
                   help="the simulator's option set: 'ours' (default) or 'paper_code' (the "
                        "authors' observation, forward-only insertion, reward, heartbeat)")
    p.add_argument('--population', type=int, default=0, metavar='N',
                   help='spread the episodes over the first N population training anatomies '
                        '(--anatomy is then not used)')
    p.add_argument('--include', nargs='+', default=[], metavar='NAME',
                   help='with --population: built-in anatomies (default, elongated) that get '
                        "episodes too, after the population's (the pool of a preset's "
                        'population.include)')
    p.add_argument('--out', type=Path, required=True, help='bag directory to create')
    p.add_argument('--no-progress', action='store_true',
                   help="hide the progress bar of the expert's episodes")
    g = p.add_argument_group('from session bags',
                             'teleoperated trial bags instead of the scripted expert')
    g.add_argument('--from-bags', nargs='+', type=Path, default=None, metavar='BAG',
                   help='convert teleoperated trial bags (or directories of them) recorded in '
                        '--anatomy instead of running the scripted expert')
    g.add_argument('--tip-topic', default='auto',
                   help="tip poses to read: 'auto' (phantom/tip_pose where recorded, else "
                        "em_tracker/tip_pose) or a topic name")
    g.add_argument('--smooth-s', type=float, default=None,
                   help='half-window of the local linear fit of the tip positions, s (default: '
                        '0.4 for em_tracker/tip_pose, 0 for phantom/tip_pose)')
    g.add_argument('--max-deviation-mm', type=float, default=5.0,
                   help='cut an episode where the simulated tip strays farther from the '
                        'recorded one, mm')
    g.add_argument('--start-tolerance-mm', type=float, default=3.0,
                   help="largest distance of an episode's first tip position from a scenario "
                        'start, mm')
    g.add_argument('--target-tolerance-mm', type=float, default=5.0,
                   help='largest distance of a goal from a scenario target, mm')
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cgail make-demos``."""
    args = build_parser().parse_args(argv)
    if args.from_bags is not None:
        return _from_bags_main(args)
    if args.include and not args.population:
        print('cgail make-demos: error: --include: expected --population N beside it (it adds '
              'built-in anatomies to a population bag)', file=sys.stderr)
        return 2
    if args.episodes < 1:
        print(f'cgail make-demos: error: --episodes must be >= 1, found {args.episodes}',
              file=sys.stderr)
        return 2
    if args.population:
        return _population_main(args)
    from cgail_sim.anatomy_spec import anatomy_label, is_named
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    try:
        env = CatheterNavEnv(EnvConfig.from_options(args.env_options, mode='static',
                                                    anatomy=args.anatomy,
                                                    scenario_seed=args.scenario_seed))
        label = anatomy_label(args.anatomy)
        t0 = time.monotonic()
        with _progress(args, args.episodes) as bar:
            episodes, stats = record_episodes(env, args.episodes, args.seed, done=bar.update)
        stats['wall_s'] = time.monotonic() - t0
        write_demo_bag(args.out, episodes, anatomy=label, mode='static',
                       dt=env.config.dt, anatomy_hash=env.anatomy.content_hash,
                       anatomy_path=None if is_named(args.anatomy)
                       else str(Path(args.anatomy).expanduser().resolve()),
                       scenario_seed=args.scenario_seed, env_options=args.env_options)
    except (LearningError, ValueError) as exc:
        print(f'cgail make-demos: error: {exc}', file=sys.stderr)
        return 2
    print(json.dumps({'anatomy': label, 'env_options': args.env_options, **stats}))
    return 0


def _from_bags_main(args: argparse.Namespace) -> int:
    """``cgail make-demos --from-bags BAG [BAG ...]`` (module docstring)."""
    from dataclasses import asdict

    from cgail_bags.errors import BagError
    from cgail_bags.reader import find_trials
    from cgail_learning.demo_bags import replay_demo_bag
    from cgail_learning.teleop_demos import ConversionConfig, convert_bags
    from cgail_sim.anatomy_spec import anatomy_label, is_named
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    def fail(text: str) -> int:
        print(f'cgail make-demos: error: {text}', file=sys.stderr)
        return 2

    def log(text: str) -> None:
        print(f'cgail make-demos: {text}', file=sys.stderr, flush=True)

    if args.population or args.include:
        return fail('--from-bags: expected no --population or --include (the bags were '
                    'recorded in one anatomy, --anatomy)')
    if args.out.exists():
        return fail(f'--out: expected a new bag directory, found {args.out} (remove it first)')
    try:
        config = ConversionConfig(
            tip_topic=args.tip_topic, smooth_s=args.smooth_s,
            max_deviation_m=args.max_deviation_mm * 1e-3,
            start_tolerance_m=args.start_tolerance_mm * 1e-3,
            target_tolerance_m=args.target_tolerance_mm * 1e-3)
        env = CatheterNavEnv(EnvConfig.from_options(args.env_options, mode='static',
                                                    anatomy=args.anatomy,
                                                    scenario_seed=args.scenario_seed))
    except ValueError as exc:
        return fail(str(exc))
    bags: list[Path] = []
    unread: list[str] = []
    for item in args.from_bags:
        try:
            bags += [bag for bag, _ in find_trials([item])]
        except BagError as exc:
            unread.append(str(exc))
            log(str(exc))
    t0 = time.monotonic()
    episodes, report = convert_bags(bags, env, config, log=log)
    report.bags += len(unread)
    report.skipped[:0] = unread
    stats = report.to_dict()
    if not episodes:
        return fail(f'no episode could be converted from {report.bags} bag(s) '
                    f'({len(report.skipped)} problem(s) above)')
    label = anatomy_label(args.anatomy)
    source = {'from_bags': [str(b) for b in bags], 'config': asdict(config),
              **{k: v for k, v in stats.items() if k not in ('per_episode', 'skipped')}}
    try:
        write_demo_bag(args.out, episodes, anatomy=label, mode='static', dt=env.config.dt,
                       anatomy_hash=env.anatomy.content_hash,
                       anatomy_path=None if is_named(args.anatomy)
                       else str(Path(args.anatomy).expanduser().resolve()),
                       scenario_seed=args.scenario_seed, env_options=args.env_options,
                       source=source)
        if stats['successful']:
            replay = replay_demo_bag(args.out, env_options=args.env_options).report
            stats['replay'] = {'episodes': replay.episodes, 'steps': replay.steps,
                               'max_drift_mm': round(replay.max_drift_m * 1e3, 6),
                               'tolerance_mm': replay.tolerance_m * 1e3}
        else:
            log('no converted episode reached its target: the bag holds no episode that '
                'train replays (it replays the successful ones)')
    except (LearningError, ValueError) as exc:
        return fail(str(exc))
    stats['wall_s'] = round(time.monotonic() - t0, 2)
    print(json.dumps({'anatomy': label, 'env_options': args.env_options, 'dt': env.config.dt,
                      **stats}))
    return 0


def record_population(seeds: tuple[int, ...], episodes: int, seed: int = 0,
                      env_options: str = 'ours', include: tuple[str, ...] = (),
                      done: Callable[[int], object] | None = None
                      ) -> tuple[list[DemoEpisode], dict[str, float]]:
    """Expert episodes spread over the population anatomies ``seeds`` and then the built-in
    anatomies ``include`` (module docstring); each
    :class:`~cgail_learning.demo_bags.DemoEpisode` names its anatomy.

    Raises:
        ValueError: a seed outside the training seeds (demonstrations never touch a held-out
            anatomy), or an ``include`` name that is no built-in or real training anatomy.
    """
    from cgail_sim.anatomy_spec import REAL_HELD_OUT, resolve_anatomy, TRAINING_NAMES
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv
    from cgail_sim.population import check_training_seeds, population_name

    seeds = check_training_seeds(seeds)
    bad = [n for n in include if n not in TRAINING_NAMES]
    if bad or len(set(include)) != len(include):
        raise ValueError(f'--include: expected distinct names of built-in or real training '
                         f'anatomies {list(TRAINING_NAMES)} (the held-out real ones, '
                         f'{list(REAL_HELD_OUT)}, never train), found {list(include)}')
    names = [population_name(s) for s in seeds] + list(include)

    out: list[DemoEpisode] = []
    steps: list[float] = []
    errors: list[float] = []
    for j, name in enumerate(names):
        ks = range(j, episodes, len(names))
        count = len(ks)
        if count == 0:
            continue
        anatomy = resolve_anatomy(name)  # (a population name: sample_anatomy)
        env = CatheterNavEnv(EnvConfig.from_options(env_options, mode='static', anatomy=anatomy))
        eps, stats = record_episodes(env, count, seed, indices=ks, done=done)
        for ep in eps:
            ep.anatomy, ep.anatomy_hash = name, anatomy.content_hash
        out.extend(eps)
        steps.append(stats['mean_steps'] * count)
        errors.append(stats['mean_targeting_error_mm'] * count)
    return out, {'episodes': len(out), 'anatomies': len(names),
                 'success_rate': float(np.mean([e.success for e in out])),
                 'mean_steps': float(sum(steps) / len(out)),
                 'mean_targeting_error_mm': float(sum(errors) / len(out))}


def _population_main(args: argparse.Namespace) -> int:
    """``cgail make-demos --population N``."""
    from cgail_learning.demo_bags import population_hash
    from cgail_sim.config import EnvConfig
    from cgail_sim.population import split_seeds

    try:
        seeds = split_seeds('train', args.population)
        t0 = time.monotonic()
        with _progress(args, args.episodes) as bar:
            episodes, stats = record_population(seeds, args.episodes, args.seed,
                                                args.env_options, tuple(args.include),
                                                done=bar.update)
        stats['wall_s'] = time.monotonic() - t0
        write_demo_bag(args.out, episodes, anatomy='population', mode='static',
                       dt=EnvConfig.from_options(args.env_options).dt,
                       anatomy_hash=population_hash([str(e.anatomy_hash) for e in episodes]),
                       env_options=args.env_options, population=True)
    except (LearningError, ValueError) as exc:
        print(f'cgail make-demos: error: {exc}', file=sys.stderr)
        return 2
    print(json.dumps({'anatomy': 'population', 'population_seeds': [seeds[0], seeds[-1] + 1],
                      'include': args.include, 'env_options': args.env_options, **stats}))
    return 0


if __name__ == '__main__':
    sys.exit(main())

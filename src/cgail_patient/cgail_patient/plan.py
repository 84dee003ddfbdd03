"""``cgail plan-patient``: from a prepared anatomy to a trained, evaluated planner and the rig
command.

Usage::

    cgail plan-patient runs/patient7 --out runs/patient7_plan [--budget-min 15]

One command, in this order (each stage prints one line as it ends, training shows a progress
bar; everything lands in ``RUN``):

1. **Demonstrations**: the scripted expert (:mod:`cgail_learning.expert`) drives every
   start x target pair of the demonstration target sets (by default set 0 and every training
   set), recorded as demo bags (``RUN/demos/seed_<s>``, replayable with ``cgail train --demos``).
2. **Training, static**: C-GAIL (the ``cgail`` preset: the paper's mechanics and weights) starts
   from a committed policy (fine-tuning; ``--base``), with the training envs spread over several
   target sets of this anatomy (``EnvConfig.scenario_seed``). It opens with a behavioural-cloning
   warm start on the demonstrations (``--bc-epochs``,
   :meth:`~cgail_learning.trainer.Trainer.pretrain_bc`), validated like every later
   checkpoint, and, while that validation is under the static goal plus 5 points, a round of
   DAgger (``--dagger-rounds``, :mod:`cgail_learning.dagger`): the warm-started policy
   drives the training sets, the expert labels the states it reaches, and the warm start is
   redone on the demonstrations plus the labels. Every ``eval_every`` steps the deterministic
   policy is validated on *validation* target sets through the simulated EM tracker; the best
   one is kept. Static training goes on
   until it has held the static goal twice in a row (the warm start counts) and both goals are
   held or half the budget is spent, at most until ``static_share`` of the budget (less the
   time kept for the final evaluation).
3. **Training, dynamic** (only while the static policy misses the dynamic goal on the
   validation set and the budget lasts): the expert first demonstrates the first 4 training
   sets in the beating, deforming aorta (``RUN/demos/dynamic_seed_<s>``), then the same warm
   start and C-GAIL on those demonstrations, in the beating aorta, starting from the best
   static policy (with under 3 min left: no demonstrations and no warm start). A dynamic
   checkpoint replaces the best static policy as the dynamic one only if its validation is
   better.
4. **Export**: ``RUN/policy_static.onnx`` and ``RUN/policy_dynamic.onnx`` with their catheter
   contracts (the anatomy identified by its content hash).
5. **Evaluation** on *unseen* targets (a test target set used neither for training nor for
   validation), static and dynamic, through the simulated EM tracker, with the centerline
   follower and the un-tuned base policy beside the planner
   (:mod:`cgail_learning.evaluate`).
6. **Report**: ``RUN/report.md`` (figures, tables, plots, the exact commands that start the
   simulated rig with its GUI, and the planner on a real rig) and ``RUN/plan.yaml``.

``--budget-min`` bounds the whole run: training stops as soon as the validation reaches both
goals, or when what is left of the budget is what the final evaluation is expected to take
(timed from the validations, which run the same trials). Exit status: 0 the planner reaches
both goals on the unseen targets; 1 it does not (everything is still written; the report says
which goal was missed); 2 the input could not be used (one line on stderr says why).

Why the warm start: the paper trains C-GAIL for hours. Within minutes, fine-tuning the committed
policy with C-GAIL alone from 60 demonstrations plateaued at 64-69% static success on unseen
targets of a CT patient: the policy followed the branch centerline and missed targets lying
~10 mm off it. In-loop BC runs at ``strength x lr`` (4e-5) on one buffer of demos per update and
cannot move the policy that far; 30 epochs of BC on the demonstrations of all 17 target sets
(~20 s) reach the goals on that patient before the first C-GAIL step. C-GAIL then fine-tunes
it, and the best validated checkpoint is kept, so the warm start is also the fallback.

Why DAgger: cloning learns the expert's actions on the expert's own states. On the mesh patient
the warm-started policy validated at 93% and missed 4 of 45 unseen targets, each a collision
within 12 mm of a target lying ~10 mm off the branch centerline, where its path had drifted
from any demonstrated one. One round of the expert's labels on the policy's own states (every
4th state of the 240 training episodes, ~22,600 labels, ~160 s) took the validation to 100%
and the unseen targets to 45/45. It runs only when the warm start leaves the validation under
the goal plus 5 points (the CT patient's warm start validates at 100%).

Why several target sets: the paper trains on 5 fixed targets. A planner for a patient must
reach targets it was not trained on (the clinician picks one at the rig), and a policy trained on
5 points generalises poorly; training over a few sets of 5 costs nothing extra.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
import math
from pathlib import Path
import sys
import time
from typing import Any, TYPE_CHECKING

import numpy as np

from cgail_sim.cli_help import tool_parser

if TYPE_CHECKING:
    from cgail_learning.demos import Demos

__all__ = ['PlanOptions', 'PlanResult', 'build_parser', 'main', 'plan_patient']

_PROG = 'cgail plan-patient'
_DYNAMIC_MARGIN = 0.10
"""How far the static policy's dynamic validation must clear the dynamic goal to skip the
dynamic phase: it runs 30 trials, and a mesh-patient run that stopped at exactly 80% measured
67% on the unseen targets."""
_STATIC_MARGIN = 0.05
"""A DAgger round follows the warm start while its static validation is under the static goal
plus this margin: the validation's 45 trials pick the best of several checkpoints, so a policy
validated just at the goal measured 91-93% on the unseen targets of the mesh patient."""
_DAGGER_EVERY = 4
"""Label every 4th state of the learner's episodes (:func:`~cgail_learning.dagger.
expert_labels`): on the mesh patient, labelling every state took 385 s for the same result."""
_DYNAMIC_DEMOS_MIN_S = 180.0
"""Budget left (s) under which the dynamic phase reuses the static demonstrations rather than
record its own (4 target sets in the beating aorta take ~75 s on one core)."""


def committed_policy(name: str = 'cgail_default_static') -> Path:
    """A policy committed with the package (``cgail_planner/models/<name>.onnx``)."""
    import cgail_planner

    return Path(cgail_planner.__file__).resolve().parent / 'models' / f'{name}.onnx'


@dataclass(frozen=True)
class PlanOptions:
    """Settings of one ``plan_patient`` run (every one is a command-line option)."""

    budget_min: float = 15.0
    """Wall-clock budget of the whole run, minutes (training stops early enough for the final
    evaluation, timed from the validations); in [1, 1440]."""
    base: str = ''
    """Policy the training starts from: an exported ``.onnx`` or a ``train`` checkpoint;
    '' = the committed default static policy; 'scratch' = random initialisation."""
    preset: str = 'cgail'
    """Training preset (name or YAML path, :func:`cgail_learning.config.load_config`);
    its ``max_steps`` is ignored (the budget decides), its other settings hold."""
    goal_static: float = 0.95
    """Success rate wanted on unseen targets in the rigid aorta; in (0, 1]."""
    goal_dynamic: float = 0.80
    """Success rate wanted on unseen targets in the beating aorta; in (0, 1]."""
    train_seeds: tuple[int, ...] = tuple(range(3, 19))
    """Target sets trained on (``EnvConfig.scenario_seed``), one training env each."""
    demo_seeds: tuple[int, ...] = (0, *range(3, 19))
    """Target sets the expert demonstrates every start x target pair of (0 is the set the
    rig's phantom offers; the others are the training sets)."""
    bc_epochs: int = 30
    """Epochs of the behavioural-cloning warm start on the demonstrations, before C-GAIL
    (:meth:`~cgail_learning.trainer.Trainer.pretrain_bc`); 0: none."""
    dagger_rounds: int = 1
    """DAgger rounds after the warm start, each only while the static validation is under the
    static goal plus 5 points: the warm-started policy drives every start x target pair of the
    training sets, the expert labels the states it reaches, and the warm start is redone on
    the demonstrations plus those labels (:mod:`cgail_learning.dagger`); 0: none."""
    validation_seeds: tuple[int, ...] = (20, 21, 22, 23, 24)
    """Target sets of the periodic validation (selects the policy, stops the training); the
    beating-aorta validation uses the first two (it costs ~30x more per step)."""
    test_seeds: tuple[int, ...] = (1, 2, 30)
    """Target sets of the final evaluation: unseen by training and validation."""
    eval_every: int = 40_960
    """Training steps between validations."""
    trials: int = 15
    """Evaluation trials per test target set, method and mode (trial k: start k % 3, target
    (k // 3) % 5: 15 covers every pair once)."""
    seed: int = 0
    """Seed of the demonstrations, the training and the evaluation."""
    threads: int = 1
    """torch CPU threads."""
    jobs: int = 0
    """Processes recording the expert's demonstrations, one target set each at a time (0: one
    per CPU core this process may use)."""
    static_share: float = 0.7
    """Share of the budget (from the start) after which static training hands over to the
    dynamic phase while the static goal is still missed; in (0, 1]."""

    def __post_init__(self) -> None:
        def check(ok: bool, name: str, expected: str) -> None:
            if not ok:
                raise ValueError(f'{name} must be {expected}, found {getattr(self, name)!r}')

        check(math.isfinite(self.budget_min) and 1.0 <= self.budget_min <= 1440.0,
              'budget_min', 'in [1, 1440] minutes')
        for name in ('goal_static', 'goal_dynamic'):
            check(0.0 < getattr(self, name) <= 1.0, name, 'in (0, 1]')
        for name in ('train_seeds', 'demo_seeds', 'validation_seeds', 'test_seeds'):
            seeds = getattr(self, name)
            check(isinstance(seeds, tuple) and len(seeds) >= 1 and all(
                isinstance(x, int) and x >= 0 for x in seeds), name, 'one or more ints >= 0')
        check(len(self.train_seeds) <= 64, 'train_seeds', 'at most 64 target sets')
        held = set(self.validation_seeds) | set(self.test_seeds)
        check(not held & (set(self.train_seeds) | set(self.demo_seeds)), 'test_seeds',
              f'target sets apart from the training ones {self.train_seeds} and '
              f'{self.demo_seeds} (validation {self.validation_seeds})')
        check(not set(self.validation_seeds) & set(self.test_seeds), 'test_seeds',
              f'target sets apart from validation_seeds {self.validation_seeds}')
        check(self.eval_every >= 1024, 'eval_every', '>= 1024')
        check(isinstance(self.bc_epochs, int) and 0 <= self.bc_epochs <= 1000, 'bc_epochs',
              'an int in [0, 1000]')
        check(isinstance(self.dagger_rounds, int) and 0 <= self.dagger_rounds <= 10,
              'dagger_rounds', 'an int in [0, 10]')
        check(1 <= self.trials <= 1000, 'trials', 'in [1, 1000]')
        check(1 <= self.threads <= 64, 'threads', 'in [1, 64]')
        check(isinstance(self.jobs, int) and 0 <= self.jobs <= 256, 'jobs',
              'an int in [0, 256] (0: one per CPU core)')
        check(0.0 < self.static_share <= 1.0, 'static_share', 'in (0, 1]')


@dataclass
class PlanResult:
    """What a run produced and measured."""

    out: Path
    success: dict[str, dict[str, float]] = field(default_factory=dict)
    """mode -> method -> success rate on the unseen targets."""
    faults: dict[str, dict[str, int]] = field(default_factory=dict)
    """mode -> method -> episodes of the final evaluation that ended in a simulation fault
    (counted as failures in ``success``)."""
    goals_met: bool = False
    timings_s: dict[str, float] = field(default_factory=dict)
    """Wall time of each stage, s."""
    history: list[dict[str, Any]] = field(default_factory=list)
    """One row per validation: phase, wall s, steps, static / dynamic success."""


class _Clock:
    """Wall time since the start, the budget's deadline, and the time the final evaluation
    will need (kept free of training)."""

    def __init__(self, budget_s: float) -> None:
        self.t0 = time.monotonic()
        self.budget_s = budget_s
        self.deadline = self.t0 + budget_s
        self.eval_trials: dict[str, int] = {}
        """Trials the final evaluation runs per mode (all methods)."""
        self.trial_s: dict[str, float] = {}
        """Seconds per trial per mode, as the latest validation measured them."""

    def now(self) -> float:
        return time.monotonic() - self.t0

    def reserve(self) -> float:
        """Seconds to keep for the final evaluation (0 until a validation ran): its trials at
        the validations' pace, plus a quarter and 15 s for export, plots and reports (a fresh
        clone's mesh patient ran 11 s over a 15-min budget with the bare estimate)."""
        est = sum(self.trial_s.get(m, 0.0) * n for m, n in self.eval_trials.items())
        return 1.25 * est + 15.0 if est > 0 else 0.0

    def left(self) -> float:
        """Seconds of the budget left for demonstrations and training."""
        return self.deadline - time.monotonic() - self.reserve()

    def stamp(self) -> str:
        s = int(self.now())
        return f'[{s // 60:2d}:{s % 60:02d}]'


def _validate(policy: Callable[[np.ndarray], np.ndarray], envs: Sequence[Any],
              seed: int) -> float:
    """Success rate of a deterministic policy over every start x target pair of each env's
    target set, through the simulated EM tracker as in the final evaluation (a policy that
    only just reaches the 10 mm sphere noise-free is not selected for it)."""
    from cgail_learning.evaluate import run_trials, TrackingNoise

    wins = []
    for env in envs:
        sc = env.unwrapped.engine.scenarios
        wins += [t.success for t in run_trials(env, policy, len(sc.starts) * len(sc.targets),
                                               seed, noise=TrackingNoise())]
    return float(np.mean(wins))


def _demo_set(anatomy: str, mode: str, scenario_seed: int, seed: int, out: Path
              ) -> tuple[list[tuple[np.ndarray, np.ndarray]], float, int]:
    """Expert demonstrations of every start x target pair of one target set, written as one
    demo bag; returns the successful episodes' (obs, act) pairs, the success rate and the
    number of episodes (a worker of :func:`_record_demos`)."""
    from cgail_learning.demo_bags import write_demo_bag
    from cgail_learning.demos_cli import Pairs, record_episodes
    from cgail_sim.anatomy_spec import anatomy_label
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    pairs: Pairs = []
    env = CatheterNavEnv(EnvConfig(mode=mode, anatomy=anatomy, scenario_seed=scenario_seed))
    sc = env.scenarios
    n = len(sc.starts) * len(sc.targets)
    episodes, stats = record_episodes(env, n, seed, pairs)
    prefix = 'seed' if mode == 'static' else f'{mode}_seed'
    write_demo_bag(out / 'demos' / f'{prefix}_{scenario_seed}', episodes,
                   anatomy=anatomy_label(anatomy), mode=mode, dt=env.config.dt,
                   anatomy_hash=env.anatomy.content_hash, anatomy_path=anatomy,
                   scenario_seed=scenario_seed)
    return pairs, float(stats['success_rate']), n


def _jobs(options: PlanOptions, tasks: int) -> int:
    """Worker processes for ``tasks`` independent jobs: ``options.jobs``, or one per CPU core
    this process may use (0), never more than the tasks."""
    import os

    cores = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else \
        (os.cpu_count() or 1)
    return max(1, min(tasks, options.jobs or cores))


def _record_demos(anatomy: str, options: PlanOptions, out: Path, log: Callable[[str], None],
                  mode: str = 'static', seeds: Sequence[int] | None = None
                  ) -> tuple[Demos, dict[str, float]]:
    """Expert demonstrations of every start x target pair of each target set (default
    ``options.demo_seeds``) in ``mode``, one bag per set (``demos/seed_<s>``, dynamic:
    ``demos/dynamic_seed_<s>``), the sets spread over ``options.jobs`` processes; returns the
    successful episodes' (obs, act) pairs in the order of the sets, their count, and
    statistics. Each set is a function of the anatomy, the set and the seed alone, so the
    result does not depend on the number of processes."""
    from cgail_learning.demos import Demos

    sets = list(options.demo_seeds if seeds is None else seeds)
    done: dict[int, tuple[list[tuple[np.ndarray, np.ndarray]], float, int]] = {}

    def logged(s: int, res: tuple[list[tuple[np.ndarray, np.ndarray]], float, int]) -> None:
        done[s] = res
        log(f'expert, {mode}, target set {s}: {res[2]} episodes, success '
            f'{100 * res[1]:.0f}%')

    jobs = _jobs(options, len(sets))
    if jobs == 1:
        for s in sets:
            logged(s, _demo_set(anatomy, mode, s, options.seed, out))
    else:
        import concurrent.futures
        import multiprocessing

        with concurrent.futures.ProcessPoolExecutor(
                max_workers=jobs, mp_context=multiprocessing.get_context('spawn')) as pool:
            futures = {pool.submit(_demo_set, anatomy, mode, s, options.seed, out): s
                       for s in sets}
            for future in concurrent.futures.as_completed(futures):
                logged(futures[future], future.result())
    pairs = [pair for s in sets for pair in done[s][0]]
    if not pairs:
        from cgail_patient import PatientError

        raise PatientError(f'anatomy {anatomy}: expected the scripted expert to reach some '
                           'targets, found no successful demonstration: check the report of '
                           'cgail prepare-anatomy (lumen too narrow, bends too tight?)')
    obs = np.concatenate([o for o, _ in pairs])
    act = np.concatenate([a for _, a in pairs])
    return Demos(obs, act, len(pairs)), {
        'episodes': float(sum(done[s][2] for s in sets)),
        'expert_success': float(np.mean([done[s][1] for s in sets])),
        'samples': float(len(obs))}


def _train_phase(mode: str, anatomy: str, options: PlanOptions, out: Path, clock: _Clock,
                 demos: Demos, init: str, result: PlanResult,
                 log: Callable[[str], None], progress: bool, warm_start: bool = True,
                 incumbent: tuple[Path, float, float] | None = None
                 ) -> tuple[Path, float, float]:
    """Train in ``mode`` until the validation reaches the goals or the budget ends; returns the
    best validated checkpoint (the starting policy's when the budget allowed no training) and
    its static and dynamic validation success (NaN: not measured).

    ``warm_start``: open with the BC warm start on ``demos``. ``incumbent``: a checkpoint with
    its validated (static, dynamic) success that this phase must beat to replace (the dynamic
    phase starts from the best static policy and never exports anything worse).
    """
    import torch
    from tqdm import tqdm
    import yaml

    from cgail_learning.config import config_from_dict, config_to_dict, load_config
    from cgail_learning.envs import ConcatVecEnv
    from cgail_learning.logger import ScalarLogger
    from cgail_learning.train import sim_metadata
    from cgail_learning.trainer import Trainer
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv
    from cgail_sim.vec_env import CatheterNavVecEnv

    torch.set_num_threads(options.threads)
    # the beating wall is ~30x slower per env: the dynamic phase trains on the first 4 sets
    seeds = options.train_seeds if mode == 'static' else options.train_seeds[:4]
    d = config_to_dict(load_config(options.preset))
    d['max_steps'] = 50_000_000  # (the budget stops the run; the schedules barely decay)
    d['num_envs'] = len(seeds)
    d['checkpoint_every'] = 0
    if init:
        # No theta_max curriculum when fine-tuning: the base policy was trained through it and
        # runs at the contract's theta_max (the validation env's); with it, success over 0.6
        # moved the training envs to 75 deg, where every training episode failed (training
        # success 0.00 for the rest of a 10-minute run on the elongated patient).
        d['curriculum'] = {}
    cfg = config_from_dict(d)
    env = ConcatVecEnv([CatheterNavVecEnv(EnvConfig(mode=mode, anatomy=anatomy, scenario_seed=s),
                                          1) for s in seeds])
    trainer = Trainer(cfg, env, demo_obs=demos.obs, demo_act=demos.act, seed=options.seed,
                      demo_episodes=demos.episodes,
                      metadata={**sim_metadata(EnvConfig(mode=mode, anatomy=anatomy)),
                                'preset': cfg.name})
    if init:
        trainer.load_weights(Path(init))
    val = {m: [CatheterNavEnv(EnvConfig(mode=m, anatomy=anatomy, scenario_seed=s))
               for s in options.validation_seeds[:None if m == 'static' else 2]]
           for m in ('static', 'dynamic')}
    goal = {'static': options.goal_static, 'dynamic': options.goal_dynamic}
    run = out / 'train' / mode
    logger = ScalarLogger(run)
    (run / 'config.yaml').write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
    state: dict[str, Any] = {'streak': 0, 'key': (-1.0, -1.0), 'best': None,
                             'dyn_measured': False}  # streak: validations at the static goal
    if incumbent is not None:
        inc_s, inc_d = incumbent[1], 0.0 if math.isnan(incumbent[2]) else incumbent[2]
        state.update(best=incumbent[0], dyn_measured=not math.isnan(incumbent[2]),
                     key=(inc_s, inc_d) if mode == 'static' else (inc_d, inc_s))

    def timed_validation(m: str) -> float:
        t = time.monotonic()
        rate = _validate(trainer.act_deterministic, val[m], options.seed)
        n = sum(len(e.scenarios.starts) * len(e.scenarios.targets) for e in val[m])
        clock.trial_s[m] = (time.monotonic() - t) / n
        return rate

    def validate_and_keep(scalars: dict[str, float]) -> bool:
        """Validate the current policy, keep it if it is the best so far; True: stop."""
        s_rate = timed_validation('static')
        d_rate = math.nan
        if s_rate >= goal['static'] or mode == 'dynamic':
            d_rate = timed_validation('dynamic')
        scalars.update({'validation/static_success': s_rate,
                        'validation/dynamic_success': d_rate})
        logger.log(trainer.step, scalars)
        result.history.append({'phase': mode, 'wall_s': clock.now(),
                               'steps': float(trainer.step), 'static': s_rate,
                               'dynamic': d_rate})
        key = (s_rate, 0.0 if math.isnan(d_rate) else d_rate)
        if mode == 'dynamic':
            key = (key[1], key[0])
        if key >= state['key']:
            state.update(key=key, dyn_measured=not math.isnan(d_rate), best=run / 'best.pt')
            trainer.save(run / 'best.pt')
        state['streak'] = state['streak'] + 1 if s_rate >= goal['static'] else 0
        if mode == 'static' and state['streak'] >= 2 and \
                d_rate >= goal['dynamic'] + _DYNAMIC_MARGIN:
            return True  # both goals: done
        usable = clock.budget_s - clock.reserve()  # (the evaluation's time is not training's)
        if mode == 'static' and state['streak'] >= 2 and clock.now() >= 0.5 * usable:
            return True  # static holds its goal: the dynamic phase takes over
        if mode == 'dynamic' and s_rate >= goal['static'] and d_rate >= goal['dynamic']:
            return True
        # (static: past static_share of the budget the dynamic phase gets the rest)
        return mode == 'static' and clock.now() >= options.static_share * usable

    stop = False
    if warm_start and options.bc_epochs > 0:
        t_warm = time.monotonic()
        warm = trainer.pretrain_bc(options.bc_epochs)
        result.timings_s['bc_warm_start'] = time.monotonic() - t_warm
        stop = validate_and_keep(warm)
        row = result.history[-1]
        row['warm_start'] = True
        log(f'warm start: behavioural cloning, {options.bc_epochs} epochs on '
            f'{len(demos.obs)} demonstration pairs (loss {warm["losses/bc_pretrain_loss"]:.3f}), '
            f'validation (static, dynamic) '
            f'{_fmt_key((row["static"], row["dynamic"]), not math.isnan(row["dynamic"]))}')
        if mode == 'static':
            stop = _dagger(trainer, init, anatomy, options, clock, result, log,
                           validate_and_keep) or stop
    next_eval = options.eval_every
    with tqdm(total=max(1, int(clock.left())), disable=not progress, unit='s',
              desc=f'{_PROG}: training ({mode})', dynamic_ncols=True,
              bar_format='{desc}: {percentage:3.0f}%|{bar}| {n}/{total} s budget '
                         '{postfix}') as bar:
        while not stop and clock.left() > 0:
            scalars = trainer.train_iteration()
            bar.n = min(bar.total, int(bar.total - max(clock.left(), 0)))
            if trainer.step < next_eval:
                logger.log(trainer.step, scalars)
                bar.set_postfix_str(f'{trainer.step} steps, best validation '
                                    f'{_fmt_key(state["key"])}')
                continue
            next_eval += options.eval_every
            stop = validate_and_keep(scalars)
            bar.set_postfix_str(f'{trainer.step} steps, best validation '
                                f'{_fmt_key(state["key"])}')
    best_key, best, best_dyn_measured = state['key'], state['best'], state['dyn_measured']
    if best is None:  # the budget ended before the first validation: validate what there is
        s_rate = _validate(trainer.act_deterministic, val['static'], options.seed)
        result.history.append({'phase': mode, 'wall_s': clock.now(),
                               'steps': float(trainer.step), 'static': s_rate,
                               'dynamic': math.nan})
        best_key = (s_rate, 0.0) if mode == 'static' else (0.0, s_rate)
        best = run / 'best.pt'
        trainer.save(best)
        log(f'warning: the budget ended after {trainer.step} training steps, before the first '
            f'validation at {options.eval_every}: a larger --budget-min trains longer')
    logger.close()
    key = best_key if mode == 'static' else best_key[::-1]
    log(f'training ({mode}): {trainer.step} steps, best validation (static, dynamic) '
        f'{_fmt_key(key, best_dyn_measured)}')
    return best, key[0], key[1] if best_dyn_measured else math.nan


def _dagger(trainer: Any, init: str, anatomy: str, options: PlanOptions, clock: _Clock,
            result: PlanResult, log: Callable[[str], None],
            validate_and_keep: Callable[[dict[str, float]], bool]) -> bool:
    """The DAgger rounds that follow the static warm start (``options.dagger_rounds``); returns
    the last validation's stop decision.

    Each round runs while the latest static validation is under the goal plus
    :data:`_STATIC_MARGIN`: the current policy drives every start x target pair of each
    training set, the expert labels every :data:`_DAGGER_EVERY`-th state it reaches, and the
    warm start is redone from the base policy on the demonstrations plus every label so far
    (DAgger trains on the aggregate). Labelling ends early at half the usable budget, so
    C-GAIL and the dynamic phase keep theirs. Measured on the mesh patient (one round, every
    4th state, ~160 s): static validation 93% -> 100%, unseen targets 91% -> 100%.
    """
    from cgail_learning.dagger import expert_labels
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    envs = [CatheterNavEnv(EnvConfig(mode='static', anatomy=anatomy, scenario_seed=s))
            for s in options.train_seeds]
    labels: list[tuple[np.ndarray, np.ndarray]] = []
    stop = False

    def late() -> bool:
        return clock.now() >= 0.5 * (clock.budget_s - clock.reserve())

    for k in range(options.dagger_rounds):
        if result.history[-1]['static'] >= options.goal_static + _STATIC_MARGIN or late():
            break
        t0 = time.monotonic()
        wins, n_eps = 0.0, 0.0
        for env in envs:
            sc = env.scenarios
            o, a, st = expert_labels(env, trainer.act_deterministic,
                                     len(sc.starts) * len(sc.targets), options.seed + 1000 * k,
                                     _DAGGER_EVERY, stop=late)
            labels.append((o, a))
            wins += st['policy_success'] * st['episodes'] if st['episodes'] else 0.0
            n_eps += st['episodes']
        obs = np.concatenate([o for o, _ in labels])
        act = np.concatenate([a for _, a in labels])
        if init:
            trainer.load_weights(Path(init))
        stats = trainer.pretrain_bc(options.bc_epochs, extra=(obs, act))
        result.timings_s['dagger'] = result.timings_s.get('dagger', 0.0) + \
            time.monotonic() - t0
        stop = validate_and_keep(stats)
        row = result.history[-1]
        row['dagger'] = k + 1
        log(f'DAgger round {k + 1}: the policy reached {100 * wins / max(n_eps, 1):.0f}% of '
            f'{int(n_eps)} training episodes; {len(obs)} expert labels of its states, '
            f'{time.monotonic() - t0:.0f} s; validation (static, dynamic) '
            f'{_fmt_key((row["static"], row["dynamic"]), not math.isnan(row["dynamic"]))}')
    return stop


def _row_tag(row: dict[str, Any]) -> str:
    """What a history row validated before C-GAIL's first step ('' for a C-GAIL checkpoint)."""
    if row.get('dagger'):
        return f'DAgger round {row["dagger"]}'
    return 'BC warm start' if row.get('warm_start') else ''


def _row_label(row: dict[str, Any]) -> str:
    """The phase of a history row as the report names it."""
    return f'{row["phase"]} ({_row_tag(row)})' if _row_tag(row) else row['phase']


def _fmt_key(key: tuple[float, float], second: bool = True) -> str:
    """'static% / dynamic%' of a validation key; ``second`` False: the second was not
    measured ('-')."""
    if key[0] < 0:
        return '-'
    return f'{100 * key[0]:.0f}% / ' + (f'{100 * key[1]:.0f}%' if second else '-')


def plan_patient(anatomy_dir: Path, out: Path, options: PlanOptions | None = None, *,
                 log: Callable[[str], None] | None = None, progress: bool = True) -> PlanResult:
    """Run the whole pipeline (module docstring); see :func:`main` for the exit status.

    Raises:
        AnatomyError: the anatomy cannot be loaded or has no scenarios (one line).
        LearningError: a preset or base policy that cannot be used (one line).
        ValueError: bad options (one line).
    """
    from cgail_learning.evaluate import (
        CenterlineFollower,
        run_trials,
        summarize,
        TrackingNoise,
        write_report,
    )
    from cgail_learning.export import export_checkpoint
    from cgail_planner.core.onnx_policy import OnnxPolicy
    from cgail_sim.anatomy_spec import check_anatomy_spec
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv
    from cgail_sim.worlds import load_world

    options = options or PlanOptions()
    clock = _Clock(60.0 * options.budget_min)

    def say(line: str) -> None:
        (log or (lambda s: print(f'{_PROG}: {s}', file=sys.stderr, flush=True)))(
            f'{clock.stamp()} {line}')

    anatomy = str(Path(anatomy_dir).expanduser().resolve())
    check_anatomy_spec(anatomy)
    from cgail_learning.config import load_config

    load_config(options.preset)  # a bad preset fails before the demonstrations
    base = options.base or str(committed_policy())
    if base != 'scratch' and not Path(base).is_file():
        from cgail_learning.errors import PolicyLoadError

        raise PolicyLoadError(f'--base: expected an exported .onnx policy or a train '
                              f'checkpoint, or "scratch", found no file at {base}')
    for s in sorted({*options.train_seeds, *options.demo_seeds, *options.validation_seeds,
                     *options.test_seeds}):
        load_world(anatomy, seed=s)  # an anatomy without scenarios fails here, in one line
    out.mkdir(parents=True, exist_ok=True)
    if (out / 'plan.yaml').exists():
        raise ValueError(f'--out {out}: expected a new run directory, found an earlier run '
                         '(plan.yaml); choose another --out or remove it')
    result = PlanResult(out=out)
    per_method = options.trials * len(options.test_seeds)
    clock.eval_trials = {'static': per_method * (3 if base.endswith('.onnx') else 2),
                         'dynamic': per_method * 2}
    say(f'anatomy {anatomy}, budget {options.budget_min:g} min, base '
        f'{"random" if base == "scratch" else base}')

    demos, demo_stats = _record_demos(anatomy, options, out, say)
    result.timings_s['demonstrations'] = clock.now()
    say(f'demonstrations: {int(demo_stats["samples"])} (obs, act) pairs from '
        f'{int(demo_stats["episodes"])} expert episodes')
    init = '' if base == 'scratch' else base
    best_static, static_rate, dynamic_rate = _train_phase('static', anatomy, options, out, clock,
                                                          demos, init, result, say, progress)
    best_dynamic = None
    if clock.left() > 0 and not dynamic_rate >= options.goal_dynamic + _DYNAMIC_MARGIN:
        # (NaN: not measured)
        result.timings_s['dynamic_start'] = clock.now()
        dyn_demos = None
        if clock.left() >= _DYNAMIC_DEMOS_MIN_S:
            # the beating wall's own demonstrations: BC on static ones leaves the tip to
            # collide with the moving root (mesh patient: 76% dynamic on unseen targets from the
            # static policy; 89% after BC on dynamic demonstrations of 4 sets, 82% with the
            # static ones mixed in)
            from cgail_patient import PatientError

            try:
                d_demos, d_stats = _record_demos(anatomy, options, out, say, mode='dynamic',
                                                 seeds=options.train_seeds[:4])
            except PatientError:
                say('warning: the expert reached no target in the beating aorta; the dynamic '
                    'phase runs without a warm start')
            else:
                dyn_demos = d_demos
                demo_stats.update({f'dynamic_{k}': v for k, v in d_stats.items()})
                say(f'demonstrations, dynamic: {len(d_demos.obs)} (obs, act) pairs from '
                    f'{int(d_stats["episodes"])} expert episodes')
        else:
            say(f'dynamic phase without a warm start: {clock.left():.0f} s left, under the '
                f'{_DYNAMIC_DEMOS_MIN_S:.0f} s that recording dynamic demonstrations needs')
        # (a warm start on the static demonstrations in the beating aorta measured 30%
        # dynamic validation on the mesh patient, against 77% for the static policy)
        best_dynamic, _, _ = _train_phase(
            'dynamic', anatomy, options, out, clock, dyn_demos or demos, str(best_static),
            result, say, progress, warm_start=dyn_demos is not None,
            incumbent=(best_static, static_rate, dynamic_rate))
    result.timings_s['training'] = clock.now() - result.timings_s['demonstrations']

    policies = {'static': export_checkpoint(best_static, out / 'policy_static.onnx')}
    policies['dynamic'] = export_checkpoint(best_dynamic or best_static,
                                            out / 'policy_dynamic.onnx')
    t_eval = time.monotonic()
    noise = TrackingNoise()
    methods: dict[str, dict[str, Any]] = {m: {'C-GAIL (this run)': OnnxPolicy(policies[m]),
                                              'centerline': None} for m in policies}
    if base.endswith('.onnx'):  # the base policy before tuning, beside it (static: cheap)
        methods['static']['C-GAIL (base, not tuned)'] = OnnxPolicy(base)
    all_results: dict[str, dict[str, Any]] = {}
    for mode in ('static', 'dynamic'):
        res: dict[str, list[Any]] = {name: [] for name in methods[mode]}
        for s in options.test_seeds:
            env = CatheterNavEnv(EnvConfig(mode=mode, anatomy=anatomy, scenario_seed=s))
            for name, method in methods[mode].items():
                res[name] += run_trials(env, method or CenterlineFollower(env), options.trials,
                                        10_000 + options.seed, noise=noise)
        for name, trials in res.items():
            stats = summarize(trials)
            rate = stats['success_rate']
            result.success.setdefault(mode, {})[name] = rate
            result.faults.setdefault(mode, {})[name] = stats['faults']
            faults = f', {stats["faults"]} simulation faults' if stats['faults'] else ''
            say(f'evaluation, {mode}, unseen targets: {name} {100 * rate:.0f}% '
                f'({len(trials)} trials{faults})')
        all_results[mode] = res
    result.timings_s['evaluation'] = time.monotonic() - t_eval
    write_report(all_results, out / 'evaluation',
                 f'Anatomy `{anatomy}`. Unseen targets: target sets '
                 f'{list(options.test_seeds)}, {options.trials} trials each per method, through '
                 f'the simulated EM tracker ({noise.position_mm:g} mm / '
                 f'{noise.orientation_deg:g} deg RMS).')
    ours = {m: result.success[m]['C-GAIL (this run)'] for m in ('static', 'dynamic')}
    result.goals_met = ours['static'] >= options.goal_static and \
        ours['dynamic'] >= options.goal_dynamic
    result.timings_s['total'] = clock.now()
    _write_record(result, anatomy, base, options, demo_stats, policies)
    _plot_history(result, options, out / 'training.png')
    _write_report(result, anatomy, base, options, demo_stats, policies)
    say(f'{"goals met" if result.goals_met else "goals NOT met"}: static '
        f'{100 * ours["static"]:.0f}% (goal {100 * options.goal_static:.0f}%), dynamic '
        f'{100 * ours["dynamic"]:.0f}% (goal {100 * options.goal_dynamic:.0f}%); report '
        f'{out / "report.md"}')
    return result


def rig_commands(anatomy: str, policies: dict[str, Path]) -> list[str]:
    """The commands that run this anatomy and policy: the simulated in-vitro session with the
    guidance GUI (static, dynamic), the free-running simulated rig (``cgail launch``, GUI
    included), and the planner and GUI nodes of a real rig."""
    static, dynamic = (str(Path(policies[m]).resolve()) for m in ('static', 'dynamic'))
    return [
        f'scripts/ws cgail session --anatomy {anatomy} --policy {static} '
        f'--mode static --trials 1 --gui --out runs/session_static',
        f'scripts/ws cgail session --anatomy {anatomy} --policy {dynamic} '
        f'--mode dynamic --trials 1 --gui --out runs/session_dynamic',
        f'scripts/ws cgail launch src/cgail_rig/launch/sim_rig.launch.yaml '
        f'--in-process anatomy:={anatomy} policy_path:={static}',
        f'scripts/ros2run cgail_planner planner_node --ros-args -p anatomy:={anatomy} '
        f'-p policy_path:={static}',
        f'scripts/ros2run cgail_gui gui_node --ros-args -p anatomy:={anatomy}',
    ]


def _write_record(result: PlanResult, anatomy: str, base: str, options: PlanOptions,
                  demo_stats: dict[str, float], policies: dict[str, Path]) -> None:
    import yaml

    from cgail_sim.anatomy_spec import anatomy_identity

    label, content_hash = anatomy_identity(anatomy)
    record = {
        'anatomy': anatomy, 'anatomy_label': label, 'anatomy_hash': content_hash,
        'base': base, 'options': {k: list(v) if isinstance(v, tuple) else v
                                  for k, v in asdict(options).items()},
        'demonstrations': demo_stats, 'timings_s': {k: round(v, 1) for k, v in
                                                    result.timings_s.items()},
        'success_unseen_targets': result.success, 'simulation_faults': result.faults,
        'goals_met': result.goals_met,
        'policies': {m: str(p) for m, p in policies.items()},
        'validation_history': result.history,
    }
    (result.out / 'plan.yaml').write_text(yaml.safe_dump(record, sort_keys=False))


def _plot_history(result: PlanResult, options: PlanOptions, path: Path) -> None:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    h = result.history
    t = [r['wall_s'] / 60.0 for r in h]
    ax.plot(t, [100 * r['static'] for r in h], 'o-', markersize=8, label='static (validation)')
    td = [(r['wall_s'] / 60.0, 100 * r['dynamic']) for r in h if not math.isnan(r['dynamic'])]
    if td:
        ax.plot(*zip(*td, strict=True), 's-', markersize=4, label='dynamic (validation)')
    for r in h:
        if _row_tag(r):
            ax.annotate(_row_tag(r), (r['wall_s'] / 60.0, 100 * r['static']),
                        xytext=(0, -28), textcoords='offset points', ha='center', fontsize=7,
                        arrowprops={'arrowstyle': '->', 'color': '0.4'})
    for goal, style, what in ((options.goal_static, ':', 'static goal'),
                              (options.goal_dynamic, '--', 'dynamic goal')):
        ax.axhline(100 * goal, color='grey', linestyle=style, linewidth=0.8)
        ax.text(0.01, 100 * goal + 1, what, fontsize=7, color='grey',
                transform=ax.get_yaxis_transform())
    demos = result.timings_s.get('demonstrations', 0.0) / 60.0
    ax.axvspan(0.0, demos, color='0.92', zorder=0)
    ax.text(demos / 2, 50, 'expert\ndemos', fontsize=7, ha='center', color='0.4')
    xmax = max(options.budget_min, max(t, default=0.0))
    if 'dynamic_start' in result.timings_s:
        x = result.timings_s['dynamic_start'] / 60.0
        ax.axvline(x, color='k', linewidth=0.6)
        ax.text(x, 30, ' dynamic phase ', fontsize=8,
                ha='right' if x > 0.8 * xmax else 'left')
    ax.set_xlabel('wall time (min, from the start of the run)')
    ax.set_ylabel('success on validation targets (%)')
    ax.set_ylim(-3, 103)
    ax.set_xlim(0, xmax)
    ax.legend(loc='lower right', fontsize=8)
    ax.set_title('plan_patient: validation during training')
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _write_report(result: PlanResult, anatomy: str, base: str, options: PlanOptions,
                  demo_stats: dict[str, float], policies: dict[str, Path]) -> None:
    from cgail_sim.anatomy_spec import anatomy_identity

    label, content_hash = anatomy_identity(anatomy)
    ts = result.timings_s
    met = 'met' if result.goals_met else 'NOT met'
    phases = ' + '.join(dict.fromkeys(r['phase'] for r in result.history))
    cmds = rig_commands(anatomy, policies)
    warm = (f'; behavioural-cloning warm start {options.bc_epochs} epochs, '
            f'{ts["bc_warm_start"]:.0f} s' if 'bc_warm_start' in ts else '')
    if 'dagger' in ts:
        rounds = sum(1 for r in result.history if r.get('dagger'))
        warm += f'; DAgger, {rounds} round{"s" * (rounds > 1)}, {ts["dagger"]:.0f} s'

    lines = [
        f'# Planner for `{label}`', '',
        f'Anatomy `{anatomy}` (content hash `{content_hash}`). Base policy: '
        f'`{"random initialisation" if base == "scratch" else base}`; preset '
        f'`{options.preset}`; budget {options.budget_min:g} min; seed {options.seed}.', '',
        f'**Goals {met}** on unseen targets (target sets {list(options.test_seeds)}, used '
        f'neither for training, sets {list(options.train_seeds)} and demonstrations '
        f'{list(options.demo_seeds)}, nor for validation, sets '
        f'{list(options.validation_seeds)}): static >= {100 * options.goal_static:.0f}%, '
        f'dynamic >= {100 * options.goal_dynamic:.0f}%.', '',
        '| mode | ' + ' | '.join(result.success['static']) + ' |',
        '|---|' + '---|' * len(result.success['static']),
    ]
    for mode, rates in result.success.items():
        cells = [f'{100 * rates[m]:.0f}%' if m in rates else '-' for m in result.success['static']]
        lines.append(f'| {mode} | ' + ' | '.join(cells) + ' |')
    faulted = {f'{mode} {m}': k for mode, per in result.faults.items()
               for m, k in per.items() if k}
    lines += [
        '', f'Success over {options.trials * len(options.test_seeds)} trials per method and '
        'mode, through the simulated EM tracker. Simulation faults (episodes a blown-up wall '
        'ended, counted as failures): '
        + (', '.join(f'{k} ({v})' for k, v in faulted.items()) if faulted else 'none')
        + '. Details, timesteps, targeting errors and box '
        'plots: [evaluation/report.md](evaluation/report.md).', '',
        '## Time', '',
        '| stage | wall time |', '|---|---|',
        f'| demonstrations ({int(demo_stats["episodes"])} expert episodes, '
        f'{100 * demo_stats["expert_success"]:.0f}% successful) | '
        f'{ts["demonstrations"]:.0f} s |',
        f'| training ({phases}{warm}) | {ts["training"]:.0f} s |',
        f'| export + evaluation | {ts["evaluation"]:.0f} s |',
        f'| **total** | **{ts["total"]:.0f} s** |', '',
        '![validation during training](training.png)', '',
        '| phase | wall (s) | steps | static | dynamic |', '|---|---|---|---|---|',
    ]
    for r in result.history:
        dyn = '-' if math.isnan(r['dynamic']) else f'{100 * r["dynamic"]:.0f}%'
        lines.append(f'| {_row_label(r)} | {r["wall_s"]:.0f} | {int(r["steps"])} | '
                     f'{100 * r["static"]:.0f}% | {dyn} |')
    lines += [
        '', f'(validation: every start x target pair of target sets '
        f'{list(options.validation_seeds)} (dynamic: the first two) through the simulated EM '
        'tracker, deterministic policy; dynamic only once the static goal is reached)', '',
        '## Policies', '',
        f'- static: `{policies["static"]}`',
        f'- dynamic: `{policies["dynamic"]}`', '',
        '## Run it on the rig', '',
        'The simulated in-vitro session with the guidance GUI (it prints the GUI URL), rigid '
        'and beating phantom:', '', '```bash', *cmds[:2], '```', '',
        'The simulated rig running freely, GUI included (drive it with the gamepad or the '
        'page):', '', '```bash', cmds[2], '```', '',
        'On a real rig, the planner and the GUI with this anatomy and policy (the rig\'s device '
        'nodes as usual):', '', '```bash', *cmds[3:], '```', '',
    ]
    (result.out / 'report.md').write_text('\n'.join(lines))


def build_parser() -> argparse.ArgumentParser:
    """Command line of ``cgail plan-patient``."""
    d = PlanOptions()
    p = tool_parser('plan-patient', __doc__)
    p.add_argument('anatomy', type=Path,
                   help='prepared anatomy directory (cgail prepare-anatomy)')
    p.add_argument('--out', type=Path, required=True, help='run directory to create')
    p.add_argument('--budget-min', type=float, default=d.budget_min,
                   help='wall-clock budget of the whole run, minutes (training leaves time '
                        'for the final evaluation)')
    p.add_argument('--base', default=d.base,
                   help="policy to fine-tune (.onnx or train checkpoint; default: the committed "
                        "default static policy; 'scratch': random initialisation)")
    p.add_argument('--preset', default=d.preset, help='training preset (name or YAML)')
    p.add_argument('--goal-static', type=float, default=d.goal_static,
                   help='success rate wanted on unseen targets in the rigid aorta, in (0, 1] '
                        f'(default {d.goal_static:g})')
    p.add_argument('--goal-dynamic', type=float, default=d.goal_dynamic,
                   help='success rate wanted on unseen targets in the beating aorta, in (0, 1] '
                        f'(default {d.goal_dynamic:g})')
    p.add_argument('--trials', type=int, default=d.trials,
                   help='final evaluation trials per method, mode and test target set')
    p.add_argument('--seed', type=int, default=d.seed,
                   help='seed of the demonstrations, the training and the evaluation '
                        f'(default {d.seed})')
    for name, what in (('train', 'trained on'), ('demo', 'the expert demonstrates'),
                       ('validation', 'of the periodic validation'),
                       ('test', 'of the final evaluation (unseen)')):
        default = getattr(d, f'{name}_seeds')
        p.add_argument(f'--{name}-seeds', type=int, nargs='+', default=list(default),
                       metavar='S', help=f'target sets (EnvConfig.scenario_seed) {what}; '
                                         f'default {" ".join(map(str, default))}')
    p.add_argument('--bc-epochs', type=int, default=d.bc_epochs,
                   help='epochs of the behavioural-cloning warm start before C-GAIL (0: none)')
    p.add_argument('--dagger-rounds', type=int, default=d.dagger_rounds,
                   help='DAgger rounds after the warm start, while the static validation is '
                        'under the goal + 5 points (0: none)')
    p.add_argument('--threads', type=int, default=d.threads, help='torch CPU threads')
    p.add_argument('--jobs', type=int, default=d.jobs,
                   help='processes recording the expert demonstrations (default 0: one per '
                        'CPU core); the result does not depend on it')
    p.add_argument('--no-progress', action='store_true', help='no progress bar')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail plan-patient`` (exit status: module docstring)."""
    from cgail_learning.errors import LearningError
    from cgail_sim.anatomy import AnatomyError

    args = build_parser().parse_args(argv)
    try:
        options = PlanOptions(budget_min=args.budget_min, base=args.base, preset=args.preset,
                              goal_static=args.goal_static, goal_dynamic=args.goal_dynamic,
                              trials=args.trials, seed=args.seed, threads=args.threads,
                              jobs=args.jobs,
                              bc_epochs=args.bc_epochs, dagger_rounds=args.dagger_rounds,
                              train_seeds=tuple(args.train_seeds),
                              demo_seeds=tuple(args.demo_seeds),
                              validation_seeds=tuple(args.validation_seeds),
                              test_seeds=tuple(args.test_seeds))
        result = plan_patient(args.anatomy, args.out, options, progress=not args.no_progress)
    except (AnatomyError, LearningError, ValueError) as exc:
        print(f'{_PROG}: error: {exc}', file=sys.stderr)
        return 2
    return 0 if result.goals_met else 1


if __name__ == '__main__':
    sys.exit(main())

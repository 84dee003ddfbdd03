"""The evidence behind the in-silico study's reading: why its ordering differs from the paper's.

Run (from the workspace root, inside the workspace environment), after or beside the study::

    scripts/ws python bench/insilico_evidence.py                       # studies/insilico_authors
    scripts/ws python bench/insilico_evidence.py --study runs/my_study --no-run   # tables only

It reads a study made with ``--fresh-budgets`` (``bench/insilico_study.py``: every budget a run of
its own, ``<preset>/seed<S>/budget_<N>/``) and writes ``STUDY/evidence.md`` and
``STUDY/evidence_static_in_dynamic.png``:

- **Training** (every run's ``scalars.csv``): the best and the last periodic evaluation
  (noise-free, the training targets), and the highest training success
  (``environment/success_rate``, the stochastic policy over its last 100 episodes) with the last
  training episodes' mean length and extrinsic reward. A run whose training success never
  left 0 never reached a target while it trained.
- **Where the evaluations fail** (the study's evaluations on the training targets): successes,
  collisions, and the failures per start (trial k starts at start k % 3, as ``evaluate`` does).
- **The static policy in the beating aorta**: each run's static policy (``static.onnx``),
  evaluated without re-training in the dynamic simulator on the training targets
  (``evaluate --modes dynamic``, the study's trials and seeds), beside the study's static figure
  and its re-trained dynamic figure. It separates what the heartbeat does to a policy from what
  the study's 102,400 steps of dynamic re-training add. These evaluations run here (one process at
  a time, one thread each) into ``STUDY/evidence/static_policy_in_dynamic/``, and are skipped
  when done for the current policy (by its sha256, as the study records it). Policies with 0% on
  every static evaluation are not run (they cannot reach a target; a stalled ``paper_code``
  policy also takes its 20,000-step limit per trial).
- **How far the heartbeat moves the wall and the targets** in the dynamic simulator of each
  option set (``paper_code``, ``ours``): two heartbeats with the tip parked at a start, each
  target's largest displacement, the wall's, and how many wall vertices move more than 1 mm
  (seconds).

Re-running skips what is done; ``--no-run`` only rewrites the tables from what is there.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
import re
import subprocess
import sys

import insilico_study as study

WS = study.WS
BUDGET = re.compile(r'budget_(\d+)')
SEED = study.SEED_FOLDER
#: The study's training target set (scenario seed 0).
TRAINING = study.TRAINING_TARGETS
#: The starts of the paper's scenario (trial k: start k % STARTS).
STARTS = 3
#: The option sets whose heartbeats are measured (:func:`heartbeat_motion`).
MOTION_OPTIONS = ('paper_code', 'ours')


@dataclass(frozen=True)
class Run:
    """One budget of one preset and seed in a fresh-budget study."""

    preset: str
    seed: int
    budget: int
    folder: Path

    @property
    def name(self) -> str:
        return f'{self.preset} seed {self.seed} {self.budget:,}'


def find_runs(root: Path) -> list[Run]:
    """Every budget with a snapshot (its static training finished) under ``root``, in preset,
    seed and budget order.

    Raises:
        StudyError: ``root`` is not a study folder, or holds no fresh-budget run.
    """
    if not root.is_dir():
        raise study.StudyError(f'--study: expected a study folder, found no folder {root}')
    runs = []
    for snap in root.glob('*/seed*/budget_*/snapshot.json'):
        folder = snap.parent
        seed, budget = SEED.fullmatch(folder.parent.name), BUDGET.fullmatch(folder.name)
        if seed and budget:
            runs.append(Run(folder.parent.parent.name, int(seed[1]), int(budget[1]), folder))
    if not runs:
        raise study.StudyError(f'--study: expected runs of a study made with --fresh-budgets '
                               f'(<preset>/seed<S>/budget_<N>/snapshot.json), found none in '
                               f'{root}')
    return sorted(runs, key=lambda r: (r.preset, r.seed, r.budget))


def pct(x: float | None) -> str:
    return '-' if x is None else f'{100 * x:.0f}%'


def training_row(run: Run) -> list[str]:
    """Best and last periodic evaluation, highest training success, last episodes."""
    sc = study.read_scalars(run.folder / 'static' / 'scalars.csv')
    ev = sc.get('eval/success_rate', [])
    train = sc.get('environment/success_rate', [])
    length = sc.get('environment/episode_length', [])
    reward = sc.get('environment/episode_reward', [])
    best = max(ev, key=lambda r: (r[1], -r[0])) if ev else None
    return [run.preset, str(run.seed), f'{run.budget:,}',
            f'{pct(best[1])} at {best[0]:,}' if best else '-',
            f'{pct(ev[-1][1])} at {ev[-1][0]:,}' if ev else '-',
            pct(max(v for _, v in train)) if train else '-',
            f'{length[-1][1]:,.0f}' if length else '-',
            f'{reward[-1][1]:+.2f}' if reward else '-']


def failure_row(run: Run, mode: str) -> list[str] | None:
    """Successes, collisions, other failures and failures per start of one evaluation."""
    trials = study.load_trials(run.folder / f'eval_{mode}_targets{TRAINING}')
    if trials is None:
        return None
    fails = [k for k, t in enumerate(trials) if not t['success']]
    collisions = sum(bool(trials[k]['collision']) for k in fails)
    per_start = [sum(k % STARTS == s for k in fails) for s in range(STARTS)]
    return [run.preset, str(run.seed), f'{run.budget:,}', mode,
            f'{len(trials) - len(fails)}/{len(trials)}', str(collisions),
            str(len(fails) - collisions), ' / '.join(map(str, per_start))]


def rate(trials: list[dict] | None) -> float | None:
    return None if trials is None else sum(bool(t['success']) for t in trials) / len(trials)


def zero_shot_folder(root: Path, run: Run) -> Path:
    return root / 'evidence' / 'static_policy_in_dynamic' / run.preset / \
        f'seed{run.seed}_budget_{run.budget}'


def worth_running(runs: list[Run], run: Run) -> bool:
    """Whether a policy of ``run``'s preset ever succeeded in a static evaluation."""
    return any((rate(study.load_trials(folder)) or 0) > 0
               for r in runs if r.preset == run.preset
               for folder in r.folder.glob('eval_static_targets*'))


def run_zero_shot(root: Path, runs: list[Run], trials: int) -> None:
    """Evaluate every static policy in the dynamic simulator (what is not done yet)."""
    todo = [r for r in runs if (r.folder / 'static.onnx').is_file() and worth_running(runs, r)
            and not study.evaluated(zero_shot_folder(root, r), r.folder / 'static.onnx',
                                    trials)]
    for i, r in enumerate(todo, 1):
        out = zero_shot_folder(root, r)
        study.say(f'[{i}/{len(todo)}] {r.name}: static policy in the beating aorta, '
                  f'{trials} trials')
        out.mkdir(parents=True, exist_ok=True)
        policy = r.folder / 'static.onnx'
        cmd = study.python_module('cgail_learning.evaluate', '--policy',
                                  f'{r.preset}={policy}', '--baselines', '--modes', 'dynamic',
                                  '--trials', str(trials), '--anatomy', study.DEFAULT_ANATOMY,
                                  '--scenario-seed', str(TRAINING), '--out', str(out))
        with (out / 'evaluate.log').open('w') as log:
            code = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT,
                                  env=study.child_env(), stdin=subprocess.DEVNULL).returncode
        if code != 0:
            raise study.StudyError(f'{r.name}: evaluate exited {code}; see {out / "evaluate.log"}')
        study.record_inputs(out / 'results.json', {'policy': policy})
        study.say(f'[{i}/{len(todo)}] {r.name}: {pct(rate(study.load_trials(out)))}')


def zero_shot_rows(root: Path, runs: list[Run]) -> list[tuple[Run, list[float | None]]]:
    """Per run with a static policy: study static, static policy in dynamic, re-trained."""
    rows = []
    for r in runs:
        got = [rate(study.load_trials(r.folder / f'eval_static_targets{TRAINING}')),
               rate(study.load_trials(zero_shot_folder(root, r))),
               rate(study.load_trials(r.folder / f'eval_dynamic_targets{TRAINING}'))]
        if any(g is not None for g in got):
            rows.append((r, got))
    return rows


def plot_zero_shot(rows: list[tuple[Run, list[float | None]]], path: Path) -> bool:
    """Grouped bars: static, static policy in dynamic, re-trained dynamic, per run."""
    shown = [(r, g) for r, g in rows if g[1] is not None]
    if not shown:
        return False
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(8.0, 1.1 * len(shown) + 2), 4.6))
    labels = ['static policy, static aorta', 'static policy, beating aorta (no re-training)',
              'after 102,400 steps of re-training, beating aorta']
    width = 0.27
    for j, label in enumerate(labels):
        xs = [i + (j - 1) * width for i in range(len(shown))]
        ys = [100 * (g[j] or 0) for _, g in shown]
        bars = ax.bar(xs, ys, width, label=label, color=f'C{j}')
        for b, (_, g) in zip(bars, shown, strict=True):
            ax.annotate(pct(g[j]), (b.get_x() + b.get_width() / 2, b.get_height()),
                        ha='center', va='bottom', fontsize=7)
    ax.set_xticks(range(len(shown)))
    ax.set_xticklabels([f'{r.preset}\nseed {r.seed}, {r.budget / 1e6:g}M' for r, _ in shown],
                       fontsize=8)
    ax.set_ylim(0, 115)
    ax.set_ylabel('success, training targets (%)')
    ax.set_title('What the heartbeat does to a static policy, and what re-training adds')
    ax.legend(fontsize=7, loc='upper center', bbox_to_anchor=(0.5, -0.16), ncol=3)
    ax.grid(axis='y', alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


@dataclass(frozen=True)
class Motion:
    """How far the heartbeat of one option set moves the wall and the targets."""

    options: str
    period: float
    """The heartbeat's period, s."""
    targets_mm: tuple[float, ...]
    """Per target of the training set, its largest displacement from rest, mm."""
    wall_mm: float
    """The largest displacement of any wall vertex, mm."""
    moving: int
    """Wall vertices displaced more than 1 mm at some time."""
    vertices: int


def heartbeat_motion(options: str, cycles: float = 2.0) -> Motion:
    """Step the dynamic simulator of ``options`` (default anatomy, training targets) for
    ``cycles`` heartbeats with the tip parked at start 0 (zero actions), one episode per target,
    and measure how far the targets and the wall move."""
    import numpy as np

    from cgail_sim.config import EnvConfig
    from cgail_sim.env import NavEngine

    cfg = EnvConfig.from_options(options, mode='dynamic')
    n = len(NavEngine(cfg, 1).scenarios.targets)
    engine = NavEngine(cfg, n)
    for i in range(n):
        engine.reset_env(i, 0, i)
    rest_targets = engine.target.copy()
    rest_wall = engine.walls[0].vertices.copy()
    target_peak = np.zeros(n)
    wall_peak = np.zeros(len(rest_wall))
    for _ in range(int(np.ceil(cycles * cfg.heartbeat.period / cfg.dt))):
        engine.step(np.zeros((n, 3)))
        target_peak = np.maximum(target_peak,
                                 np.linalg.norm(engine.target - rest_targets, axis=1))
        wall_peak = np.maximum(wall_peak,
                               np.linalg.norm(engine.walls[0].vertices - rest_wall, axis=1))
    return Motion(options, cfg.heartbeat.period, tuple(1000 * target_peak),
                  1000 * float(wall_peak.max()), int((wall_peak > 1e-3).sum()), len(rest_wall))


def table(head: list[str], rows: list[list[str]]) -> list[str]:
    return ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head),
            *('| ' + ' | '.join(r) + ' |' for r in rows)]


def build_evidence(root: Path, runs: list[Run], trials: int,
                   motions: Sequence[Motion] = ()) -> str:
    """``evidence.md`` (and its PNG in ``root``)."""
    lines = ['# Evidence for the study\'s reading', '',
             'Made by `scripts/ws python bench/insilico_evidence.py --study '
             f'{root.relative_to(WS) if root.is_relative_to(WS) else root}` from the runs '
             'beside it; the reading itself is in `reasons.md` (placed in `report.md`).', '',
             '## Training', '',
             'Periodic evaluation: noise-free, the training targets (what selects `best.pt`). '
             'Training success: the stochastic policy over its last 100 training episodes, '
             'its highest value over the run (0% means not one training episode reached a '
             'target). Last episodes: the mean length (steps) and extrinsic reward of the '
             'last logged training episodes (-1 is a collision or an exit).', '',
             *table(['preset', 'seed', 'budget', 'best periodic evaluation',
                     'last periodic evaluation', 'highest training success',
                     'last episodes: length', 'last episodes: reward'],
                    [training_row(r) for r in runs]), '',
             '## Where the evaluations fail', '',
             f'The study\'s evaluations on the training targets ({trials} trials each, through '
             'the simulated EM tracker). Other failures: the step limit or an exit. Failures per '
             'start: trial k starts at start k % 3.', '']
    rows = [row for r in runs for mode in study.MODES if (row := failure_row(r, mode))]
    lines += [*table(['preset', 'seed', 'budget', 'mode', 'success', 'collisions',
                      'other failures', 'failures per start 0 / 1 / 2'], rows), '']
    zs = zero_shot_rows(root, runs)
    lines += ['## The static policy in the beating aorta', '',
              'Each run\'s static policy evaluated without re-training in the dynamic simulator '
              f'(training targets, {trials} trials, the study\'s trial seeds), beside the '
              'study\'s static figure and its figure after the dynamic re-training. "-": not '
              'run (the preset never succeeded in a static evaluation) or not yet.', '',
              *table(['preset', 'seed', 'budget', 'static policy, static aorta',
                      'static policy, beating aorta', 'after dynamic re-training'],
                     [[r.preset, str(r.seed), f'{r.budget:,}', *map(pct, g)] for r, g in zs]),
              '']
    png = 'evidence_static_in_dynamic.png'
    if plot_zero_shot(zs, root / png):
        lines += [f'![static policy in the beating aorta]({png})', '']
    if motions:
        lines += ['## How far the heartbeat moves the wall and the targets', '',
                  'The dynamic simulator of each option set (default anatomy, the training '
                  'targets), two heartbeats with the tip parked at start 0 (zero actions): '
                  'each target\'s largest displacement from rest (it rides on its wall vertex), '
                  'the wall\'s largest vertex displacement, and how many wall vertices move '
                  'more than 1 mm.', '',
                  *table(['option set', 'period', 'targets (mm)', 'wall, largest (mm)',
                          'wall vertices moving > 1 mm'],
                         [[f'`{m.options}`', f'{m.period:.2f} s',
                           ', '.join(f'{d:.1f}' for d in m.targets_mm), f'{m.wall_mm:.1f}',
                           f'{m.moving:,} of {m.vertices:,}'] for m in motions]), '']
    return '\n'.join(lines) + '\n'


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='insilico_evidence', description=__doc__.split('\n')[0])
    p.add_argument('--study', type=Path, default=WS / 'studies' / 'insilico_authors',
                   help='the study folder (made with --fresh-budgets)')
    p.add_argument('--trials', type=int, default=100,
                   help='trials of each static-policy evaluation in the beating aorta')
    p.add_argument('--no-run', action='store_true',
                   help='run no evaluation; write the tables from what is there')
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.trials < 1:
            raise study.StudyError(f'--trials: expected >= 1, found {args.trials}')
        root = args.study.resolve()
        runs = find_runs(root)
        if not args.no_run:
            run_zero_shot(root, runs, args.trials)
    except study.StudyError as exc:
        print(f'insilico_evidence: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        study.say('interrupted; re-run the same command to continue')
        return 130
    motions = [heartbeat_motion(options) for options in MOTION_OPTIONS]
    path = root / 'evidence.md'
    path.write_text(build_evidence(root, runs, args.trials, motions))
    study.say(f'evidence: {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

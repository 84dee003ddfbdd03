"""The paper's in-silico comparison in one resumable command: train, evaluate, report.

Run (from the workspace root, inside the workspace environment)::

    scripts/ws python bench/insilico_study.py                    # the defaults below
    scripts/ws python bench/insilico_study.py --methods paper_code_cgail paper_code_gail \
        paper_code_mu0 --seeds 0 1 --steps 500000 5000000 --jobs 2
    scripts/ws python bench/insilico_study.py --report-only      # rebuild OUT/report.md only
    scripts/ws python bench/insilico_study.py --prepare-commit   # OUT/.gitignore, then git add OUT
    scripts/ws python bench/insilico_study.py --methods smoke --seeds 0 --steps 4096 8192 \
        --trials 3 --dynamic-steps 2048 --out runs/insilico_smoke   # a smoke run, minutes
    scripts/ws python bench/insilico_study.py --methods paper_code_cgail paper_code_gail \
        cgail gail mu0 lambda0 nu0 --seeds 0 1 2 --authors-budgets --fresh-budgets --jobs 1 \
        --out runs/insilico_authors                   # issue 35: the authors' budgets, fresh
    scripts/ws python bench/insilico_study.py --methods paper_code_cgail paper_code_gail \
        cgail --seeds 0 1 --authors-budgets --budget-scale 0.001 --fresh-budgets --trials 3 \
        --dynamic-steps 2048 --out /tmp/insilico_authors_smoke   # its shape, minutes

Issue 13 (items 4 and 5): the baselines trained as the authors trained theirs, and the
side-by-side report. For every preset of ``--methods`` (default the five "ours" presets: C-GAIL,
GAIL and the three ablations) and every seed of ``--seeds`` it runs:

1. **Static training** (``python -m cgail_learning.train --preset P --mode static
   --seed S --max-steps N1``, 1 torch thread), in the rigid aorta on the training targets
   (scenario seed 0: the paper's 3 starts x 5 targets) with the committed demonstrations
   (``--demos``). Each larger budget of ``--steps`` **continues the same run** with
   ``train --resume RUN --max-steps N2``, after the smaller budget's result was snapshotted
   (its ``best.pt``, ``scalars.csv`` and ``config.yaml`` go to ``steps_<N1>/``), so every budget
   is reported from one training. The linear schedules (learning rate, epsilon, beta) of the
   continued run first decayed towards N1 and then decay from there towards N2, so a budget
   reached by continuation is not the same run as a fresh run of that budget.

   With ``--fresh-budgets`` every budget is **a run of its own from scratch**
   (``train --preset P --seed S --max-steps N``, in ``budget_<N>/static/``), its schedules
   decaying over that budget, as a single run of that budget would; no budget waits for
   another, and with ``--jobs 1`` the study goes seed by seed (every method and budget of the
   first seed, then the next), so the report compares the methods early. Its snapshot,
   policies, dynamic re-training and evaluations are those of the continued budgets, in
   ``budget_<N>/``.

   **Budgets per method.** ``--authors-budgets`` (instead of ``--steps``) gives every preset
   its own budgets: a ``paper_code`` preset the authors' budgets of its method
   (:data:`AUTHORS_STEPS`: C-GAIL 8M; GAIL 5M and 1,275,443, where their run stopped,
   :data:`AUTHORS_STOPPED`; the ablations their C-GAIL's 8M), any other preset (ours) its
   preset's ``max_steps``. ``--budget-scale F`` multiplies them all by F in (0, 1] for a
   smoke run of the same shape (a budget below one PPO buffer trains one buffer).
2. **Dynamic re-training** (``--modes`` with ``dynamic``), as the committed dynamic policy was
   made (docs/reports/insilico.md, ``cgail_planner/models/insilico/report.md``):
   ``train --preset P --mode dynamic
   --init-from steps_<N>/best.pt --max-steps D --seed S`` (``--dynamic-steps`` D, default
   102,400), in the beating aorta with the moving target, from each budget's static best; every
   method is re-trained the same way.
3. **Export** of each policy (``export_onnx``): the run's ``best.pt`` (its best periodic
   evaluation, on the training targets; ``final.pt`` when the run made no periodic evaluation).
4. **Evaluation** (``python -m cgail_learning.evaluate``), ``--trials`` trials (default
   100) per policy through the simulated EM tracker, as ``evaluate`` does, on the training
   targets (scenario seed 0) and on unseen targets (``--unseen-scenario-seed``, default 1: a
   target set no run trained on), static policies in the static simulator and re-trained
   policies in the dynamic one; ``--baselines`` (default the centerline follower) run on the same
   target sets as references.
5. **Report** ``OUT/report.md``: per option set (``ours``, ``paper_code``) a summary of every
   method at each of its budgets, per mode and target set: success per seed, the mean over the
   seeds, their range, the 95% t interval over the seeds (the seed is the unit that varies: a
   run finds the path or does not) and the 95% Wilson interval of the pooled trials (trial
   noise only), beside the paper's figure (also ``OUT/summary.csv``); the orderings of the
   methods against the paper's, per budget and, with per-method budgets, of each method at
   its largest and at its smallest budget; per budget, a table of success per seed with the
   mean and its t interval beside the paper's figures and the steps used beside the authors'
   budgets; learning curves ``OUT/curves_<options>_<mode>.png`` (``eval/success_rate``
   against steps, one line per run and seed, from each run's ``scalars.csv``);
   ``OUT/results.csv`` in long form. A run that has not reached a budget is shown with the
   steps it reached, marked.

**Resuming.** Everything lives under ``--out`` (default ``runs/insilico_study``). Re-running the
same command skips what is done (snapshots; policies exported from their current checkpoint;
evaluations of the current policy with ``--trials`` trials), resumes
unfinished trainings from their latest checkpoint (``train --resume``; a run without a
checkpoint restarts) and rebuilds the report. Ctrl-C or SIGTERM stops the running processes;
their checkpoints stay. Each process logs to ``OUT/logs/<task>.log`` (appended across
invocations). A progress line per running training every ``--progress-every`` seconds gives its
steps, steps/s, ETA and last evaluation success.

What is done is judged by content, not file times: each output records the sha256 of what it
was made from (``snapshot.json`` and a run's ``study_state.json``: their policy checkpoint's
``policy_sha256``; ``static.onnx.sha256.json`` beside a policy: its checkpoint's;
``eval_*/results.json.sha256.json``: the evaluated policy's), and is done while those inputs
still hash the same, or are not there (a checkpoint left out of git: then compared with the
hash recorded where it was made). So a budget whose ``snapshot.json``, policies and
evaluations agree is done without any ``*.pt``. Outputs made before these records are judged
by file times (an output not older than its inputs) and recorded by content on the next run
(or ``--prepare-commit``) on the machine that made them.

*Across machines: commit OUT.* Every run writes ``OUT/.gitignore``: ``git add OUT`` then takes
the reports, CSVs, PNGs, JSON, YAML, ONNX policies and logs, and of the checkpoints (``*.pt``)
only what a task not done yet needs: an unfinished training's latest periodic checkpoint
(``checkpoints/step_<n>.pt``), ``final.pt`` and ``best.pt`` (``train --resume`` needs no more
beside ``config.yaml`` and ``scalars.csv``), and a budget's ``best.pt`` until its exports and
dynamic re-training are done. To end a session: stop the study (Ctrl-C or SIGTERM: it rewrites
``OUT/.gitignore`` as it stops; after a harder stop, or for a folder made before this, run the
same command with ``--prepare-commit``, which runs nothing), then ``git add OUT && git commit``.
A later session re-runs the same command in its clone and continues where it stopped.
Checkpoints committed earlier that no task needs any more stay tracked until removed:
``git rm --cached $(git ls-files -ci --exclude-standard OUT)``.

Layout of ``OUT``: ``<preset>/seed<S>/static/`` (the static run, continued budget after budget),
``<preset>/seed<S>/steps_<N>/`` (snapshot ``best.pt`` + ``scalars.csv`` + ``config.yaml`` +
``snapshot.json``, ``static.onnx``, ``dynamic/`` run, ``dynamic.onnx``,
``eval_<mode>_targets<K>/`` with ``evaluate``'s ``report.md`` and ``results.json``),
``baselines/<options>/eval_<mode>_targets<K>/``, ``logs/``, ``report.md``, ``summary.csv``,
``results.csv``, ``.gitignore``. With ``--fresh-budgets``: ``<preset>/seed<S>/budget_<N>/``
holds the same as ``steps_<N>/`` and the budget's own static run in ``static/``. Re-run, or
``--report-only``, with the same budget options: they say which layout to read.

**Anatomies.** This command runs in the default anatomy, with ``--demos``. ``bench/sweep.py``
runs the same tasks in several anatomies (an :class:`Anatomy` each, what ``train`` and
``evaluate`` are told) and on Ray (:data:`Launcher`): the default anatomy's runs lie as above,
another's under ``anatomies/<name>/`` in the same layout, and the report has a row per anatomy.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable, Iterator, Sequence
import contextlib
import csv
from dataclasses import dataclass, field, replace
import datetime
from fractions import Fraction
from functools import partial
import hashlib
import itertools
import json
import os
from pathlib import Path
import platform
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from typing import Any, Protocol

import yaml

WS = Path(__file__).resolve().parent.parent
DEFAULT_METHODS = ('cgail', 'gail', 'mu0', 'lambda0', 'nu0')
MODES = ('static', 'dynamic')
TRAINING_TARGETS = 0
#: Paper success rates (%), ``paper.tex``: static and ablations §V-A (text of Fig.
#: ``fig:comp_path``: C-GAIL 80, GAIL 42, mu = 0 11, lambda = 0 58, nu = 0 48, epsilon 10 mm);
#: dynamic §V-A (text of Fig. ``fig:comp_softrig``: C-GAIL 17, GAIL 0); the second anatomy
#: Table IV (``tab:models``: 79). Keyed by method kind (the preset name without ``paper_code_``).
PAPER_SUCCESS: dict[tuple[str, str], int] = {
    ('cgail', 'static'): 80, ('gail', 'static'): 42, ('mu0', 'static'): 11,
    ('lambda0', 'static'): 58, ('nu0', 'static'): 48,
    ('cgail', 'dynamic'): 17, ('gail', 'dynamic'): 0}
PAPER_SECOND_ANATOMY = 79
#: The authors' step budgets (``docs/fidelity.md``, "One row per trained run"): their GAIL
#: baseline ``chi_soft_gail_3`` 5M, their C-GAIL ``softAorta12`` and PPO-only ``ppo_only_1`` 8M.
#: Their repository holds no ablation run; the ablations get their C-GAIL run's 8M (as the
#: ``paper_code_mu0`` / ``paper_code_lambda0`` presets do), marked as such in the report.
AUTHORS_STEPS: dict[str, int] = {'cgail': 8_000_000, 'gail': 5_000_000, 'ppo': 8_000_000,
                                 'mu0': 8_000_000, 'lambda0': 8_000_000, 'nu0': 8_000_000}
AUTHORS_STEPS_INFERRED = frozenset({'mu0', 'lambda0', 'nu0'})
#: Where an authors' run stopped short of its configured budget: their GAIL ``chi_soft_gail_3``
#: was configured for 5M steps and stopped at 1,275,443 (``training_status.json`` of their
#: repository; ``docs/fidelity.md``). ``--authors-budgets`` trains both, each from scratch.
AUTHORS_STOPPED: dict[str, int] = {'gail': 1_275_443}
#: ``--steps`` when neither it nor ``--authors-budgets`` is given.
DEFAULT_STEPS = (500_000, 2_000_000)
LABELS = {'cgail': 'C-GAIL', 'gail': 'GAIL', 'mu0': 'mu = 0 (no BC)',
          'lambda0': 'lambda = 0 (no GAIL)', 'nu0': 'nu = 0 (no curiosity)', 'ppo': 'PPO only'}
#: Two success rates closer than this are a tie in the ordering (with 100 trials per seed the
#: standard error of a rate near 50% is 3.5 points over two seeds).
TIE = Fraction(5, 100)


class StudyError(ValueError):
    """A one-line failure of the study (bad input, or a run that cannot give a budget)."""


# ------------------------------------------------------------------------------------------
# Pure pieces: names, files, results, tables, ordering (unit-tested without training).


def method_kind(preset: str) -> str:
    """The method a preset trains: its name without the ``paper_code_`` prefix."""
    return preset.removeprefix('paper_code_')


def method_label(preset: str) -> str:
    """Display name of a preset's method (``paper_code_gail`` -> ``GAIL``)."""
    return LABELS.get(method_kind(preset), preset)


def check_budgets(steps: Sequence[int]) -> tuple[int, ...]:
    """The step budgets, which must be positive and strictly increasing.

    Raises:
        StudyError: an empty list, a budget < 1, or budgets out of order.
    """
    if not steps:
        raise StudyError('--steps: expected one or more budgets, found none')
    if any(n < 1 for n in steps):
        raise StudyError(f'--steps: expected budgets >= 1, found {list(steps)}')
    if any(b <= a for a, b in itertools.pairwise(steps)):
        raise StudyError(f'--steps: expected strictly increasing budgets (a larger budget '
                         f'continues the smaller one), found {list(steps)}')
    return tuple(steps)


def authors_budgets(kind: str) -> tuple[int, ...]:
    """The authors' budgets of a method kind, increasing: where their run stopped when it
    stopped short (:data:`AUTHORS_STOPPED`), and its configured budget (:data:`AUTHORS_STEPS`);
    empty for a method they did not run."""
    if kind not in AUTHORS_STEPS:
        return ()
    return tuple(sorted({AUTHORS_STEPS[kind], *([AUTHORS_STOPPED[kind]]
                                                 if kind in AUTHORS_STOPPED else [])}))


def method_budgets(option_sets: dict[str, str], max_steps: dict[str, int],
                   scale: float = 1.0) -> dict[str, tuple[int, ...]]:
    """``--authors-budgets``: each preset's budgets. A ``paper_code`` preset of a method the
    authors ran gets their budgets (:func:`authors_budgets`); any other preset (ours) its own
    ``max_steps``. ``scale`` multiplies every budget (a smoke run of the same shape), rounded,
    at least 1.

    Raises:
        StudyError: ``scale`` is not in (0, 1].
    """
    if not 0 < scale <= 1:
        raise StudyError(f'--budget-scale: expected a factor in (0, 1], found {scale}')
    out = {}
    for preset, options in option_sets.items():
        kind = method_kind(preset)
        full = authors_budgets(kind) if options == 'paper_code' and kind in AUTHORS_STEPS \
            else (max_steps[preset],)
        out[preset] = tuple(sorted({max(1, round(n * scale)) for n in full}))
    return out


#: The anatomy a study runs in unless told otherwise; its runs lie directly under ``--out``.
DEFAULT_ANATOMY = 'default'


@dataclass(frozen=True)
class Anatomy:
    """One anatomy of a study: what ``train`` and ``evaluate`` are told, and the demonstrations.

    A built-in name or a path becomes ``--anatomy X`` for both (:meth:`named`). Any other
    anatomy (a population: ``train`` with a population preset, ``evaluate --population N``)
    gives its own arguments, so the study needs no knowledge of how it is drawn.
    """

    name: str
    """Its label in task keys, folders (``anatomies/<name>/``) and tables."""
    train_args: tuple[str, ...]
    """Arguments of every ``train`` invocation in it (fresh, resumed, dynamic)."""
    eval_args: tuple[str, ...]
    """Arguments of every ``evaluate`` invocation in it."""
    demos: tuple[Path, ...]
    """``train --demos``."""

    @classmethod
    def named(cls, spec: str, demos: Sequence[Path] | None = None) -> Anatomy:
        """A built-in anatomy or a path (``--anatomy spec``): its demonstrations default to
        ``bags/demos/<name>`` for a built-in one, else ``bags/demos/default`` (``train``
        re-simulates them in a path anatomy).

        Raises:
            StudyError: ``spec`` is neither a built-in name nor a usable anatomy path.
        """
        from cgail_sim.anatomy import AnatomyError
        from cgail_sim.anatomy_spec import anatomy_label, check_anatomy_spec, is_builtin

        try:
            check_anatomy_spec(spec)
        except AnatomyError as exc:
            raise StudyError(f'anatomy: {exc}') from None
        name = anatomy_label(spec)
        if demos is None:
            demos = [WS / 'bags' / 'demos' / (name if is_builtin(spec) else DEFAULT_ANATOMY)]
        return cls(name, ('--anatomy', spec), ('--anatomy', spec), tuple(demos))


#: A seed's folder under its preset's (:meth:`Layout.run_root`); group 1 is the seed.
SEED_FOLDER = re.compile(r'seed(\d+)')


@dataclass(frozen=True)
class Layout:
    """Where everything of a study lives under ``root``: the default anatomy's runs directly
    there (as before anatomies were an axis, so older studies resume), every other anatomy's
    in a layout of its own under ``root/anatomies/<name>/`` (:meth:`of_anatomy`); the logs and
    the report of all of them under ``root``.

    With ``fresh`` (``--fresh-budgets``) every budget is a run of its own:
    ``<preset>/seed<S>/budget_<N>/static/`` beside that budget's snapshot, policies, dynamic
    run and evaluations; without, one static run ``<preset>/seed<S>/static/`` is continued
    budget after budget and each budget's results lie in ``<preset>/seed<S>/steps_<N>/``."""

    root: Path
    fresh: bool = False

    def of_anatomy(self, name: str) -> Layout:
        """The layout of anatomy ``name``'s runs, evaluations and baselines."""
        return self if name == DEFAULT_ANATOMY else Layout(self.root / 'anatomies' / name,
                                                           self.fresh)

    def run_root(self, preset: str, seed: int) -> Path:
        """Folder of one preset and seed (its static run or runs plus their budgets)."""
        return self.root / preset / f'seed{seed}'

    def static_run(self, preset: str, seed: int, steps: int | None = None) -> Path:
        """The static training run of budget ``steps``: the budget's own run when ``fresh``
        (``steps`` required), else the one run continued budget after budget."""
        if not self.fresh:
            return self.run_root(preset, seed) / 'static'
        if steps is None:
            raise ValueError('a fresh-budget layout has one static run per budget')
        return self.budget(preset, seed, steps) / 'static'

    def budget(self, preset: str, seed: int, steps: int) -> Path:
        """Everything of one budget: snapshot, policies, dynamic run, evaluations (and, when
        ``fresh``, its static run)."""
        return self.run_root(preset, seed) / (f'budget_{steps}' if self.fresh
                                              else f'steps_{steps}')

    def snapshot(self, preset: str, seed: int, steps: int) -> Path:
        """The marker of a budget's snapshot (written last)."""
        return self.budget(preset, seed, steps) / 'snapshot.json'

    def dynamic_run(self, preset: str, seed: int, steps: int) -> Path:
        """The dynamic re-training from a budget's static best."""
        return self.budget(preset, seed, steps) / 'dynamic'

    def policy(self, preset: str, seed: int, steps: int, mode: str) -> Path:
        """The exported policy of a budget in ``mode``."""
        return self.budget(preset, seed, steps) / f'{mode}.onnx'

    def evaluation(self, preset: str, seed: int, steps: int, mode: str, targets: int) -> Path:
        """``evaluate``'s output folder of one policy, mode and target set."""
        return self.budget(preset, seed, steps) / f'eval_{mode}_targets{targets}'

    def baselines(self, options: str, mode: str, targets: int) -> Path:
        """``evaluate``'s output folder of the baselines."""
        return self.root / 'baselines' / options / f'eval_{mode}_targets{targets}'

    def log(self, task: str) -> Path:
        """The log file of a task."""
        return self.root / 'logs' / f'{task.replace("/", "_")}.log'


def read_scalars(path: Path) -> dict[str, list[tuple[int, float]]]:
    """``tag -> [(step, value), ...]`` from a run's long-format ``scalars.csv`` (empty when it
    does not exist; malformed rows, e.g. a half-written last line, are skipped)."""
    out: dict[str, list[tuple[int, float]]] = {}
    if not path.is_file():
        return out
    with path.open(newline='') as f:
        for row in csv.reader(f):
            if len(row) != 3 or not row[0].isdigit():
                continue
            try:
                value = float(row[2])
            except ValueError:
                continue
            out.setdefault(row[1], []).append((int(row[0]), value))
    return out


def last_step(scalars: dict[str, list[tuple[int, float]]]) -> int:
    """The highest step logged (0 for none)."""
    return max((s for rows in scalars.values() for s, _ in rows), default=0)


@dataclass(frozen=True)
class Progress:
    """Where a training run stands, from its ``scalars.csv``."""

    step: int
    steps_per_s: float | None
    eval_step: int | None
    eval_success: float | None

    def line(self, target: int) -> str:
        """``step/target (pct), steps/s, ETA, last eval success``."""
        parts = [f'{self.step:,}/{target:,} steps ({100 * self.step / target:.0f}%)']
        if self.steps_per_s:
            eta = max(target - self.step, 0) / self.steps_per_s
            parts += [f'{self.steps_per_s:,.0f} steps/s', f'ETA {format_duration(eta)}']
        if self.eval_success is not None:
            parts.append(f'last eval success {self.eval_success:.2f} at {self.eval_step:,}')
        return ', '.join(parts)


def run_progress(run: Path, since: int = 0) -> Progress:
    """The :class:`Progress` of the run in ``run``; its steps/s from the rows past step
    ``since`` (those of the running ``train`` process, which resumed there)."""
    sc = read_scalars(run / 'scalars.csv')
    rate = [r for r in sc.get('time/steps_per_s', []) if r[0] > since]
    ev = sc.get('eval/success_rate', [])
    return Progress(last_step(sc), rate[-1][1] if rate else None,
                    ev[-1][0] if ev else None, ev[-1][1] if ev else None)


def format_duration(seconds: float) -> str:
    """``42 s``, ``12.5 min`` or ``3.2 h``."""
    if seconds < 90:
        return f'{seconds:.0f} s'
    if seconds < 5400:
        return f'{seconds / 60:.1f} min'
    return f'{seconds / 3600:.1f} h'


def run_max_steps(run: Path) -> int | None:
    """``max_steps`` of the last ``train`` invocation in ``run`` (its ``config.yaml``)."""
    path = run / 'config.yaml'
    if not path.is_file():
        return None
    data = yaml.safe_load(path.read_text()) or {}
    value = data.get('max_steps')
    return int(value) if isinstance(value, int) else None


def trained_to(run: Path, steps: int) -> bool:
    """Whether the run in ``run`` finished a ``train`` invocation of ``max_steps`` = ``steps``:
    its ``final.pt`` exists, its ``config.yaml`` says ``steps`` and its log reached them."""
    return ((run / 'final.pt').is_file() and run_max_steps(run) == steps
            and last_step(read_scalars(run / 'scalars.csv')) >= steps)


def checkpoint_steps(run: Path) -> list[int]:
    """Steps of the run's periodic checkpoints ``checkpoints/step_<n>.pt``."""
    return sorted(int(p.stem[5:]) for p in (run / 'checkpoints').glob('step_*.pt')
                  if p.stem[5:].isdigit())


def resumable(run: Path) -> bool:
    """Whether ``train --resume`` can continue the run (a periodic checkpoint or final.pt)."""
    return bool(checkpoint_steps(run)) or (run / 'final.pt').is_file()


def resumable_step(run: Path) -> int:
    """The step ``train --resume`` would continue from, as far as the files tell without
    loading a checkpoint: the highest periodic checkpoint, or the step the study recorded
    when a ``train`` invocation ended (``study_state.json``) while its final.pt is there."""
    best = max(checkpoint_steps(run), default=0)
    state = run / 'study_state.json'
    if (run / 'final.pt').is_file() and state.is_file():
        best = max(best, int(json.loads(state.read_text()).get('step', 0)))
    return best


def wall_seconds_from_log(log: Path) -> float | None:
    """The run's cumulative training wall time: the last ``time/wall_s`` that ``train`` printed
    in its result YAML (None when the log has none)."""
    if not log.is_file():
        return None
    found = re.findall(r'^time/wall_s: ([0-9.eE+-]+)$', log.read_text(errors='replace'),
                       flags=re.M)
    return float(found[-1]) if found else None


@dataclass(frozen=True)
class Outcome:
    """Successes of a policy over its evaluation trials."""

    successes: int
    trials: int

    @property
    def rate(self) -> Fraction:
        """The success rate, exact."""
        return Fraction(self.successes, self.trials)


def load_trials(folder: Path, name: str | None = None) -> list[dict[str, Any]] | None:
    """The trial records of method ``name`` (default: the first method) of the first mode in
    ``folder/results.json`` (``evaluate``'s), or None when they are not there."""
    path = folder / 'results.json'
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    for methods in data['modes'].values():
        key = name if name is not None else next(iter(methods), None)
        if key in methods:
            return list(methods[key]['trials'])
    return None


def load_outcome(folder: Path, name: str | None = None) -> Outcome | None:
    """The outcome of :func:`load_trials` (None when they are not there)."""
    trials = load_trials(folder, name)
    if trials is None:
        return None
    return Outcome(sum(bool(t['success']) for t in trials), len(trials))


def load_baselines(folder: Path) -> dict[str, Outcome]:
    """``method -> outcome`` of every method in ``folder/results.json`` (empty when absent)."""
    path = folder / 'results.json'
    if not path.is_file():
        return {}
    data = json.loads(path.read_text())
    return {name: Outcome(sum(bool(t['success']) for t in m['trials']), len(m['trials']))
            for methods in data['modes'].values() for name, m in methods.items()}


def mean_outcome(outcomes: Iterable[Outcome | None]) -> Outcome | None:
    """The pooled outcome of the seeds (None unless every seed has one)."""
    got = list(outcomes)
    if not got or any(o is None for o in got):
        return None
    return Outcome(sum(o.successes for o in got if o), sum(o.trials for o in got if o))


def percent(rate: Fraction) -> str:
    """``80%`` (rounded half up, exact)."""
    return f'{int(rate * 100 + Fraction(1, 2))}%'


#: The two-sided normal quantile of a 95% interval (Wilson's z).
Z95 = 1.959963984540054


def t_interval(values: Sequence[float], confidence: float = 0.95
               ) -> tuple[float, float] | None:
    """Student's t interval of the mean of ``values`` (mean +- t(n-1) s / sqrt(n)), clipped to
    [0, 1]; None for fewer than two values (no spread to estimate)."""
    from scipy.stats import t

    n = len(values)
    if n < 2:
        return None
    mean = sum(values) / n
    sd = (sum((v - mean) ** 2 for v in values) / (n - 1)) ** 0.5
    half = float(t.ppf(0.5 + confidence / 2, n - 1)) * sd / n ** 0.5
    return max(0.0, mean - half), min(1.0, mean + half)


def wilson_interval(o: Outcome, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval of a success rate (95% by default): within [0, 1], and not
    empty at 0 or all successes."""
    n, p = o.trials, o.successes / o.trials
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * (p * (1 - p) / n + z * z / (4 * n * n)) ** 0.5
    return max(0.0, centre - half), min(1.0, centre + half)


def span(interval: tuple[float, float] | None) -> str:
    """``61-100%`` (whole percent) or ``-``."""
    if interval is None:
        return '-'
    lo, hi = interval
    return f'{100 * lo:.0f}-{100 * hi:.0f}%'


@dataclass(frozen=True)
class SeedStats:
    """One method's success over its seeds at one budget, mode and target set."""

    outcomes: tuple[Outcome, ...]
    """Per seed, in seed order."""

    @property
    def mean(self) -> Fraction:
        """The mean of the seeds' success rates (the pooled rate when every seed had the
        same number of trials)."""
        return sum((o.rate for o in self.outcomes), Fraction(0)) / len(self.outcomes)

    @property
    def range(self) -> tuple[float, float]:
        """(lowest, highest) seed's success rate."""
        rates = [o.rate for o in self.outcomes]
        return float(min(rates)), float(max(rates))

    @property
    def t95(self) -> tuple[float, float] | None:
        """The 95% t interval over the seeds (:func:`t_interval`); None with one seed."""
        return t_interval([float(o.rate) for o in self.outcomes])

    @property
    def wilson95(self) -> tuple[float, float]:
        """The 95% Wilson interval of the seeds' trials pooled (:func:`wilson_interval`)."""
        pooled = mean_outcome(self.outcomes)
        assert pooled is not None
        return wilson_interval(pooled)


def seed_stats(outcomes: Iterable[Outcome | None]) -> SeedStats | None:
    """The :class:`SeedStats` of the seeds' outcomes (None unless every seed has one)."""
    got = list(outcomes)
    if not got or any(o is None for o in got):
        return None
    return SeedStats(tuple(o for o in got if o is not None))


def ordering(values: dict[str, Fraction], tie: Fraction = Fraction(0)) -> list[list[str]]:
    """Methods from best to worst, grouped: a method joins the current group when its value is
    within ``tie`` of the group's best; order within a group by value, then by name order."""
    ranked = sorted(values, key=lambda k: (-values[k], list(values).index(k)))
    groups: list[list[str]] = []
    for name in ranked:
        if groups and values[groups[-1][0]] - values[name] <= tie:
            groups[-1].append(name)
        else:
            groups.append([name])
    return groups


def format_ordering(values: dict[str, Fraction], tie: Fraction = Fraction(0),
                    label: Callable[[str], str] = str) -> str:
    """``A 80% > B 58% ≈ C 55%`` (``≈``: within ``tie``)."""
    return ' > '.join(' ≈ '.join(f'{label(n)} {percent(values[n])}' for n in group)
                      for group in ordering(values, tie))


def pair_agreement(ours: dict[str, Fraction], paper: dict[str, Fraction],
                   tie: Fraction = TIE) -> tuple[int, int, list[tuple[str, str]]]:
    """How many method pairs (with both figures) ours orders as the paper does.

    A pair agrees when the paper's better method is better here by more than ``tie``; equal
    paper figures want a tie here. Returns (agreeing, pairs, the disagreeing pairs as
    (paper's better, paper's worse)).
    """
    names = [n for n in paper if n in ours]
    agree, total, differ = 0, 0, []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            hi, lo = (a, b) if paper[a] >= paper[b] else (b, a)
            total += 1
            if paper[hi] == paper[lo]:
                ok = abs(ours[hi] - ours[lo]) <= tie
            else:
                ok = ours[hi] - ours[lo] > tie
            if ok:
                agree += 1
            else:
                differ.append((hi, lo))
    return agree, total, differ


@dataclass(frozen=True)
class StudyPlan:
    """What a study covers."""

    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    budgets: tuple[int, ...]
    modes: tuple[str, ...]
    option_sets: dict[str, str]
    """preset -> its env option set (``ours``, ``paper_code``)."""
    trials: int = 100
    unseen: int = 1
    dynamic_steps: int = 102_400
    baselines: tuple[str, ...] = ('centerline',)
    anatomies: tuple[Anatomy, ...] = ()
    """Every run trains and is evaluated in each of them (empty: the default anatomy with its
    committed demonstrations)."""
    fresh: bool = False
    """``--fresh-budgets``: every budget its own run from scratch, its schedules over that
    budget (else a larger budget continues the smaller one's run)."""
    method_budgets: dict[str, tuple[int, ...]] = field(default_factory=dict)
    """preset -> its own budgets (``--authors-budgets``); a preset not in it has ``budgets``,
    which then holds every preset's budgets."""

    def __post_init__(self) -> None:
        if not self.anatomies:
            object.__setattr__(self, 'anatomies', (Anatomy.named(DEFAULT_ANATOMY),))

    def budgets_of(self, preset: str) -> tuple[int, ...]:
        """The budgets ``preset`` trains to, increasing."""
        return self.method_budgets.get(preset, self.budgets)

    @property
    def target_sets(self) -> tuple[int, int]:
        """(training targets, unseen targets) scenario seeds."""
        return (TRAINING_TARGETS, self.unseen)

    def options(self) -> list[str]:
        """The option sets of the methods, in method order."""
        return list(dict.fromkeys(self.option_sets[m] for m in self.methods))


@dataclass
class StudyResults:
    """Everything the report needs, read from the files (:func:`collect`)."""

    plan: StudyPlan
    anatomy: str = DEFAULT_ANATOMY
    outcomes: dict[tuple[str, int, int, str, int], Outcome] = field(default_factory=dict)
    """(preset, seed, budget, mode, target set) -> outcome."""
    snapshots: dict[tuple[str, int, int], dict[str, Any]] = field(default_factory=dict)
    """(preset, seed, budget) -> snapshot.json (``step``, ``wall_s``, ``policy``...)."""
    reached: dict[tuple[str, int, int], int] = field(default_factory=dict)
    """(preset, seed, budget) -> the last logged step of the budget's static run (with
    continued budgets, the one run's, the same for every budget)."""
    baselines: dict[tuple[str, str, int], dict[str, Outcome]] = field(default_factory=dict)
    """(options, mode, target set) -> baseline -> outcome."""
    curves: dict[tuple[str, int, int], list[tuple[int, float]]] = field(default_factory=dict)
    """(preset, seed, budget) -> the budget's static run's eval/success_rate curve."""
    dynamic_curves: dict[tuple[str, int, int], list[tuple[int, float]]] = field(
        default_factory=dict)
    """(preset, seed, budget) -> dynamic re-training eval/success_rate curve."""


def plan_layout(layout: Layout, plan: StudyPlan) -> Layout:
    """``layout`` with the plan's kind of budgets (fresh runs or one continued run)."""
    return layout if layout.fresh == plan.fresh else replace(layout, fresh=plan.fresh)


def collect(layout: Layout, plan: StudyPlan, anatomy: str = DEFAULT_ANATOMY) -> StudyResults:
    """Read every result of ``plan`` in ``anatomy`` that exists under ``layout``."""
    res = StudyResults(plan, anatomy)
    layout = plan_layout(layout, plan).of_anatomy(anatomy)
    for m in plan.methods:
        for s in plan.seeds:
            for n in plan.budgets_of(m):
                sc = read_scalars(layout.static_run(m, s, n) / 'scalars.csv')
                res.reached[(m, s, n)] = last_step(sc)
                res.curves[(m, s, n)] = sc.get('eval/success_rate', [])
                snap = layout.snapshot(m, s, n)
                if snap.is_file():
                    res.snapshots[(m, s, n)] = json.loads(snap.read_text())
                dyn = read_scalars(layout.dynamic_run(m, s, n) / 'scalars.csv')
                if dyn:
                    res.dynamic_curves[(m, s, n)] = dyn.get('eval/success_rate', [])
                for mode in plan.modes:
                    for k in plan.target_sets:
                        o = load_outcome(layout.evaluation(m, s, n, mode, k))
                        if o is not None:
                            res.outcomes[(m, s, n, mode, k)] = o
    for options in plan.options():
        for mode in plan.modes:
            for k in plan.target_sets:
                got = load_baselines(layout.baselines(options, mode, k))
                if got:
                    res.baselines[(options, mode, k)] = got
    return res


def authors_cell(preset: str) -> str:
    """The authors' budget of the preset's method: ``8,000,000``, ``8,000,000*`` (their C-GAIL
    run's, for an ablation), ``5,000,000; stopped at 1,275,443`` or ``-``."""
    kind = method_kind(preset)
    theirs = AUTHORS_STEPS.get(kind)
    if theirs is None:
        return '-'
    stop = AUTHORS_STOPPED.get(kind)
    return (f"{theirs:,}{'*' if kind in AUTHORS_STEPS_INFERRED else ''}"
            + (f'; stopped at {stop:,}' if stop else ''))


def steps_cell(res: StudyResults, preset: str, budget: int) -> str:
    """The steps used for ``budget`` (per seed when they differ; a dagger where not reached)
    and the authors' budget."""
    parts = []
    for s in res.plan.seeds:
        snap = res.snapshots.get((preset, s, budget))
        if snap is not None:
            parts.append(f"{int(snap['step']):,}")
        else:
            parts.append(f'{res.reached.get((preset, s, budget), 0):,} of {budget:,} †')
    used = parts[0] if len(set(parts)) == 1 else ', '.join(
        f'seed {s}: {p}' for s, p in zip(res.plan.seeds, parts, strict=True))
    return f'{used} (authors: {authors_cell(preset)})'


def seed_outcomes(res: StudyResults, preset: str, budget: int, mode: str, targets: int
                  ) -> list[Outcome | None]:
    """The outcome of every seed (None where it is not evaluated yet)."""
    return [res.outcomes.get((preset, s, budget, mode, targets)) for s in res.plan.seeds]


def success_cell(res: StudyResults, preset: str, budget: int, mode: str, targets: int) -> str:
    """``100%, 93%, 97% (mean **97%**, 95% CI 88-100%)``: per seed, then the mean over the
    seeds and its t interval (:attr:`SeedStats.t95`); ``-`` where missing."""
    per = seed_outcomes(res, preset, budget, mode, targets)
    seeds = ', '.join(percent(o.rate) if o else '-' for o in per)
    st = seed_stats(per)
    if len(per) == 1:
        return f'**{seeds}**' if st else seeds
    if st is None:
        return f'{seeds} (mean -)'
    return f'{seeds} (mean **{percent(st.mean)}**, 95% CI {span(st.t95)})'


def paper_cell(preset: str, mode: str) -> str:
    """The paper's success rate of the preset's method in ``mode``, or ``-``."""
    value = PAPER_SUCCESS.get((method_kind(preset), mode))
    return '-' if value is None else f'{value}%'


def methods_at(plan: StudyPlan, options: str, budget: int | None = None) -> list[str]:
    """The presets of option set ``options`` (that train to ``budget``, if given)."""
    return [m for m in plan.methods if plan.option_sets[m] == options
            and (budget is None or budget in plan.budgets_of(m))]


def budget_table(results: Sequence[StudyResults], options: str, budget: int) -> list[str]:
    """The side-by-side table of one option set and budget (markdown lines): a row per method
    that trains to ``budget`` and anatomy (the anatomy column only when there are several; the
    paper's figures only in the default anatomy, the paper's)."""
    plan = results[0].plan
    seeds = ('seeds ' if len(plan.seeds) > 1 else 'seed ') + ', '.join(map(str, plan.seeds))
    by_anatomy = len(results) > 1
    head = ['anatomy'] * by_anatomy + ['method', 'steps used (authors\')']
    for mode in plan.modes:
        head += [f'{mode}: paper', f'{mode}: training targets ({seeds})',
                 f'{mode}: unseen targets ({seeds})']
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for res in results:
        for m in methods_at(plan, options, budget):
            row = [f'`{res.anatomy}`'] * by_anatomy + [f'{method_label(m)} (`{m}`)',
                                                       steps_cell(res, m, budget)]
            for mode in plan.modes:
                paper = paper_cell(m, mode) if res.anatomy == DEFAULT_ANATOMY else '-'
                row += [paper] + [success_cell(res, m, budget, mode, k)
                                  for k in plan.target_sets]
            lines.append('| ' + ' | '.join(row) + ' |')
    return lines


def baseline_line(res: StudyResults, options: str) -> str | None:
    """``Baselines ...: centerline static 100% / 97%; ...`` (training / unseen targets)."""
    parts = []
    for mode in res.plan.modes:
        got = [res.baselines.get((options, mode, k), {}) for k in res.plan.target_sets]
        for name in dict.fromkeys(n for g in got for n in g):
            cells = [percent(g[name].rate) if name in g else '-' for g in got]
            parts.append(f'`{name}` {mode} {" / ".join(cells)}')
    if not parts:
        return None
    return ('Baselines on the same trials (training / unseen targets; not trained, the same at '
            'every budget): ' + '; '.join(parts) + '.')


def targets_name(k: int) -> str:
    """``training`` or ``unseen (scenario seed K)``."""
    return 'training' if k == TRAINING_TARGETS else f'unseen (scenario seed {k})'


SUMMARY_HEAD = ['anatomy', 'options', 'preset', 'budget', 'mode', 'targets', 'seeds',
                'per seed', 'mean', 'min-max', 't95', 'wilson95', 'paper']


def summary_rows(results: Sequence[StudyResults]) -> list[list[str]]:
    """Per anatomy, option set, method, budget, mode and target set with every seed
    evaluated: the success per seed, the mean over the seeds, the range, the 95% t interval
    over the seeds and the 95% Wilson interval of the pooled trials, and the paper's figure
    (``summary.csv``, and the report's summary tables). Heading: :data:`SUMMARY_HEAD`."""
    rows = []
    for res in results:
        plan = res.plan
        for options in plan.options():
            for m in methods_at(plan, options):
                for n in plan.budgets_of(m):
                    for mode in plan.modes:
                        for k in plan.target_sets:
                            st = seed_stats(seed_outcomes(res, m, n, mode, k))
                            if st is None:
                                continue
                            paper = (paper_cell(m, mode) if k == TRAINING_TARGETS
                                     and res.anatomy == DEFAULT_ANATOMY else '-')
                            rows.append([
                                res.anatomy, options, m, str(n), mode, targets_name(k),
                                ' '.join(map(str, plan.seeds)),
                                ', '.join(percent(o.rate) for o in st.outcomes),
                                percent(st.mean), span(st.range), span(st.t95),
                                span(st.wilson95), paper])
    return rows


def summary_table(results: Sequence[StudyResults], options: str) -> list[str]:
    """The report's summary of one option set (markdown lines; empty when nothing of it has
    every seed evaluated)."""
    by_anatomy = len(results) > 1
    rows = [r for r in summary_rows(results) if r[1] == options]
    if not rows:
        return []
    head = ['anatomy'] * by_anatomy + ['method', 'budget (authors\')', 'mode', 'targets',
                                       'per seed', 'mean', 'min-max', '95% t interval',
                                       '95% Wilson (pooled trials)', 'paper']
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for a, _, m, n, mode, k, _, per, mean, rng, t95, w95, paper in rows:
        lines.append('| ' + ' | '.join(
            [f'`{a}`'] * by_anatomy + [f'{method_label(m)} (`{m}`)',
                                       f'{int(n):,} ({authors_cell(m)})', mode,
                                       k.split(' (')[0], per, f'**{mean}**', rng, t95, w95,
                                       paper]) + ' |')
    return lines


def seed_means(res: StudyResults, budgets: dict[str, int], mode: str, targets: int
               ) -> dict[str, Fraction]:
    """preset -> its mean success over the seeds at its budget in ``budgets`` (presets with
    every seed evaluated)."""
    out = {}
    for m, n in budgets.items():
        st = seed_stats(seed_outcomes(res, m, n, mode, targets))
        if st is not None:
            out[m] = st.mean
    return out


def ordering_lines(res: StudyResults, budgets: dict[str, int]) -> list[str]:
    """Ours (each preset of ``budgets`` at its budget there) and the paper's ordering of the
    methods per mode and target set, and how many method pairs keep the paper's order (the
    paper's only in its anatomy, the default)."""
    lines = []
    for mode in res.plan.modes:
        paper = {m: Fraction(PAPER_SUCCESS[(method_kind(m), mode)], 100)
                 for m in budgets if (method_kind(m), mode) in PAPER_SUCCESS
                 and res.anatomy == DEFAULT_ANATOMY}
        if len(paper) >= 2:
            lines.append(f'- {mode}, paper: {format_ordering(paper, label=method_label)}')
        for k in res.plan.target_sets:
            ours = seed_means(res, budgets, mode, k)
            where = 'training targets' if k == TRAINING_TARGETS else 'unseen targets'
            if len(ours) < 2:
                lines.append(f'- {mode}, {where}: fewer than two methods with every seed '
                             'evaluated yet')
                continue
            line = f'- {mode}, {where}: {format_ordering(ours, TIE, method_label)}'
            agree, total, differ = pair_agreement(ours, paper)
            if total:
                line += f'; {agree} of {total} pairs ordered as in the paper'
                if differ:
                    line += ' (not: ' + ', '.join(
                        f'{method_label(a)} > {method_label(b)}' for a, b in differ) + ')'
            lines.append(line)
    return lines


def own_budget_orderings(plan: StudyPlan, options: str) -> list[tuple[str, dict[str, int]]]:
    """With per-method budgets (methods of ``options`` that do not share their budgets): the
    comparisons of each method at its largest and at its smallest budget, each titled
    (empty when the methods share their budgets: the per-budget orderings cover them)."""
    methods = methods_at(plan, options)
    if len({plan.budgets_of(m) for m in methods}) < 2:
        return []
    largest = {m: plan.budgets_of(m)[-1] for m in methods}
    smallest = {m: plan.budgets_of(m)[0] for m in methods}
    def title(b: dict[str, int]) -> str:
        return ', '.join(f'{method_label(m)} {n:,}' for m, n in b.items())
    out = [(f'each method at its largest budget ({title(largest)})', largest)]
    if smallest != largest:
        out.append((f'each method at its smallest budget ({title(smallest)})', smallest))
    return out


def results_rows(results: Sequence[StudyResults]) -> list[list[Any]]:
    """Long-form rows of every evaluated outcome of every anatomy (``results.csv``)."""
    rows: list[list[Any]] = [['anatomy', 'options', 'preset', 'seed', 'budget', 'steps', 'mode',
                              'targets', 'successes', 'trials']]
    for res in results:
        for (m, s, n, mode, k), o in sorted(res.outcomes.items()):
            snap = res.snapshots.get((m, s, n), {})
            rows.append([res.anatomy, res.plan.option_sets[m], m, s, n, snap.get('step', ''),
                         mode,
                         'training' if k == TRAINING_TARGETS else f'unseen (scenario seed {k})',
                         o.successes, o.trials])
    return rows


def plot_curves(curves: dict[str, list[tuple[int, float]]], budgets: Sequence[int], path: Path,
                title: str, xlabel: str = 'env steps') -> bool:
    """One line per run (``eval/success_rate`` against steps), dotted lines at ``budgets``:
    a colour per method (the label before `` seed``), a line style and hollow marker per run
    of it (per seed). Returns False (and writes nothing) when no curve has a point."""
    if not any(curves.values()):
        return False
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    styles = ['-', '--', ':', '-.']
    markers = ['o', 's', '^', 'D']  # hollow: runs on the same values stay visible
    colours: dict[str, str] = {}
    count: dict[str, int] = {}
    for label, pts in curves.items():
        if not pts:
            continue
        method = label.split(' seed')[0]  # one colour per method, one style per run of it
        colour = colours.setdefault(method, f'C{len(colours) % 10}')
        count[method] = count.get(method, -1) + 1
        xs, ys = zip(*pts, strict=True)
        ax.plot(xs, ys, styles[count[method] % len(styles)], color=colour,
                marker=markers[count[method] % len(markers)], markersize=5, fillstyle='none',
                label=label)
    for n in budgets:
        ax.axvline(n, color='0.6', linestyle=':', linewidth=1)
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlim(left=0)
    ax.set_xlabel(xlabel)
    ax.set_ylabel('eval/success_rate')
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc='best', handlelength=4)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def build_report(results: Sequence[StudyResults], command: str, out: Path,
                 notes: str = '') -> str:
    """The study's markdown report of every anatomy's results (the default anatomy's alone
    reads as before anatomies were an axis), then ``notes`` (markdown placed as it is, after
    the tables); writes the learning-curve PNGs next to it in ``out``."""
    plan = results[0].plan
    seeds = ', '.join(str(s) for s in plan.seeds)
    lines = [
        '# In-silico study: the paper side by side with ours', '',
        f'Made on {datetime.date.today().isoformat()} '
        f'({platform.node() or "?"}, {os.cpu_count()} CPUs); re-run or continue with:', '',
        f'```bash\n{command}\n```', '',
        f'Seeds {seeds}; {plan.trials} evaluation trials per policy, target set and mode; '
        'trial k uses start k % 3 and target (k // 3) % 5, seed 1000 + k, and the policy '
        'perceives the tip through the simulated EM tracker (0.48 mm / 0.30 deg RMS), as '
        '`evaluate` does. "training targets": scenario seed 0, the paper\'s 3 starts x 5 '
        'targets that the demonstrations and every run trained on (each run\'s `best.pt` was '
        'also selected on them by its periodic evaluation); "unseen targets": scenario seed '
        f'{plan.unseen}, a target set no run trained on. Each cell: success per seed, then the '
        'mean over the seeds and its 95% interval.', '',
        STATISTICS, '',
        *([f'Anatomies: {", ".join(f"`{r.anatomy}`" for r in results)}; each run trains and '
           'is evaluated in its own anatomy.', ''] if len(results) > 1 else []),
        *budgets_paragraph(plan), '']
    if 'dynamic' in plan.modes:
        lines += [f'Dynamic: as the committed dynamic policy was made, each budget\'s static '
                  f'`best.pt` re-trained {plan.dynamic_steps:,} steps in the beating aorta '
                  '(`train --mode dynamic --init-from .../best.pt`), then its `best.pt` '
                  '(its `final.pt` when it made no periodic evaluation) evaluated in the '
                  'dynamic simulator. Every method is re-trained the same way.', '']
    lines += [f'Paper figures (`paper.tex`): static and ablations from §V-A (C-GAIL 80%, GAIL '
              f'42%, mu = 0 11%, lambda = 0 58%, nu = 0 48%), dynamic from §V-A (C-GAIL 17%, '
              f'GAIL 0%); the paper trained 5e5 steps by its Table III, while the authors\' '
              f'code ran 5M (GAIL) and 8M (C-GAIL, PPO) steps (`docs/fidelity.md`). Their '
              f'second anatomy ({PAPER_SECOND_ANATOMY}%, Table IV) is not part of this study. '
              '† budget not reached yet (steps reached so far; no evaluation). * the authors\' '
              'repository has no ablation run: their C-GAIL run\'s budget.', '']
    by_anatomy = len(results) > 1
    for options in plan.options():
        lines += [f'## Option set `{options}`', '']
        for res in results:
            base = baseline_line(res, options)
            if base:
                lines += [f'`{res.anatomy}`: {base}' if by_anatomy else base, '']
        summary = summary_table(results, options)
        if summary:
            lines += ['Every method at each of its budgets, over the seeds (training targets '
                      'and unseen targets; the paper\'s figure beside the training targets):',
                      '', *summary, '']
        for title, budgets in own_budget_orderings(plan, options):
            lines += [f'Ordering, {title} (ties: within 5 points):', '']
            for res in results:
                lines += [f'- `{res.anatomy}` {ln[2:]}' if by_anatomy else ln
                          for ln in ordering_lines(res, budgets)]
            lines.append('')
        for n in plan.budgets:
            if not methods_at(plan, options, n):
                continue
            lines += [f'### {n:,} steps', '', *budget_table(results, options, n), '']
            at = {m: n for m in methods_at(plan, options, n)}
            if len(at) > 1:  # else the orderings across budgets compare it
                lines += ['Ordering (ties: within 5 points):', '']
                for res in results:
                    lines += [f'- `{res.anatomy}` {ln[2:]}' if by_anatomy else ln
                              for ln in ordering_lines(res, at)]
                lines.append('')
        for res in results:
            # the default anatomy's pictures keep their names; another's carry its name
            stem = f'curves_{options}' if res.anatomy == DEFAULT_ANATOMY else \
                f'curves_{res.anatomy}_{options}'
            where = f' in `{res.anatomy}`' if by_anatomy else ''
            curves = static_curves(res, options)
            png = f'{stem}_static.png'
            marks = sorted({n for m in methods_at(plan, options) for n in plan.budgets_of(m)})
            if plot_curves(curves, marks, out / png, f'option set {options}{where}: '
                           'static training, periodic evaluation (training targets)'):
                lines += [f'Learning curves{where} (periodic evaluation of each run on the '
                          'training targets, noise-free; one line per seed'
                          + (', a colour per method and budget' if plan.fresh else '')
                          + '; dotted: the budgets):', '', f'![static]({png})', '']
            dyn = {f'{m} from {n:,} seed {s}': res.dynamic_curves.get((m, s, n), [])
                   for m in methods_at(plan, options) for n in plan.budgets_of(m)
                   for s in plan.seeds}
            png = f'{stem}_dynamic.png'
            if 'dynamic' in plan.modes and plot_curves(
                    dyn, [], out / png, f'option set {options}{where}: dynamic re-training, '
                    'periodic evaluation', 'env steps of the re-training'):
                lines += [f'![dynamic]({png})', '']
    if notes:  # the reading of the tables above
        lines += [notes, '']
    walls = [f"{m}{f' {res.anatomy}' if by_anatomy else ''} seed {s} {n:,}: "
             f"{format_duration(float(snap['wall_s']))}"
             for res in results for (m, s, n), snap in sorted(res.snapshots.items())
             if snap.get('wall_s')]
    if walls:
        lines += [f"Training wall time ({'each run' if plan.fresh else 'cumulative'}, from "
                  '`train`): ' + '; '.join(walls) + '.', '']
    return '\n'.join(lines) + '\n'


#: The report's paragraph on the intervals.
STATISTICS = (
    'Mean: the mean of the seeds\' success rates (with as many trials per seed, the pooled '
    'rate). 95% CI in the tables: Student\'s t interval over the seeds (mean +- t(0.975, n-1) '
    's / sqrt(n), clipped to 0-100%), because the seed is what varies most: a run finds the '
    'path or does not, so the trials of one policy are not independent draws of the method\'s '
    'success, and an interval of the pooled trials would understate the spread. With 3 seeds '
    't(0.975, 2) = 4.30, so the interval is wide, and it has no width when the seeds agree. '
    'The summary also gives the range over the seeds and the 95% Wilson score interval of the '
    'pooled trials, which holds only the trial noise of these policies.')


def budgets_paragraph(plan: StudyPlan) -> list[str]:
    """What the budgets are and how each was trained (report lines)."""
    if plan.fresh:
        lines = ['Static: `train --mode static --max-steps N` from scratch for every budget N: '
                 'each budget is a run of its own, its linear schedules (learning rate, '
                 'epsilon, beta) decaying over that budget. The policy of a budget is its '
                 'run\'s `best.pt`.']
    else:
        lines = ['Static: `train --mode static` to each budget of `--steps`; a larger budget '
                 'continues the same run (`train --resume RUN --max-steps N`) after the smaller '
                 'budget\'s `best.pt` was kept, so the linear schedules of a continued run '
                 'first decayed towards the smaller budget. The policy of a budget is the run\'s '
                 '`best.pt` up to that budget.']
    if plan.method_budgets:
        lines += ['', 'Budgets per method (`--authors-budgets`: a `paper_code` preset at the '
                  'authors\' budgets of its method, with GAIL also where their run stopped; '
                  'ours at their preset\'s `max_steps`): ' + '; '.join(
                      f'`{m}` ' + ', '.join(f'{n:,}' for n in plan.budgets_of(m))
                      for m in plan.methods) + '.']
    return lines


def static_curves(res: StudyResults, options: str) -> dict[str, list[tuple[int, float]]]:
    """The static learning curves of an option set, one per run: ``<preset> seed <S>`` (the
    one continued run), or with fresh budgets ``<preset> <N> steps seed <S>``."""
    plan = res.plan
    if plan.fresh:
        return {f'{m} {n:,} steps seed {s}': res.curves.get((m, s, n), [])
                for m in methods_at(plan, options) for n in plan.budgets_of(m)
                for s in plan.seeds}
    return {f'{m} seed {s}': res.curves.get((m, s, plan.budgets_of(m)[-1]), [])
            for m in methods_at(plan, options) for s in plan.seeds}


#: A hand-written section of ``OUT`` that the report places after its tables: why the
#: ordering differs from the paper's, with the evidence (the results are generated; their
#: reading is not).
REASONS = 'reasons.md'
#: Its heading when it starts without one.
REASONS_HEADING = "## Why the ordering differs from the paper's"


def write_report(layout: Layout, plan: StudyPlan, command: str) -> Path:
    """Collect the results and write ``report.md`` (with ``OUT/reasons.md`` when there is
    one, :data:`REASONS`), the curves, ``results.csv`` and ``summary.csv``."""
    results = [collect(layout, plan, a.name) for a in plan.anatomies]
    layout.root.mkdir(parents=True, exist_ok=True)
    with (layout.root / 'results.csv').open('w', newline='') as f:
        csv.writer(f).writerows(results_rows(results))
    with (layout.root / 'summary.csv').open('w', newline='') as f:
        csv.writer(f).writerows([SUMMARY_HEAD, *summary_rows(results)])
    path = layout.root / 'report.md'
    reasons = layout.root / REASONS
    notes = reasons.read_text().strip() if reasons.is_file() else ''
    if notes and not notes.startswith('#'):  # a section of its own under the tables
        notes = f'{REASONS_HEADING}\n\n{notes}'
    path.write_text(build_report(results, command, layout.root, notes))
    return path


# ------------------------------------------------------------------------------------------
# Running: tasks (subprocesses with dependencies), scheduled --jobs at a time.


@dataclass
class Task:
    """One step of the study: a subprocess (or nothing to run) and what follows it."""

    key: str
    kind: str
    """``train``, ``export``, ``eval``: trainings are long, the rest short."""
    deps: list[str]
    done: Callable[[], bool]
    command: Callable[[], list[str] | None]
    """The command to run now (None: nothing to run, only ``post``); may raise StudyError."""
    post: Callable[[], None] | None = None
    run: Path | None = None
    """A training's run folder (progress lines)."""
    target: int = 0
    """A training's step budget (progress lines)."""
    order: int = 0
    keep: Callable[[], list[Path]] | None = None
    """The checkpoints (``*.pt``) the task needs while it is not done, which ``OUT/.gitignore``
    lets git commit (:func:`write_gitignore`)."""
    adopt: Callable[[], object] | None = None
    """Record by content what the task made before records were kept (:func:`adopt`)."""


def python_module(module: str, *args: str) -> list[str]:
    """``python -m module args`` with this interpreter."""
    return [sys.executable, '-m', module, *args]


def snapshot(run: Path, dest: Path, budget: int, log: Path) -> None:
    """Keep what a budget's result needs before the run continues: ``best.pt`` (or
    ``final.pt``), ``scalars.csv``, ``config.yaml``, then ``snapshot.json`` (written last).

    Raises:
        StudyError: the run is not at ``budget`` (or went one iteration past it).
    """
    sc = read_scalars(run / 'scalars.csv')
    step = last_step(sc)
    cfg = yaml.safe_load((run / 'config.yaml').read_text()) or {}
    per_iter = int(cfg.get('ppo', {}).get('buffer_size', 0)) or step
    if not (budget <= step < budget + per_iter):
        raise StudyError(f'{run}: expected the run at {budget:,} steps to snapshot, found it at '
                         f'{step:,}')
    dest.mkdir(parents=True, exist_ok=True)
    policy = 'best.pt' if (run / 'best.pt').is_file() else 'final.pt'
    shutil.copy2(run / policy, dest / 'best.pt')
    shutil.copy2(run / 'scalars.csv', dest / 'scalars.csv')
    shutil.copy2(run / 'config.yaml', dest / 'config.yaml')
    ev = [v for s, v in sc.get('eval/success_rate', []) if s <= step]
    info = {'budget': budget, 'step': step, 'policy': policy,
            'policy_sha256': sha256_file(dest / 'best.pt'),
            'best_eval_success': max(ev) if ev else None,
            'wall_s': wall_seconds_from_log(log),
            'time': datetime.datetime.now().isoformat(timespec='seconds')}
    tmp = dest / 'snapshot.json.tmp'
    tmp.write_text(json.dumps(info, indent=1) + '\n')
    tmp.replace(dest / 'snapshot.json')


def record_state(run: Path) -> None:
    """After a ``train`` invocation ended well: the step its final.pt holds and the sha256 of
    the policy an export takes from it (``best.pt``, else ``final.pt``), which tells whether
    that export is current once the checkpoints are not there (a git clone)."""
    policy = export_source(run / 'best.pt')
    (run / 'study_state.json').write_text(json.dumps(
        {'step': last_step(read_scalars(run / 'scalars.csv')),
         'policy_sha256': sha256_file(policy) if policy.is_file() else None}) + '\n')


#: Steps between the periodic checkpoints of every training of the study, whatever its preset
#: says (``paper_code`` presets keep the authors' 500,000): a stopped session loses at most this
#: much of a training. Checkpoints change nothing in the training; the superseded ones are
#: deleted when the training resumes.
CHECKPOINT_EVERY = 51_200


def train_command(run: Path, steps: int, fresh: list[str], common: list[str]) -> list[str] | None:
    """Resume ``run`` to ``steps``, start it fresh (``fresh`` + ``common``), or None when it
    already finished at ``steps``.

    Raises:
        StudyError: the run is already past ``steps`` (that budget was not kept in time).
    """
    if trained_to(run, steps):
        return None
    if resumable(run):
        at = resumable_step(run)
        if at >= steps:
            raise StudyError(f'{run}: expected a run before {steps:,} steps, found one at '
                             f'{at:,}: that budget was not snapshotted; use another --out')
        for step in checkpoint_steps(run)[:-1]:  # (superseded: a resume reads the latest only)
            (run / 'checkpoints' / f'step_{step}.pt').unlink()
        return python_module('cgail_learning.train', '--resume', str(run),
                             '--max-steps', str(steps), *common)
    if run.exists():
        shutil.rmtree(run)  # nothing to resume (no checkpoint): start again
    return python_module('cgail_learning.train', *fresh, '--max-steps', str(steps),
                         '--out', str(run), *common)


def up_to_date(output: Path, *inputs: Path) -> bool:
    """Whether ``output`` exists and is not older than any of the ``inputs`` that exist (the
    rule for outputs made before :func:`record_inputs`; file times mean nothing in a clone)."""
    if not output.is_file():
        return False
    t = output.stat().st_mtime
    return all(t >= i.stat().st_mtime for i in inputs if i.is_file())


# Content records: what an output was made from, by sha256, so that the study resumes from a
# git clone (arbitrary file times, no ``*.pt`` of finished work; ``--prepare-commit``).

#: An output's record lies beside it: ``static.onnx`` -> ``static.onnx.sha256.json``.
RECORD_SUFFIX = '.sha256.json'


def sha256_file(path: Path) -> str:
    """The sha256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with path.open('rb') as f:
        for chunk in iter(lambda: f.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest()


def record_path(output: Path) -> Path:
    """Where the record of ``output`` lies."""
    return output.with_name(output.name + RECORD_SUFFIX)


def record_inputs(output: Path, inputs: dict[str, Path]) -> None:
    """Write the record of ``output`` after it was made from ``inputs`` (name -> file): the
    sha256 of it and of each input (:func:`made_from` reads it)."""
    data = {'sha256': sha256_file(output),
            'inputs': {name: sha256_file(path) for name, path in inputs.items()}}
    tmp = record_path(output).with_suffix('.tmp')
    tmp.write_text(json.dumps(data, indent=1) + '\n')
    tmp.replace(record_path(output))


def made_from(output: Path, inputs: dict[str, Path],
              known: dict[str, str | None] | None = None) -> bool | None:
    """Whether ``output`` is what its record says and was made from the ``inputs`` as they are
    now; None when it has no record (made before records: judge it by :func:`up_to_date`).

    An input that is not here (a checkpoint left out of git) is compared by the sha256 that
    ``known`` gives for its name (recorded where it was made: ``snapshot.json``,
    ``study_state.json``); with neither, the record stands.
    """
    path = record_path(output)
    if not output.is_file():
        return False
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        recorded, was = data['sha256'], dict(data['inputs'])
    except (ValueError, KeyError, TypeError):
        return False  # a damaged record: make the output again
    if recorded != sha256_file(output):
        return False
    for name, file in inputs.items():
        now = sha256_file(file) if file.is_file() else (known or {}).get(name)
        if name not in was or (now is not None and now != was[name]):
            return False
    return True


def current(output: Path, inputs: dict[str, Path],
            known: dict[str, str | None] | None = None) -> bool:
    """Whether ``output`` is current: by its record (:func:`made_from`), or, made before
    records, not older than the inputs that are here (:func:`up_to_date`)."""
    by_content = made_from(output, inputs, known)
    return up_to_date(output, *inputs.values()) if by_content is None else by_content


def adopt(output: Path, inputs: dict[str, Path]) -> bool:
    """Record ``output`` made before records (it has none) when its file times say it is
    current and every input is here, so that a clone judges it by content; returns whether it
    wrote the record. Run where the output was made: a clone's file times mean nothing."""
    if (not output.is_file() or record_path(output).is_file()
            or not all(p.is_file() for p in inputs.values())
            or not up_to_date(output, *inputs.values())):
        return False
    record_inputs(output, inputs)
    return True


def recorded_sha256(path: Path, key: str = 'policy_sha256') -> str | None:
    """``key`` of a JSON file (``snapshot.json``, ``study_state.json``); None when absent."""
    if not path.is_file():
        return None
    try:
        value = json.loads(path.read_text()).get(key)
    except (ValueError, AttributeError):
        return None
    return value if isinstance(value, str) else None


def adopt_policy_hash(path: Path, policy: Path) -> bool:
    """Add ``policy_sha256`` of ``policy`` to ``path`` (``snapshot.json``,
    ``study_state.json``) written before it held one; returns whether it did."""
    if not path.is_file() or not policy.is_file() or recorded_sha256(path) is not None:
        return False
    data = json.loads(path.read_text())
    data['policy_sha256'] = sha256_file(policy)
    tmp = path.with_suffix('.tmp')
    tmp.write_text(json.dumps(data, indent=1) + '\n')
    tmp.replace(path)
    return True


def evaluated(folder: Path, policy: Path | None, trials: int) -> bool:
    """Whether ``folder/results.json`` holds ``trials`` trials of the current ``policy``
    (:func:`current`: by the sha256 of the policy it recorded, else by file times)."""
    path = folder / 'results.json'
    if not path.is_file() or (policy is not None and not current(path, {'policy': policy})):
        return False
    return bool(json.loads(path.read_text()).get('trials') == trials)


def export_source(ckpt: Path) -> Path:
    """The checkpoint an export of ``ckpt`` (``best.pt``) takes: it, or ``final.pt`` beside
    it when the run made no periodic evaluation."""
    return ckpt if ckpt.is_file() else ckpt.with_name('final.pt')


def exported(policy: Path, ckpt: Path, known_from: Path) -> bool:
    """Whether ``policy`` is the current export of ``ckpt`` (:func:`export_source`): by its
    record, with the checkpoint's sha256 from ``known_from`` (``snapshot.json``,
    ``study_state.json``) when the checkpoint is not here; else by file times."""
    return current(policy, {'checkpoint': export_source(ckpt)},
                   {'checkpoint': recorded_sha256(known_from)})


def dynamic_done(run: Path, steps: int, policy: Path | None = None) -> bool:
    """Whether the dynamic re-training in ``run`` finished its ``steps``: its ``final.pt`` is
    here, or (its checkpoints left out of git) ``policy`` is the recorded export of it."""
    if not (run / 'study_state.json').is_file():
        return False
    if trained_to(run, steps):
        return True
    return (policy is not None and run_max_steps(run) == steps
            and last_step(read_scalars(run / 'scalars.csv')) >= steps
            and made_from(policy, {'checkpoint': export_source(run / 'best.pt')},
                          {'checkpoint': recorded_sha256(run / 'study_state.json')}) is True)


def export_command(ckpt: Path, policy: Path) -> list[str]:
    """Export ``ckpt`` (``best.pt``; ``final.pt`` beside it when the run made no periodic
    evaluation) to ``policy``."""
    return python_module('cgail_learning.export', str(export_source(ckpt)), '--out', str(policy))


def record_export(ckpt: Path, policy: Path) -> None:
    """After an export: record the checkpoint ``policy`` was made from."""
    record_inputs(policy, {'checkpoint': export_source(ckpt)})


def export_keep(ckpt: Path) -> list[Path]:
    """What an export not done needs: its checkpoint (:func:`export_source`)."""
    return [export_source(ckpt)]


def adopt_export(ckpt: Path, policy: Path) -> bool:
    """:func:`adopt` an export made before records."""
    return adopt(policy, {'checkpoint': export_source(ckpt)})


def dynamic_keep(run: Path, init: Path) -> list[Path]:
    """What a dynamic re-training not done needs: its :func:`resume_files`, and the static
    ``best.pt`` it starts from (``init``) should it restart."""
    return [*resume_files(run), init]


def adopt_state(state: Path, ckpt: Path) -> bool:
    """:func:`adopt_policy_hash` of a finished run's ``study_state.json`` made before it held
    one."""
    return adopt_policy_hash(state, export_source(ckpt))


def resume_files(run: Path) -> list[Path]:
    """What ``train --resume`` needs of ``run`` beside its small files (``config.yaml``,
    ``scalars.csv``, ``study_state.json``): the highest periodic checkpoint and ``final.pt``
    (:func:`cgail_learning.train.latest_checkpoint` takes the later of them), and ``best.pt``
    (the resumed run overwrites it only with a better evaluation). Those that exist."""
    steps = checkpoint_steps(run)
    files = ([run / 'checkpoints' / f'step_{steps[-1]}.pt'] if steps else []) + [
        run / 'final.pt', run / 'best.pt']
    return [f for f in files if f.is_file()]


def static_post(layout: Layout, preset: str, seed: int, budget: int, log: Path) -> None:
    """After the static training reached ``budget``: record its step, snapshot the budget
    (its wall time from the training's ``log``)."""
    run = layout.static_run(preset, seed, budget)
    record_state(run)
    snapshot(run, layout.budget(preset, seed, budget), budget, log)


def plan_tasks(root: Layout, plan: StudyPlan) -> list[Task]:
    """Every task of the study, dependencies first, in every anatomy of the plan.

    Task keys are ``<preset>/seed<S>/<budget>/<step>`` in the default anatomy and
    ``<anatomy>/<preset>/...`` in another; their logs all lie in ``root``'s ``logs/``.
    Order among ready tasks: exports and evaluations, then baselines and dynamic re-trainings,
    then static trainings; with continued budgets budget by budget (with ``--jobs`` 1, the
    whole smaller budget before the larger), with fresh budgets (no budget waits for another)
    seed by seed (with ``--jobs`` 1, every method and budget of the first seed before the
    second seed's, so the report compares the methods early).
    """
    tasks: list[Task] = []
    evaluate = 'cgail_learning.evaluate'
    for anatomy in plan.anatomies:
        layout = plan_layout(root, plan).of_anatomy(anatomy.name)
        at = '' if anatomy.name == DEFAULT_ANATOMY else f'{anatomy.name}/'
        common = ['--demos', *[str(d) for d in anatomy.demos], '--threads', '1',
                  '--checkpoint-every', str(CHECKPOINT_EVERY),
                  '--no-progress', *anatomy.train_args]
        in_anatomy = ['--trials', str(plan.trials), *anatomy.eval_args]
        for m in plan.methods:
            for si, s in enumerate(plan.seeds):
                prev: str | None = None
                for bi, n in enumerate(plan.budgets_of(m)):
                    run = layout.static_run(m, s, n)
                    key = f'{at}{m}/seed{s}/{n}'
                    static_key = f'{key}/train-static'
                    rank = 10 * (si if plan.fresh else bi)
                    snap = layout.snapshot(m, s, n)
                    best = snap.with_name('best.pt')
                    tasks.append(Task(
                        static_key, 'train', [prev] if prev and not plan.fresh else [],
                        done=snap.is_file,
                        command=partial(train_command, run, n,
                                        ['--preset', m, '--seed', str(s)],
                                        ['--mode', 'static', *common]),
                        post=partial(static_post, layout, m, s, n, root.log(static_key)),
                        run=run, target=n, order=rank + 2, keep=partial(resume_files, run),
                        adopt=partial(adopt_policy_hash, snap, best)))
                    prev = static_key
                    for mode in plan.modes:
                        policy = layout.policy(m, s, n, mode)
                        if mode == 'static':
                            ckpt, source, known = best, static_key, snap
                        else:
                            dyn, d = layout.dynamic_run(m, s, n), plan.dynamic_steps
                            ckpt, source = dyn / 'best.pt', f'{key}/train-dynamic'
                            known = dyn / 'study_state.json'
                            tasks.append(Task(
                                source, 'train', [static_key],
                                done=partial(dynamic_done, dyn, d, policy),
                                command=partial(train_command, dyn, d,
                                                ['--preset', m, '--seed', str(s), '--init-from',
                                                 str(best)], ['--mode', 'dynamic', *common]),
                                post=partial(record_state, dyn), run=dyn, target=d,
                                order=rank + 1,
                                keep=partial(dynamic_keep, dyn, best),
                                adopt=partial(adopt_state, known, ckpt)))
                        tasks.append(Task(f'{key}/export-{mode}', 'export', [source],
                                          done=partial(exported, policy, ckpt, known),
                                          command=partial(export_command, ckpt, policy),
                                          post=partial(record_export, ckpt, policy),
                                          keep=partial(export_keep, ckpt),
                                          adopt=partial(adopt_export, ckpt, policy)))
                        for k in plan.target_sets:
                            folder = layout.evaluation(m, s, n, mode, k)
                            results = {'policy': policy}
                            tasks.append(Task(
                                f'{key}/eval-{mode}-targets{k}', 'eval',
                                [f'{key}/export-{mode}'],
                                done=partial(evaluated, folder, policy, plan.trials),
                                command=partial(python_module, evaluate, '--policy',
                                                f'{m}={policy}', '--baselines', '--modes', mode,
                                                *in_anatomy, '--scenario-seed', str(k),
                                                '--out', str(folder)),
                                post=partial(record_inputs, folder / 'results.json', results),
                                adopt=partial(adopt, folder / 'results.json', results)))
        if plan.baselines:
            for options in plan.options():
                for mode in plan.modes:
                    for k in plan.target_sets:
                        folder = layout.baselines(options, mode, k)
                        tasks.append(Task(
                            f'{at}baselines/{options}/{mode}-targets{k}', 'eval', [],
                            done=partial(evaluated, folder, None, plan.trials),
                            command=partial(python_module, evaluate, '--baselines',
                                            *plan.baselines, '--env-options', options,
                                            '--modes', mode, *in_anatomy, '--scenario-seed',
                                            str(k), '--out', str(folder)),
                            order=1))
    return tasks


#: The fixed part of ``OUT/.gitignore`` (:func:`write_gitignore`).
GITIGNORE_HEAD = """\
# Written by bench/insilico_study.py on every run and by --prepare-commit: what `git add OUT`
# commits so that the study resumes from a clone. Kept: reports, CSVs, PNGs, JSON (snapshots,
# content records *.sha256.json, evaluation results), YAML, ONNX policies, logs. Left out:
# the lock, temporary files, TensorBoard event files (scalars.csv holds the same) and every
# checkpoint (*.pt) but those a task not done yet needs (the "!" lines: an unfinished
# training's latest checkpoint, final.pt and best.pt; a snapshot's best.pt until its exports
# and its dynamic re-training are done).
/.lock
*.tmp
events.out.tfevents.*
*.pt
"""


def gitignore_pattern(path: Path) -> str:
    """A ``.gitignore`` line matching exactly ``path`` (relative to the file's folder), with
    git's special characters escaped."""
    return '/' + re.sub(r'([\\*?\[\]!# ])', r'\\\1', path.as_posix())


def gitignore_text(root: Path, tasks: Sequence[Task]) -> str:
    """``OUT/.gitignore``: :data:`GITIGNORE_HEAD`, then a ``!`` line for every checkpoint that
    a task not done needs (:attr:`Task.keep`) and that exists under ``root``."""
    keep = sorted({p.resolve() for t in tasks if t.keep is not None and not t.done()
                   for p in t.keep() if p.is_file()})
    lines = [f'!{gitignore_pattern(p.relative_to(root.resolve()))}' for p in keep
             if p.is_relative_to(root.resolve())]
    return GITIGNORE_HEAD + ''.join(f'{ln}\n' for ln in lines)


def write_gitignore(root: Path, tasks: Sequence[Task]) -> Path:
    """Write ``root/.gitignore`` (:func:`gitignore_text`); returns its path."""
    root.mkdir(parents=True, exist_ok=True)
    path = root / '.gitignore'
    tmp = path.with_name('.gitignore.tmp')
    tmp.write_text(gitignore_text(root, tasks))
    tmp.replace(path)
    return path


def adopt_records(tasks: Sequence[Task]) -> int:
    """Record by content what the tasks made before records were kept (:attr:`Task.adopt`,
    judged by file times, so on the machine that made it); returns how many it recorded."""
    return sum(bool(t.adopt()) for t in tasks if t.adopt is not None)


def prepare_commit(layout: Layout, plan: StudyPlan) -> tuple[Path, int]:
    """``--prepare-commit``: record what is done by content (:func:`adopt_records`) and write
    ``OUT/.gitignore``; returns its path and how many records were added."""
    tasks = plan_tasks(layout, plan)
    added = adopt_records(tasks)
    return write_gitignore(layout.root, tasks), added


def child_env() -> dict[str, str]:
    """The environment of every process: one thread for torch, BLAS and numba."""
    env = dict(os.environ)
    for name in ('OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'OPENBLAS_NUM_THREADS',
                 'NUMBA_NUM_THREADS'):
        env[name] = '1'
    return env


def stamp() -> str:
    """Wall-clock time for the progress lines."""
    return time.strftime('%H:%M:%S')


def say(line: str) -> None:
    """One progress line."""
    print(f'[{stamp()}] {line}', flush=True)


def last_log_line(path: Path, containing: str = '') -> str:
    """The last non-empty line of a log (with ``containing`` in it, if given) since the last
    invocation's header."""
    if not path.is_file():
        return ''
    text = path.read_text(errors='replace').rsplit('\n=== ', 1)[-1]
    lines = [ln for ln in text.splitlines() if ln.strip() and containing in ln]
    return lines[-1][-200:] if lines else ''


class Process(Protocol):
    """What the scheduler needs of a running task: :class:`subprocess.Popen` has it, and so
    has a task run elsewhere (``bench/sweep.py``'s Ray tasks)."""

    def poll(self) -> int | None:
        """The exit status, or None while it runs."""

    def terminate(self) -> None:
        """Ask it to stop (SIGTERM: a training keeps its checkpoints)."""

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the exit status; raises :class:`subprocess.TimeoutExpired`."""

    def kill(self) -> None:
        """Stop it now."""


#: Starts a task's command with its output appended to the log file; returns its process.
Launcher = Callable[[list[str], Path], Process]


def launch_process(cmd: list[str], log: Path) -> Process:
    """The default :data:`Launcher`: a child process of this one, in :func:`child_env`."""
    with log.open('a') as f:
        return subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=child_env(),
                                stdin=subprocess.DEVNULL)


@dataclass
class Running:
    """A task's running process."""

    task: Task
    proc: Process
    started: float
    since: int
    """The step a training starts or resumes from."""


def run_tasks(tasks: list[Task], layout: Layout, jobs: int, progress_every: float,
              on_done: Callable[[Task], None] | None = None,
              launch: Launcher = launch_process) -> tuple[int, int]:
    """Run the tasks that are not done, ``jobs`` at a time, dependencies first, each started
    by ``launch`` (default: a local child process).

    Returns:
        (tasks done, tasks failed or blocked by a failure).
    """
    by_key = {t.key: t for t in tasks}
    state = {t.key: 'done' if t.done() else 'todo' for t in tasks}
    skipped = sum(v == 'done' for v in state.values())
    todo = len(tasks) - skipped
    say(f'{len(tasks)} tasks: {skipped} already done, {todo} to run, {jobs} at a time')
    running: dict[str, Running] = {}
    last_progress = time.monotonic()
    layout.root.joinpath('logs').mkdir(parents=True, exist_ok=True)

    def finish(key: str, ok: bool, why: str = '') -> None:
        state[key] = 'done' if ok else 'failed'
        if ok and on_done is not None:
            on_done(by_key[key])
        if not ok:
            say(f'FAILED {key}: {why}')

    try:
        while True:
            progressed = False  # a task finished without a process: its dependants may be ready
            for key, st in state.items():  # a failure blocks what depends on it
                if st == 'todo' and any(state[d] in ('failed', 'blocked')
                                        for d in by_key[key].deps):
                    state[key] = 'blocked'
            ready = sorted((t for t in tasks if state[t.key] == 'todo'
                            and all(state[d] == 'done' for d in t.deps)),
                           key=lambda t: (t.order, tasks.index(t)))
            for t in ready:
                if len(running) >= jobs:
                    break
                try:
                    cmd = t.command()
                    if cmd is None:  # nothing to run: the outputs are there
                        if t.post is not None:
                            t.post()
                        finish(t.key, t.done(), 'not done after its step')
                        progressed = True
                        continue
                except (StudyError, OSError) as exc:
                    finish(t.key, False, str(exc))
                    continue
                log_path = layout.log(t.key)
                with log_path.open('a') as log:
                    log.write(f'=== {datetime.datetime.now().isoformat(timespec="seconds")} '
                              f'{shlex.join(cmd)}\n')
                proc = launch(cmd, log_path)
                since = resumable_step(t.run) if t.run is not None else 0
                running[t.key] = Running(t, proc, time.monotonic(), since)
                state[t.key] = 'running'
                say(f'start {t.key} (log {log_path.relative_to(layout.root)})')
            if not running:
                if progressed:
                    continue
                break
            time.sleep(1.0)
            for key, r in list(running.items()):
                rc = r.proc.poll()
                if rc is None:
                    continue
                del running[key]
                took = format_duration(time.monotonic() - r.started)
                if rc != 0:
                    finish(key, False, f'exit {rc} after {took}: '
                           f'{last_log_line(layout.log(key))}')
                    continue
                try:
                    if r.task.post is not None:
                        r.task.post()
                except (StudyError, OSError) as exc:
                    finish(key, False, str(exc))
                    continue
                done = r.task.done()
                if done:
                    result = last_log_line(layout.log(key), ': success ')
                    say(f'done {key} in {took}' + (f' ({result})' if result else ''))
                finish(key, done, 'its outputs are missing after exit 0')
            if time.monotonic() - last_progress >= progress_every:
                last_progress = time.monotonic()
                for key, r in running.items():
                    if r.task.run is not None:
                        say(f'{key}: {run_progress(r.task.run, r.since).line(r.task.target)}')
    finally:
        for key, r in running.items():
            say(f'stopping {key}; it resumes on the next run')
            r.proc.terminate()
        for r in running.values():
            try:
                r.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                r.proc.kill()
                r.proc.wait()
    n_done = sum(v == 'done' for v in state.values())
    return n_done, len(tasks) - n_done


# ------------------------------------------------------------------------------------------
# Command line.


def build_parser() -> argparse.ArgumentParser:
    """The study's command line."""
    p = argparse.ArgumentParser(prog='insilico_study', description=__doc__.split('\n')[0])
    p.add_argument('--methods', nargs='+', default=list(DEFAULT_METHODS), metavar='PRESET',
                   help='training presets (config/presets/); default: the five "ours" presets')
    p.add_argument('--seeds', nargs='+', type=int, default=[0, 1])
    p.add_argument('--steps', nargs='+', type=int, default=None, metavar='N',
                   help='step budgets, increasing (default 500000 2000000); a larger one '
                        'continues the smaller run unless --fresh-budgets')
    p.add_argument('--fresh-budgets', action='store_true',
                   help='train every budget as its own run from scratch, its schedules '
                        'decaying over that budget (OUT/<preset>/seed<S>/budget_<N>/)')
    p.add_argument('--authors-budgets', action='store_true',
                   help="each preset's own budgets instead of --steps: a paper_code preset "
                        "the authors' (8M; GAIL 5M and 1,275,443, where their run stopped), "
                        "ours their preset's max_steps")
    p.add_argument('--budget-scale', type=float, default=1.0, metavar='F',
                   help='with --authors-budgets: multiply every budget by F in (0, 1], for a '
                        'smoke run of the same shape')
    p.add_argument('--modes', nargs='+', choices=MODES, default=list(MODES))
    p.add_argument('--jobs', type=int, default=1,
                   help='processes at a time (trainings use 1 torch thread each)')
    p.add_argument('--trials', type=int, default=100, help='evaluation trials per policy')
    p.add_argument('--out', type=Path, default=Path('runs/insilico_study'))
    p.add_argument('--demos', nargs='+', type=Path, default=[WS / 'bags/demos/default'],
                   help='demonstrations (train --demos)')
    p.add_argument('--unseen-scenario-seed', type=int, default=1,
                   help='target set of the unseen-target evaluation (not 0, the training one)')
    p.add_argument('--dynamic-steps', type=int, default=102_400,
                   help='steps of the dynamic re-training from each static best')
    p.add_argument('--baselines', nargs='*', choices=('centerline', 'expert'),
                   default=['centerline'], help='reference methods evaluated on the same targets')
    p.add_argument('--progress-every', type=float, default=60.0,
                   help='seconds between progress lines of the running trainings')
    p.add_argument('--report-only', action='store_true',
                   help='rebuild OUT/report.md from what exists; run nothing')
    p.add_argument('--prepare-commit', action='store_true',
                   help='before `git add OUT`: record what is done by content (outputs made '
                        'before records, judged by their file times here) and write '
                        'OUT/.gitignore (every run writes it too); run nothing')
    return p


def check_args(args: argparse.Namespace) -> StudyPlan:
    """The plan of valid arguments.

    Raises:
        StudyError: an unknown preset, duplicate methods or seeds, bad budgets or counts.
    """
    from cgail_learning.config import load_config
    from cgail_learning.errors import ConfigError

    authors = getattr(args, 'authors_budgets', False)
    scale = getattr(args, 'budget_scale', 1.0)
    if authors and args.steps is not None:
        raise StudyError(f'--steps: expected no budgets with --authors-budgets (each preset '
                         f'has its own), found {args.steps}')
    if scale != 1.0 and not authors:
        raise StudyError(f'--budget-scale: expected only with --authors-budgets, found {scale}')
    budgets = check_budgets(DEFAULT_STEPS if args.steps is None else args.steps)
    for name, values in (('--methods', args.methods), ('--seeds', args.seeds),
                         ('--modes', args.modes)):
        if len(set(values)) != len(values):
            raise StudyError(f'{name}: expected distinct values, found {values}')
    if any(s < 0 for s in args.seeds):
        raise StudyError(f'--seeds: expected seeds >= 0, found {args.seeds}')
    for name, value in (('--jobs', args.jobs), ('--trials', args.trials),
                        ('--dynamic-steps', args.dynamic_steps)):
        if value < 1:
            raise StudyError(f'{name}: expected >= 1, found {value}')
    if args.unseen_scenario_seed < 1:
        raise StudyError(f'--unseen-scenario-seed: expected a target set other than the '
                         f'training one (0), found {args.unseen_scenario_seed}')
    option_sets, max_steps = {}, {}
    for m in args.methods:
        try:
            cfg = load_config(m)
        except ConfigError as exc:
            raise StudyError(f'--methods: {exc}') from None
        option_sets[m], max_steps[m] = cfg.env_options, cfg.max_steps
    per_method = method_budgets(option_sets, max_steps, scale) if authors else {}
    if per_method:
        budgets = tuple(sorted({n for b in per_method.values() for n in b}))
    if not args.report_only:
        missing = [str(d) for d in args.demos if not d.exists()]
        if missing:
            raise StudyError(f'--demos: expected existing demonstrations, found none at '
                             f'{missing}')
    anatomy = Anatomy.named(DEFAULT_ANATOMY, [d.resolve() for d in args.demos])
    return StudyPlan(tuple(args.methods), tuple(args.seeds), budgets, tuple(args.modes),
                     option_sets, args.trials, args.unseen_scenario_seed, args.dynamic_steps,
                     tuple(args.baselines), (anatomy,),
                     fresh=getattr(args, 'fresh_budgets', False), method_budgets=per_method)


def command_line(args: argparse.Namespace) -> str:
    """The command that re-runs this study (relative paths where they are inside WS)."""
    def rel(p: Path) -> str:
        p = p.resolve()
        return str(p.relative_to(WS)) if p.is_relative_to(WS) else str(p)

    if args.authors_budgets:
        budgets = ['--authors-budgets'] + (['--budget-scale', str(args.budget_scale)]
                                           if args.budget_scale != 1.0 else [])
    else:
        budgets = ['--steps', *map(str, args.steps or DEFAULT_STEPS)]
    parts = ['scripts/ws', 'python', 'bench/insilico_study.py', '--methods', *args.methods,
             '--seeds', *map(str, args.seeds), *budgets,
             *(['--fresh-budgets'] if args.fresh_budgets else []), '--modes',
             *args.modes, '--trials', str(args.trials), '--dynamic-steps',
             str(args.dynamic_steps), '--unseen-scenario-seed', str(args.unseen_scenario_seed),
             '--baselines', *args.baselines, '--demos', *map(rel, args.demos),
             '--out', rel(args.out), '--jobs', str(args.jobs)]
    return shlex.join(parts)


@contextlib.contextmanager
def study_lock(root: Path) -> Iterator[None]:
    """Hold ``root/.lock`` so two studies never share a folder.

    Raises:
        StudyError: another study holds it.
    """
    import fcntl

    root.mkdir(parents=True, exist_ok=True)
    with (root / '.lock').open('w') as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise StudyError(f'--out {root}: expected a folder no other study is using, found '
                             'one running there') from None
        f.write(f'{os.getpid()}\n')
        f.flush()
        yield


def left_out(layout: Layout, plan: StudyPlan) -> list[str]:
    """The presets that have runs in the study's folder (``<preset>/seed<S>/`` of any anatomy)
    but are not in ``plan``: the report this plan writes leaves them out, and so does the
    ``.gitignore``'s list of checkpoints kept for their unfinished tasks."""
    roots = [layout.of_anatomy(a.name).root for a in plan.anatomies]
    found = {d.name for r in roots if r.is_dir() for d in r.iterdir()
             if d.is_dir() and any(c.is_dir() and SEED_FOLDER.fullmatch(c.name)
                                   for c in d.iterdir())}
    return sorted(found - set(plan.methods))


def note_left_out(layout: Layout, plan: StudyPlan) -> None:
    """Say which presets of the folder :func:`left_out` finds (nothing when none)."""
    others = left_out(layout, plan)
    if others:
        say(f'note: {layout.root} also holds runs of {", ".join(others)}, which this command '
            'leaves out of the report and of .gitignore; add them to --methods to keep them')



def _terminate(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    args = build_parser().parse_args(argv)
    try:
        plan = check_args(args)
    except StudyError as exc:
        print(f'insilico_study: error: {exc}', file=sys.stderr)
        return 2
    layout = Layout(args.out.resolve(), plan.fresh)
    command = command_line(args)
    note_left_out(layout, plan)
    if args.report_only:
        say(f'report: {write_report(layout, plan, command)}')
        return 0
    if args.prepare_commit:
        path, added = prepare_commit(layout, plan)
        say(f'{added} outputs recorded by content; {path} written: git add {args.out}')
        return 0
    try:
        with study_lock(layout.root):
            return run_study(layout, plan, command, args.jobs, args.progress_every)
    except StudyError as exc:
        print(f'insilico_study: error: {exc}', file=sys.stderr)
        return 2


def run_study(layout: Layout, plan: StudyPlan, command: str, jobs: int, progress_every: float,
              launch: Launcher = launch_process) -> int:
    """Run what is not done of ``plan`` (the caller holds :func:`study_lock`), rewriting the
    report after every evaluation and at the end; SIGTERM stops it as Ctrl-C does.

    Returns:
        The exit status: 0 all done, 1 a task failed, 130 interrupted.
    """
    signal.signal(signal.SIGTERM, _terminate)
    t0 = time.monotonic()
    tasks = plan_tasks(layout, plan)
    adopted = adopt_records(tasks)
    if adopted:
        say(f'{adopted} outputs made before content records: recorded by content')
    write_gitignore(layout.root, tasks)

    def on_done(task: Task) -> None:
        if task.kind == 'eval':
            write_report(layout, plan, command)
        write_gitignore(layout.root, tasks)

    try:
        n_done, n_bad = run_tasks(tasks, layout, jobs, progress_every, on_done, launch)
    except KeyboardInterrupt:
        say('interrupted; re-run the same command to continue')
        write_report(layout, plan, command)
        write_gitignore(layout.root, tasks)
        return 130
    write_gitignore(layout.root, tasks)
    path = write_report(layout, plan, command)
    say(f'{n_done} of {n_done + n_bad} tasks done in '
        f'{format_duration(time.monotonic() - t0)}; report: {path}')
    return 0 if n_bad == 0 else 1


if __name__ == '__main__':
    sys.exit(main())

"""``cgail evaluate``: the paper's in-silico experiments as a markdown report with box plots.

Example::

    cgail evaluate --policy C-GAIL=models/cgail_default.onnx --policy GAIL=runs/gail.onnx \\
        --baselines centerline expert --modes static dynamic --trials 100 --out runs/evaluate

Each method runs ``--trials`` episodes; trial k uses start ``k % 3``, target ``(k // 3) % 5`` and
seed ``seed + k``, so every method sees the same start x target sequence. Metrics (paper
Sec. IV-C): success rate delta (tip within epsilon = 10 mm of the target), timesteps T_s (all
trials and successful ones), targeting error T_a (minimum tip-target distance, mm; all trials and
successful ones). Kruskal-Wallis tests (p < 0.05) compare the methods on T_s and T_a.
``--scenario-seed S`` evaluates on the anatomy's target set ``S`` (``EnvConfig.scenario_seed``;
0, the default, is the set the demonstrations and the presets train on, so another seed gives
targets no run trained on). Next to ``report.md`` goes ``results.json``: per mode and method
the summary and every trial's outcome, for scripts (``bench/insilico_study.py``).

**Why every trial differs (tracking noise).** With 3 starts x 5 targets there are only 15
distinct scenarios, and in the rigid-wall simulator a deterministic planner is a deterministic
function of the scenario: 100 noise-free trials would be 15 outcomes each counted ~7 times, which
inflates every Kruskal-Wallis p-value (the test assumes independent samples). So, as on the rig,
the learned policies and the centerline follower perceive the tip through a simulated EM tracker
(:class:`TrackingNoise`, default the NDI Aurora 6DOF sensor's RMS accuracy, 0.48 mm and 0.30 deg,
drawn per step from trial k's seed): the observation (position, axes, u, v and the 25 rays, which
are cast from the perceived pose) is that of the perceived pose while the simulator moves the true
catheter. Each trial is then an independent sample of the planner's behaviour; the report gives
the number of distinct outcomes. ``--position-noise-mm 0 --orientation-noise-deg 0`` gives the
noise-free simulator (and then each repeated start x target pair is simulated once in static
mode). The scripted expert is the demonstrator with the simulator's state (no tracker), seeded.

**Held-out anatomies** (``--population N``): the same trials in each of the first N held-out
population anatomies (:data:`cgail_sim.population.HELD_OUT_SEEDS`, which no training
run may use), pooled per method, with a per-anatomy success table at the end of the report.
With ``--anatomy default`` or ``elongated`` and a generalist policy (trained on the
population only) the targets are unseen too. Several ``--anatomy`` (e.g. the held-out real
aortas ``avt-D4 avt-D10 avt-D13 avt-D15 avt-D18``, :data:`cgail_sim.anatomy_spec.REAL_HELD_OUT`)
are pooled the same way.

**Failures drawn.** For each method and anatomy with a failed trial, ``failures_<mode>_<anatomy>
_<method>.png`` shows the tip paths of its first failures (where each ended, and its target),
linked at the end of the report (``--no-failure-pictures`` skips them).

**Env option set.** The simulator runs in the option set the policies were trained in (their
contracts' ``env_options``: ``ours`` or ``paper_code``, :data:`cgail_sim.config.
OPTION_SETS`), so a ``paper_code`` policy sees its 27-float observation; policies of different
option sets are evaluated separately. ``--env-options`` sets it for a run of baselines only.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import dataclasses
from dataclasses import dataclass
import json
import logging
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np
from tqdm import tqdm

from cgail_learning.errors import LearningError
from cgail_planner.core.onnx_policy import OnnxPolicy
from cgail_planner.core.rotations import rotvec_to_matrix
from cgail_sim.cli_help import tool_parser

_LOG = logging.getLogger(__name__)

#: Wall-clock bound of the rrt baseline's search, s: generous, so that its iteration budget
#: (``RrtConfig.max_iterations``) ends every search and the results do not depend on the host.
RRT_TIME_LIMIT_S = 30.0

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class TrackingNoise:
    """RMS errors of the simulated EM tracker through which the evaluated methods see the tip.

    Defaults: NDI Aurora 6DOF sensor in the cube measurement volume, 0.48 mm / 0.30 deg RMS
    (NDI Aurora specification). Zero-mean Gaussian, isotropic, independent per step.
    """

    position_mm: float = 0.48
    """3-D RMS position error, mm; in [0, 10]."""
    orientation_deg: float = 0.30
    """RMS orientation error (rotation angle), deg; in [0, 10]."""

    def __post_init__(self) -> None:
        for name in ('position_mm', 'orientation_deg'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value)
                    and 0.0 <= value <= 10.0):
                raise ValueError(f'{name} must be in [0, 10], found {value!r}')

    @property
    def enabled(self) -> bool:
        """Whether any noise is applied."""
        return self.position_mm > 0.0 or self.orientation_deg > 0.0

    def perceive(self, p: np.ndarray, r: np.ndarray, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray]:
        """A tracker reading of the true tip pose ``(p, R)`` (m, rotation matrix)."""
        if not self.enabled:
            return p.copy(), r.copy()
        # per-axis sigma = RMS / sqrt(3) gives the stated 3-D RMS
        dp = rng.normal(0.0, 1e-3 * self.position_mm / np.sqrt(3.0), 3)
        w = rng.normal(0.0, np.radians(self.orientation_deg) / np.sqrt(3.0), 3)
        return p + dp, rotvec_to_matrix(w) @ r


def evaluation_options(policies: dict[str, Any], requested: str | None = None) -> str:
    """The env option set an evaluation runs in: the one the policies' contracts name (a policy
    without a contract counts as ``ours``), else ``requested``, else ``ours``.

    Raises:
        LearningError: the policies name different option sets, or ``requested`` is not
            theirs (one line: each policy's set).
    """
    from cgail_sim.config import check_options

    found = {name: (p.contract.env_options if getattr(p, 'contract', None) is not None
                    else 'ours') for name, p in policies.items()}
    sets = sorted(set(found.values()))
    if len(sets) > 1:
        raise LearningError(f'policies: expected one env option set, found {found}: evaluate '
                            'them separately')
    if requested is not None and sets and requested != sets[0]:
        raise LearningError(f'--env-options {requested!r}: expected the policies\' option set, '
                            f'found {found}')
    return check_options(sets[0] if sets else (requested or 'ours'))


def observation_at(env: Any, p: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The environment's observation (its spec's layout) of env 0 as if its tip were at
    ``(p, R)``: the rays (or ``paper_code`` probes) sense the wall's current shape from that
    pose. With the true pose it equals the env's own observation (tested)."""
    from cgail_sim.ftl_model import observe_pose

    eng = env.unwrapped.engine
    return observe_pose(eng.spec, p, r, eng.target[0], eng.readings_at(0, p, r))


@dataclass
class Trial:
    """Outcome of one evaluation episode."""

    success: bool
    collision: bool
    timesteps: int
    targeting_error_mm: float
    plan_ms: float | None = None
    """Wall time of the method's plan for this trial, ms (None: a method that does not plan)."""
    fault: bool = False
    """The episode ended in a simulation fault (the env's ``info["simulation_fault"]``: the
    deformable wall blew up); neither a success nor a collision."""
    path: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    """The true tip positions, (T + 1, 3) m, from the reset to the last step (not in
    ``results.json``; :func:`render_failures` draws them)."""
    target: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    """The trial's target, (3,) m."""


class CenterlineFollower:
    """Baseline: pure pursuit of the target branch's centerline, then of the target (the
    carrot rule of :mod:`cgail_learning.pursuit`).

    Subclasses pursue another polyline by overriding :meth:`waypoints` (:class:`RrtFollower`).
    """

    def __init__(self, env: Any, lookahead: int = 6, approach: float = 0.035) -> None:
        self.env = env.unwrapped
        self.lookahead, self.approach = lookahead, approach
        self.progress = 0

    def reset(self, seed: int | None = None) -> None:
        """New episode."""
        self.progress = 0

    def waypoints(self) -> np.ndarray:
        """(W, 3) the polyline pursued: the episode's centerline waypoints."""
        return self.env.engine.waypoints[0]

    def act(self, pose: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Steer at the carrot (lookahead waypoints past the furthest reached one).

        Args:
            pose: the perceived tip pose ``(p, R)`` (a tracker reading); default the true one.
        """
        from cgail_learning.pursuit import carrot as pursuit_carrot
        from cgail_sim.ftl_model import steer_towards

        eng = self.env.engine
        if pose is None:
            p, R = eng.catheter.tip_position[0], eng.catheter.tip_rotation[0]
        else:
            p, R = pose
        carrot, self.progress, _ = pursuit_carrot(p, self.waypoints(), self.progress,
                                                  self.lookahead, eng.target[0], self.approach)
        return steer_towards(p, R, carrot, eng.config.catheter,
                             eng.catheter.theta_max).astype(np.float32)


class RrtFollower(CenterlineFollower):
    """The classical planner as a method: at every reset the curvature-constrained RRT
    (:mod:`cgail_planner.core.rrt_planner`, through :class:`~cgail_planner.core.planner.
    Planner`) plans from the episode's start pose to its target in the env's wall, and the
    centerline baseline's pure pursuit follows that path instead of the centerline (resampled at
    the centerline's waypoint spacing, so the lookahead is the same distance). Without a path
    within the search budget the catheter holds still until the episode is truncated (a
    failure). The budget is host-independent: by default the search is bounded by
    ``max_iterations`` (:class:`~cgail_planner.core.rrt_planner.RrtConfig`'s default) with a
    generous time limit of :data:`RRT_TIME_LIMIT_S`, so whether a trial's plan is found is a
    function of its seed and the settings, not of the machine or its load. ``plan_ms`` is the
    last plan's wall time (host-dependent, reported only). The default lookahead is 3
    waypoints (the centerline's 6): the planned path keeps only ``clearance_margin`` from the
    wall in the bends, and a far carrot cuts them (static, 15 pairs, seed 0, measured before
    the planner asked OMPL for 5% more radius: 6 waypoints 80% / 40%, 3 waypoints 87% / 93%
    success on default / elongated, the losses at 6 mostly collisions).

    Args:
        env: the environment (its world, wall and catheter model are the planner's).
        config: the RRT settings (default :class:`~cgail_planner.core.rrt_planner.RrtConfig`
            with ``time_limit_s`` :data:`RRT_TIME_LIMIT_S`); its seed is offset by each trial's
            seed.
    """

    def __init__(self, env: Any, config: Any = None, lookahead: int = 3,
                 approach: float = 0.035) -> None:
        from cgail_planner.core.planner import model_world_from_sim, PlannerConfig
        from cgail_planner.core.rrt_planner import RrtConfig

        super().__init__(env, lookahead, approach)
        eng = self.env.engine
        self.rrt_config = config if config is not None else \
            RrtConfig(time_limit_s=RRT_TIME_LIMIT_S)
        self._settings = PlannerConfig(planner_type='rrt', catheter=eng.config.catheter,
                                       rrt=self.rrt_config)
        self._model = model_world_from_sim(eng.world, exit_rule=eng.config.exit_rule)
        self.path: np.ndarray | None = None
        self.plan_ms: float | None = None
        self.error = ''

    def reset(self, seed: int | None = None) -> None:
        """New episode: plan from the start pose to the target."""
        from cgail_planner.core.errors import PlannerError
        from cgail_planner.core.path_fit import resample_by_arc_length
        from cgail_planner.core.planner import Planner

        super().reset(seed)
        eng = self.env.engine
        rrt = dataclasses.replace(self.rrt_config,
                                  seed=(self.rrt_config.seed + (seed or 0)) % 2**31)
        planner = Planner(dataclasses.replace(self._settings, rrt=rrt), self._model,
                          eng.walls[0], None)
        t0 = time.perf_counter()
        try:
            found = planner.plan(eng.catheter.tip_position[0], eng.catheter.tip_rotation[0],
                                 eng.target[0])
            wps = eng.waypoints[0]  # (the episode's, set by the env's reset)
            spacing = float(np.mean(np.linalg.norm(np.diff(wps, axis=0), axis=1)))
            self.path, self.error = resample_by_arc_length(found.path, spacing), ''
        except PlannerError as exc:
            self.path, self.error = None, str(exc)
        self.plan_ms = (time.perf_counter() - t0) * 1e3

    def waypoints(self) -> np.ndarray:
        """(W, 3) the planned path."""
        assert self.path is not None
        return self.path

    def act(self, pose: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Pure pursuit of the planned path; hold still without one."""
        if self.path is None:
            return np.zeros(3, dtype=np.float32)
        return super().act(pose)


def run_trials(env: Any, method: Any, trials: int, seed: int,
               reuse_pairs: bool = False, noise: TrackingNoise | None = None,
               tracked: bool = True, drawn: bool = False,
               on_trial: Callable[[int], object] | None = None) -> list[Trial]:
    """``trials`` episodes of a policy (obs -> action) or a state-based baseline (``act()``).

    Args:
        env: a :class:`~cgail_sim.env.CatheterNavEnv`.
        method: a policy callable or an object with ``act()`` (and optionally ``reset(seed)``).
        trials: number of episodes; trial k uses start ``k % n_starts``, target
            ``(k // n_starts) % n_targets`` and seed ``seed + k``.
        seed: base seed.
        reuse_pairs: simulate each start x target pair once and count its outcome for every
            trial that uses it. Only valid without noise, in static mode and for a
            deterministic method: the rigid-wall simulator and the method are then
            deterministic functions of the pair (the demo re-simulation check verifies this
            to 1 micrometre).
        noise: the tracker through which ``method`` perceives the tip (default: none).
        tracked: whether ``method`` sees the tip through ``noise`` (False for a method that
            uses the simulator's state, e.g. the scripted expert).
        drawn: trial k's target is drawn anew from its seed in the anatomy's 30 mm sphere (an
            env with ``EnvConfig.targets == "sphere"``) instead of one of the fixed set: every
            method meets the same target in trial k.
        on_trial: called with 1 as each trial ends (a progress bar's ``update``); it sees
            nothing of the trial, so it cannot change a result.
    """
    if drawn and env.unwrapped.config.targets != 'sphere':
        raise ValueError(f'drawn targets need an env that draws them (env options '
                         f'sphere_targets), found targets {env.unwrapped.config.targets!r}')
    if drawn and reuse_pairs:
        raise ValueError('reuse_pairs needs fixed targets (a drawn target differs per trial)')
    noise = noise if noise is not None else TrackingNoise(0.0, 0.0)
    noisy = tracked and noise.enabled
    if reuse_pairs and noisy:
        raise ValueError('reuse_pairs needs a noise-free evaluation (tracking noise makes '
                         'every trial different)')
    eng = env.unwrapped.engine
    sc = eng.scenarios
    n_s, n_t = len(sc.starts), len(sc.targets)
    out: list[Trial] = []
    done: dict[tuple[int, int], Trial] = {}
    for k in range(trials):
        pair = (k % n_s, (k // n_s) % n_t)
        if reuse_pairs and pair in done:
            out.append(done[pair])
            if on_trial is not None:
                on_trial(1)
            continue
        options = {'start': pair[0]} if drawn else {'start': pair[0], 'target': pair[1]}
        obs, _ = env.reset(seed=seed + k, options=options)
        rng = np.random.default_rng([seed, k, 7001])
        if hasattr(method, 'reset'):
            method.reset(seed + k)
        tips = [eng.catheter.tip_position[0].copy()]
        target = np.array(eng.target[0], dtype=float)
        while True:
            pose = None
            if noisy:
                pose = noise.perceive(eng.catheter.tip_position[0],
                                      eng.catheter.tip_rotation[0], rng)
            if hasattr(method, 'act'):
                a = method.act(pose) if pose is not None else method.act()
            else:
                a = method(observation_at(env, *pose) if pose is not None else obs)
            obs, _, te, tr, info = env.step(a)
            tips.append(eng.catheter.tip_position[0].copy())
            if te or tr:
                break
        fault = bool(info.get('simulation_fault', False))
        if fault:
            from cgail_sim.anatomy_spec import anatomy_label

            _LOG.warning('simulation fault in %s, trial %d (start %d, target %d, seed %d) at '
                         'step %d: %s', anatomy_label(env.unwrapped.config.anatomy), k,
                         pair[0], int(info['target']), seed + k, int(info['timesteps']),
                         info.get('simulation_fault_message', ''))
        out.append(Trial(bool(info['success']), bool(info['collision']), int(info['timesteps']),
                         1e3 * float(info['targeting_error']),
                         getattr(method, 'plan_ms', None), fault, np.asarray(tips), target))
        done[pair] = out[-1]
        if on_trial is not None:
            on_trial(1)
    return out


def summarize(trials: list[Trial]) -> dict[str, Any]:
    """Success rate, T_s and T_a (all and successful) of a method, and their 95 % confidence
    intervals (``*_ci``: ``(low, high)``): Wilson score intervals for the success and
    collision rates, percentile-bootstrap intervals of the medians
    (:mod:`cgail_planner.core.metrics`; seeded, so a function of the trials). The trials are
    taken as independent: true within one anatomy, where every trial draws its own tracker
    noise; across anatomies :func:`anatomy_interval` gives the honest one."""
    from cgail_planner.core.metrics import bootstrap_interval, wilson_interval

    succ = [t for t in trials if t.success]
    planned = [t.plan_ms for t in trials if t.plan_ms is not None]

    def med(xs: list[float]) -> float:
        return float(np.median(xs)) if xs else float('nan')

    return {
        'success_ci': wilson_interval(len(succ), len(trials)),
        'collision_ci': wilson_interval(sum(t.collision for t in trials), len(trials)),
        'T_s_succ_ci': bootstrap_interval([t.timesteps for t in succ]),
        'T_a_all_ci': bootstrap_interval([t.targeting_error_mm for t in trials]),
        'plan_ms_ci': bootstrap_interval(planned),
        'n': len(trials),
        'distinct': len({(t.success, t.collision, t.timesteps, round(t.targeting_error_mm, 6))
                         for t in trials}),
        'success_rate': float(np.mean([t.success for t in trials])),
        'collision_rate': float(np.mean([t.collision for t in trials])),
        'faults': sum(t.fault for t in trials),
        'T_s_all': med([t.timesteps for t in trials]),
        'T_s_succ': med([t.timesteps for t in succ]),
        'T_a_all_mm': med([t.targeting_error_mm for t in trials]),
        'T_a_succ_mm': med([t.targeting_error_mm for t in succ]),
        'plan_ms_median': med([t.plan_ms for t in trials if t.plan_ms is not None]),
        'plan_ms_max': max([t.plan_ms for t in trials if t.plan_ms is not None],
                           default=float('nan')),
    }


def kruskal(groups: dict[str, list[float]]) -> float:
    """Kruskal-Wallis p-value over the non-empty groups (nan with fewer than two)."""
    from scipy.stats import kruskal as kw

    vals = [np.asarray(v) for v in groups.values() if len(v) > 0]
    if len(vals) < 2 or all(np.all(v == vals[0][0]) for v in vals):
        return float('nan')
    return float(kw(*vals).pvalue)


def boxplot(results: dict[str, list[Trial]], metric: str, title: str, path: Path) -> None:
    """Box plot of one metric per method (paper Fig. 6/7 style)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    names = list(results)
    data = [[getattr(t, metric) for t in results[n]] for n in names]
    fig, ax = plt.subplots(figsize=(1.6 * len(names) + 2, 4))
    ax.boxplot(data, tick_labels=names)
    ax.set_title(title)
    ax.set_ylabel({'timesteps': 'T_s (steps)', 'targeting_error_mm': 'T_a (mm)'}[metric])
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def results_json(all_results: dict[str, dict[str, list[Trial]]],
                 meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """The machine-readable results: ``meta``, then per mode and method the
    :func:`summarize` figures (nan as None) and every trial's outcome."""
    def clean(v: Any) -> Any:
        if isinstance(v, tuple):
            return [clean(x) for x in v]
        return None if isinstance(v, float) and not np.isfinite(v) else v

    return {**(meta or {}), 'modes': {
        mode: {name: {'summary': {k: clean(v) for k, v in summarize(trials).items()},
                      'trials': [{f.name: getattr(t, f.name) for f in dataclasses.fields(t)
                                  if f.name not in ('path', 'target')} for t in trials]}
               for name, trials in results.items()}
        for mode, results in all_results.items()}}


def _interval(ci: tuple[float, float], fmt: str) -> str:
    """``[low-high]`` of a confidence interval (empty for an undefined one)."""
    lo, hi = ci
    return '' if not (np.isfinite(lo) and np.isfinite(hi)) else f'[{lo:{fmt}}-{hi:{fmt}}]'


def _with(value: float, ci: tuple[float, float], fmt: str) -> str:
    """A value and its interval, e.g. ``434 [394-474]``."""
    return f'{value:{fmt}} {_interval(ci, fmt)}'.strip()


def _pct(rate: float, ci: tuple[float, float]) -> str:
    """A rate and its interval in per cent, e.g. ``87% [80-92]``."""
    return f"{100 * rate:.0f}% {_interval((100 * ci[0], 100 * ci[1]), '.0f')}".strip()


def anatomy_interval(per_trial: dict[str, list[bool]]) -> tuple[float, float]:
    """95 % interval of a success rate pooled over anatomies (``anatomy -> successes``):
    a bootstrap over the anatomies (:func:`cgail_planner.core.metrics.cluster_bootstrap_rate`),
    since the trials of one anatomy share its geometry."""
    from cgail_planner.core.metrics import cluster_bootstrap_rate

    return cluster_bootstrap_rate(list(per_trial.values()))


def write_report(all_results: dict[str, dict[str, list[Trial]]], out: Path,
                 notes: str = '', meta: dict[str, Any] | None = None) -> Path:
    """Markdown report with one table per mode, KW p-values and the box plots, and
    ``results.json`` (:func:`results_json` with ``meta``) beside it."""
    out.mkdir(parents=True, exist_ok=True)
    (out / 'results.json').write_text(json.dumps(results_json(all_results, meta), indent=1)
                                      + '\n')
    lines = ['# In-silico evaluation', '', notes, '']
    for mode, results in all_results.items():
        lines += [f'## {mode}', '',
                  '| method | n | distinct | success [95% CI] | collision [95% CI] | '
                  'simulation faults | T_s all | T_s succ [95% CI] | T_a all (mm) [95% CI] | '
                  'T_a succ (mm) |',
                  '|---|---|---|---|---|---|---|---|---|---|']
        for name, trials in results.items():
            s = summarize(trials)
            lines.append(f"| {name} | {s['n']} | {s['distinct']} | "
                         f"{_pct(s['success_rate'], s['success_ci'])} | "
                         f"{_pct(s['collision_rate'], s['collision_ci'])} | {s['faults']} | "
                         f"{s['T_s_all']:.0f} | "
                         f"{_with(s['T_s_succ'], s['T_s_succ_ci'], '.0f')} | "
                         f"{_with(s['T_a_all_mm'], s['T_a_all_ci'], '.1f')} | "
                         f"{s['T_a_succ_mm']:.1f} |")
        p_ts = kruskal({n: [t.timesteps for t in tr if t.success] for n, tr in results.items()})
        p_ta = kruskal({n: [t.targeting_error_mm for t in tr] for n, tr in results.items()})
        planned = {n: summarize(tr) for n, tr in results.items()
                   if any(t.plan_ms is not None for t in tr)}
        if planned:
            lines.append('')
        lines += [f"- {n} planning time: median {s['plan_ms_median']:.0f} ms "
                  f"{_interval(s['plan_ms_ci'], '.0f')}, max {s['plan_ms_max']:.0f} ms per "
                  "trial" for n, s in planned.items()]
        lines += ['', '(medians; T_s/T_a "succ" over successful trials only; "distinct": '
                  'number of different outcomes among the trials; 95% CIs: Wilson for rates, '
                  'bootstrap for medians, trials taken as independent)', '',
                  f'Kruskal-Wallis across methods: T_s (successful) p = {p_ts:.3g}; '
                  f'T_a (all) p = {p_ta:.3g}.', '']
        first = next(iter(results))
        for other in list(results)[1:]:
            pa = kruskal({first: [t.targeting_error_mm for t in results[first]],
                          other: [t.targeting_error_mm for t in results[other]]})
            lines.append(f'- {first} vs {other}: T_a p = {pa:.3g}')
        for metric, label in (('timesteps', 'T_s'), ('targeting_error_mm', 'T_a')):
            png = f'{mode}_{label}.png'
            boxplot(results, metric, f'{label} ({mode})', out / png)
            lines += ['', f'![{label} {mode}]({png})']
        lines.append('')
    path = out / 'report.md'
    path.write_text('\n'.join(lines) + '\n')
    return path


#: Failing trials drawn in one failure picture (the first ones, in trial order).
FAILURES_SHOWN = 6


def render_failures(env: Any, results: dict[str, list[Trial]], mode: str, out: Path,
                    where: str = '') -> list[tuple[str, str]]:
    """One PNG per method that failed a trial in ``env``'s anatomy: the first
    :data:`FAILURES_SHOWN` failing trials' tip paths (each ending in a cross where the
    episode ended: the wall for a collision) and their targets, in two views
    (:func:`cgail_sim.render.render_anatomy`; the ostia are marked too). Returns ``(caption,
    file name)`` per picture, the file in ``out``."""
    from cgail_sim.render import render_anatomy

    anatomy = env.unwrapped.engine.world.anatomy
    made: list[tuple[str, str]] = []
    for name, trials in results.items():
        failed = [(k, t) for k, t in enumerate(trials) if not t.success and t.path is not None]
        if not failed:
            continue
        shown = failed[:FAILURES_SHOWN]
        outcome = {True: 'collision', False: 'time-out'}
        rollouts = [(f'trial {k}: ' + ('simulation fault' if t.fault else outcome[t.collision])
                     + f', {t.targeting_error_mm:.0f} mm from its target (star)', t.path,
                     t.target) for k, t in shown if t.path is not None]
        safe = ''.join(ch if ch.isalnum() or ch in '._-' else '_' for ch in name)
        png = f'failures_{mode}_{anatomy.name}_{safe}.png'
        render_anatomy(anatomy, out / png, rollouts=rollouts, scenarios=False,
                       views=('anterior', 'left-lateral'),
                       title=f'{name}, {mode}{where}: {len(shown)} of {len(failed)} failed '
                             f'trials of {len(trials)}')
        made.append((f'{name}, {mode}, {anatomy.name}: {len(failed)} of {len(trials)} trials '
                     f'failed ({len(shown)} shown)', png))
    return made


def _append_failures(report: Path, pictures: dict[str, list[tuple[str, str]]]) -> None:
    """The failure pictures of each mode (:func:`render_failures`) at the end of the report."""
    if not any(pictures.values()):
        return
    lines = ['## Failures', '',
             'Where the failing trials went: the tip path of each (true positions), a cross '
             'where its episode ended and a star on its target, in the colour of its path.',
             '']
    for shown in pictures.values():
        for caption, png in shown:
            lines += [f'- {caption}', '', f'  ![{caption}]({png})', '']
    with report.open('a') as f:
        f.write('\n'.join(lines) + '\n')


def _held_out(count: int) -> list[Any]:
    """The first ``count`` held-out population anatomies (none for 0)."""
    if count == 0:
        return []
    if count < 0:
        raise ValueError(f'--population must be >= 0 (held-out anatomies), found {count}')
    from cgail_sim.population import sample_anatomy, split_seeds

    return [sample_anatomy(s) for s in split_seeds('held_out', count)]


def _run_methods(env: Any, policies: dict[str, Any], args: argparse.Namespace,
                 noise: TrackingNoise, mode: str, where: str = '') -> dict[str, list[Trial]]:
    """The trials of every method (the policies and the requested baselines) in ``env``."""
    from cgail_learning.expert import ScriptedExpert

    methods: dict[str, Any] = dict(policies)
    if 'centerline' in args.baselines:
        methods['centerline'] = CenterlineFollower(env)
    if 'rrt' in args.baselines:
        methods['rrt'] = RrtFollower(env)
    if 'expert' in args.baselines:
        methods['expert'] = ScriptedExpert(env)
    results = {}
    for name, method in methods.items():
        t0 = time.monotonic()
        tracked = name != 'expert'  # the demonstrator uses the simulator's state
        # noise-free static: a deterministic method's outcome is a function of the pair
        reuse = mode == 'static' and tracked and not noise.enabled and not args.drawn_targets
        # a bar with the time left (stderr), shown once a method has run for a second
        with tqdm(total=args.trials, desc=f'{mode}{where} {name}', unit='trial', leave=False,
                  delay=1.0, disable=getattr(args, 'no_progress', False)) as bar:
            results[name] = run_trials(env, method, args.trials, args.seed, reuse, noise,
                                       tracked, args.drawn_targets, on_trial=bar.update)
        s = summarize(results[name])
        print(f"{mode}{where} {name}: success {100 * s['success_rate']:.0f}% "
              f"({time.monotonic() - t0:.0f} s)", flush=True)
    return results


def per_anatomy_plot(methods: dict[str, dict[str, list[bool]]], title: str, path: Path) -> None:
    """Grouped bars: each method's success rate in each anatomy (where each one fails)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    names = list(methods)
    anatomies = list(next(iter(methods.values())))
    x = np.arange(len(anatomies))
    width = 0.8 / len(names)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.55 * len(anatomies) * max(1, len(names) / 2)), 3.8))
    for k, n in enumerate(names):
        ax.bar(x + (k - (len(names) - 1) / 2) * width,
               [100 * np.mean(methods[n][a]) for a in anatomies], width, label=n)
    ax.set_xticks(x, [a.replace('population-', 'p') for a in anatomies], rotation=60,
                  fontsize=8)
    ax.set_ylabel('success (%)')
    ax.set_ylim(0, 105)
    ax.set_title(title)
    ax.legend(fontsize=8, loc='upper left', bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _append_per_anatomy(report: Path, outcomes: dict[str, dict[str, dict[str, list[bool]]]]
                        ) -> None:
    """Add a per-anatomy success table (anatomies x methods) per mode to ``report``, with the
    pooled rate and its 95 % interval over anatomies (:func:`anatomy_interval`)."""
    lines = ['## Success per anatomy', '']
    for mode, methods in outcomes.items():
        names = list(methods)
        anatomies = list(next(iter(methods.values())))
        lines += [f'### {mode}', '', '| anatomy | ' + ' | '.join(names) + ' |',
                  '|---|' + '---|' * len(names)]
        lines += [f'| {a} | ' + ' | '.join(f'{100 * np.mean(methods[n][a]):.0f}%' for n in names)
                  + ' |' for a in anatomies]
        pooled = {n: float(np.mean([x for a in anatomies for x in methods[n][a]]))
                  for n in names}
        lines.append('| **all** [95% CI over anatomies] | ' + ' | '.join(
            _pct(pooled[n], anatomy_interval(methods[n])) for n in names) + ' |')
        lines.append('| anatomies at 100% | ' + ' | '.join(
            f'{sum(bool(np.all(methods[n][a])) for a in anatomies)} of {len(anatomies)}'
            for n in names) + ' |')
        png = f'per_anatomy_{mode}.png'
        per_anatomy_plot(methods, f'success per anatomy ({mode})', report.parent / png)
        lines += ['', f'![success per anatomy, {mode}]({png})', '']
    lines += ['(The interval over anatomies resamples whole anatomies, whose trials share '
              'their geometry; with few anatomies it understates the uncertainty: read the '
              'per-trial Wilson interval above beside it.)', '']
    with report.open('a') as f:
        f.write('\n'.join(lines) + '\n')


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``cgail evaluate``."""
    p = tool_parser('evaluate', __doc__)
    p.add_argument('--policy', action='append', default=[], metavar='NAME=PATH.onnx',
                   help='a learned policy to evaluate, shown as NAME in the report (repeatable)')
    p.add_argument('--baselines', nargs='*', default=['centerline', 'expert'],
                   choices=('centerline', 'expert', 'rrt'),
                   help='the non-learned methods beside the policies: centerline (pure pursuit '
                        'of the centerline), expert (the scripted demonstrator, with the '
                        "simulator's state) and rrt (the curvature-constrained RRT of "
                        'core/rrt_planner.py, planned at each reset within its iteration '
                        'budget and a 30 s limit, then followed by the centerline pure pursuit)')
    p.add_argument('--modes', nargs='+', default=['static'], choices=('static', 'dynamic'),
                   help='rigid aorta (static) and/or deformable beating wall (dynamic)')
    p.add_argument('--anatomy', nargs='+', default=['default'], metavar='ANATOMY',
                   help='built-in anatomy name (default, elongated), shipped real aorta '
                        '(avt-D4, ...), population-<seed>, prepared anatomy directory or mesh '
                        'file with its <stem>.yaml landmarks; several: --trials in each, the '
                        'results pooled, with a per-anatomy table (as --population)')
    p.add_argument('--trials', type=int, default=100,
                   help='trials per method and mode (per anatomy with --population or several '
                        '--anatomy); trial k: '
                        'start k %% 3, target (k // 3) %% 5')
    p.add_argument('--seed', type=int, default=1000,
                   help='seed of trial 0; trial k uses seed + k, the same for every method')
    p.add_argument('--scenario-seed', type=int, default=0,
                   help="the anatomy's target set (EnvConfig.scenario_seed): 0 is the set the "
                        'demonstrations and presets train on; another gives unseen targets')
    p.add_argument('--drawn-targets', action='store_true',
                   help="trial k's target drawn anew from its seed in the anatomy's 30 mm "
                        'sphere, the same for every method, instead of the target set\'s five '
                        '(needs the env options sphere_targets, a generalist\'s)')
    p.add_argument('--position-noise-mm', type=float, default=TrackingNoise.position_mm,
                   help='RMS position error of the simulated EM tracker, mm (0: none)')
    p.add_argument('--orientation-noise-deg', type=float, default=TrackingNoise.orientation_deg,
                   help='RMS orientation error of the simulated EM tracker, deg (0: none)')
    p.add_argument('--env-options', default=None,
                   help="the simulator's option set (ours, paper_code); default: the one the "
                        "policies were trained in (their contracts'), else ours")
    p.add_argument('--population', type=int, default=0, metavar='N',
                   help='evaluate on the first N held-out population anatomies (seeds 10000 on, '
                        'which no training uses; cgail_sim/population.py) instead of --anatomy: '
                        '--trials per anatomy, the results pooled, with a per-anatomy table')
    p.add_argument('--failure-pictures', action=argparse.BooleanOptionalAction, default=True,
                   help='draw where the failing trials went: one PNG per method and anatomy '
                        f'with the tip paths of its first {FAILURES_SHOWN} failures, linked at '
                        'the end of the report')
    p.add_argument('--out', type=Path, default=Path('runs/evaluate'),
                   help='directory for report.md, results.json and the box plots')
    p.add_argument('--no-progress', action='store_true',
                   help='hide the progress bar (each method\'s trials, with the time left)')
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cgail evaluate``."""
    args = build_parser().parse_args(argv)
    from cgail_sim.anatomy_spec import anatomy_identity, check_anatomy_spec
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv
    from cgail_sim.ftl_model import describe_anatomy

    try:
        for spec in args.anatomy:
            check_anatomy_spec(spec)  # (before the policies are loaded)
        held_out = _held_out(args.population)
        # several anatomies: pooled as the held-out population is
        pooled: list[Any] = held_out or (list(args.anatomy) if len(args.anatomy) > 1 else [])
        noise = TrackingNoise(args.position_noise_mm, args.orientation_noise_deg)
        policies: dict[str, Any] = {}
        paths: dict[str, str] = {}
        for spec in args.policy:
            name, sep, path = spec.partition('=')
            if not sep:
                raise LearningError(f'--policy expects NAME=PATH.onnx, found {spec!r}')
            policies[name] = OnnxPolicy(path)
            paths[name] = path
        options = evaluation_options(policies, args.env_options)
        all_results: dict[str, dict[str, list[Trial]]] = {}
        outcomes: dict[str, dict[str, dict[str, list[bool]]]] = {}
        pictures: dict[str, list[tuple[str, str]]] = {}
        for mode in args.modes:
            results: dict[str, list[Trial]] = {}
            for anatomy in pooled or args.anatomy:
                env = CatheterNavEnv(EnvConfig.from_options(options, mode=mode,
                                                            anatomy=anatomy,
                                                            scenario_seed=args.scenario_seed))
                where = f' {env.anatomy.name}' if pooled else ''
                by_method = _run_methods(env, policies, args, noise, mode, where)
                for name, trials in by_method.items():
                    results.setdefault(name, []).extend(trials)
                    outcomes.setdefault(mode, {}).setdefault(name, {})[
                        env.anatomy.name] = [t.success for t in trials]
                if args.failure_pictures:
                    args.out.mkdir(parents=True, exist_ok=True)
                    pictures.setdefault(mode, []).extend(
                        render_failures(env, by_method, mode, args.out, where))
            all_results[mode] = results
        if held_out:
            named = (f'{len(held_out)} held-out population anatomies '
                     f'({held_out[0].name} to {held_out[-1].name}, never trained on)')
            label = f'population-held-out-{len(held_out)}'
        elif pooled:
            names = [anatomy_identity(spec)[0] for spec in pooled]
            named = f'{len(pooled)} anatomies ({", ".join(names)})'
            label = f'anatomies-{len(pooled)}'
        else:
            label, content_hash = anatomy_identity(args.anatomy[0])
            named = f'`{label}`' if not content_hash else describe_anatomy(label, content_hash)
            named = f'Anatomy {named}'
        per = ' per anatomy' if pooled else ''
        if args.drawn_targets:
            target = "a target drawn anew from seed + k in the anatomy's 30 mm sphere. "
        else:
            target = '(k // 3) % 5' + (f' of target set (scenario seed) {args.scenario_seed}. '
                                       if args.scenario_seed else '. ')
        notes = (f'{named}, {args.trials} trials per method{per}, epsilon 10 mm, '
                 f'seed {args.seed}, env options `{options}`. Trial k: start k % 3, target '
                 f'{target}')
        if noise.enabled:
            notes += (f'The methods perceive the tip through a simulated EM tracker '
                      f'({noise.position_mm:g} mm / {noise.orientation_deg:g} deg RMS, drawn per '
                      'step from the trial seed), so every trial is an independent sample; the '
                      'scripted expert uses the simulator state and its own seed.')
        elif args.drawn_targets:
            notes += 'No tracking noise; every trial has a target of its own.'
        else:
            notes += ('No tracking noise: in static mode a deterministic method gives the same '
                      'outcome for a repeated start x target pair, so each pair is simulated '
                      'once and counted for each of its trials (the p-values then overstate '
                      'the evidence); the seeded expert runs every trial.')
        meta = {'anatomy': label, 'trials': args.trials, 'seed': args.seed,
                'scenario_seed': args.scenario_seed, 'drawn_targets': args.drawn_targets,
                'env_options': options,
                'position_noise_mm': noise.position_mm,
                'orientation_noise_deg': noise.orientation_deg,
                'policies': paths}
        if held_out:
            meta['population_seeds'] = [a.name for a in held_out]
        elif pooled:
            meta['anatomies'] = names
        if pooled:
            meta['per_anatomy_success'] = {
                mode: {n: {a: float(np.mean(ok)) for a, ok in by.items()}
                       for n, by in methods.items()}
                for mode, methods in outcomes.items()}
            meta['success_ci_over_anatomies'] = {
                mode: {n: list(anatomy_interval(by)) for n, by in methods.items()}
                for mode, methods in outcomes.items()}
        path = write_report(all_results, args.out, notes, meta)
        if pooled:
            _append_per_anatomy(path, outcomes)
        _append_failures(path, pictures)
    except (LearningError, ValueError) as exc:
        print(f'cgail evaluate: error: {exc}', file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == '__main__':
    sys.exit(main())

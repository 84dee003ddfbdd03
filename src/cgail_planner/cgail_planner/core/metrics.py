"""Offline in-vitro metrics of one trial and across conditions (paper section IV-C).

Pure numpy/scipy (no rclpy). A trial is given as time-stamped arrays (SI units, see
:class:`TrialData`); :mod:`cgail_bags.reader` builds them from a bag.

Definitions (documented choices where the paper leaves room):

* **Trial window.** The trial starts at ``t_0``, the first tip pose at or after the first goal
  (target) message, and lasts at most ``time_limit`` (3 minutes, the paper's protocol). Samples
  after ``t_0 + time_limit`` are ignored: the paper stops the experiment there.
* **Duration** ``T = t_g - t_0`` with ``t_g`` the last tip pose in the window (the operator ends
  the recording when done; a trial cut by the time limit has ``T <= time_limit``).
* **Tracking error** ``T_r(t) = ||p^d_t - p_t||``. The path in effect at ``t`` (the latest
  ``planner/path`` received at or before ``t``, so replanning is honoured) is B-spline fitted and
  resampled (:func:`~cgail_planner.core.path_fit.fit_path`); ``p^d_t`` is the closest point of
  that resampled path to ``p_t``. Paths stamped before the trial's first goal belong to an
  earlier trial (the planner's transient-local path of the previous run, delivered again when
  the recorder subscribes) and are left out, as are the samples before the first path of this
  trial. Reported: mean, std (population) and max over the samples.
* **Targeting error** ``T_a = min_t ||q_g(t) - p_t||`` over the window, with ``q_g(t)`` the latest
  goal at ``t`` (the target may move).
* **Success**: ``||q_g(t) - p_t|| <= success_radius`` (epsilon, 10 mm by default as in the
  simulator) at some sample within the 3-minute window. ``time_to_target`` is the first such
  time after ``t_0``.
* **Curvature** of the tip's path: the window's positions are first smoothed in time by a
  Savitzky-Golay filter (a cubic fitted over a window of ``curvature_smoothing``, 2 s, in
  samples that over the median sample interval, rounded to odd; cubic fits at the ends,
  ``scipy.signal.savgol_filter(mode='interp')``), then resampled at a uniform arc length
  (``curvature_spacing``, 3 mm), and the Menger curvature of each consecutive triple is taken;
  mean and std in mm^-1 as the paper reports (internally 1/m). Without the smoothing it would
  measure the tracker's noise, not the path: on the raw 40-Hz EM positions (0.5 mm RMS noise)
  at 1 mm spacing a simulated trial read 2.6 mm^-1 (a radius of 0.38 mm), against 0.017-0.022
  mm^-1 for its planned path; smoothed, 0.022-0.025. A local cubic keeps a noise-free arc's
  curvature (a 20 mm circle reads 50.0 m^-1), where a Gaussian would shrink it and flatten
  its ends. A stationary tip contributes nothing.
* **Across conditions**: the Kruskal-Wallis H test (``scipy.stats.kruskal``) per metric between
  the conditions' per-trial values; significant when ``p < 0.05``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cgail_planner.core.path_fit import (
    closest_points,
    discrete_curvature,
    fit_path,
    PathFitConfig,
    PathFitError,
    polyline_length,
    resample_by_arc_length,
)

FloatArray = NDArray[np.float64]

#: Significance level of the Kruskal-Wallis test (paper: 0.05).
ALPHA = 0.05


class MetricsError(ValueError):
    """A trial cannot be evaluated (no tip poses, no goal, no path in the window...)."""


@dataclass(frozen=True)
class MetricsConfig:
    """Settings of the offline metrics."""

    time_limit: float = 180.0
    """Maximum operation time (s) after which a trial is stopped and counted as failed unless
    the target was reached; > 0 (paper: 3 minutes)."""

    success_radius: float = 0.010
    """epsilon (m): the target counts as reached when the tip is within it; > 0."""

    path_fit: PathFitConfig = field(default_factory=PathFitConfig)
    """B-spline fit and resampling of the planned path (desired path of T_r)."""

    curvature_spacing: float = 3e-3
    """Arc-length step (m) of the smoothed trajectory's resampling before the curvature; > 0."""

    curvature_smoothing: float = 2.0
    """Window (s) of the Savitzky-Golay cubic that smooths the tip positions in time before
    the curvature (module docstring); >= 0, 0: none (the curvature of the tracker's noise)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.time_limit) and self.time_limit > 0.0):
            raise ValueError(f'time_limit must be a positive number of seconds, '
                             f'found {self.time_limit}')
        if not (math.isfinite(self.success_radius) and self.success_radius > 0.0):
            raise ValueError(f'success_radius must be a positive number of metres, '
                             f'found {self.success_radius}')
        if not (math.isfinite(self.curvature_spacing) and self.curvature_spacing > 0.0):
            raise ValueError(f'curvature_spacing must be a positive number of metres, '
                             f'found {self.curvature_spacing}')
        if not (math.isfinite(self.curvature_smoothing) and self.curvature_smoothing >= 0.0):
            raise ValueError(f'curvature_smoothing must be a non-negative number of seconds, '
                             f'found {self.curvature_smoothing}')


@dataclass(frozen=True)
class TrialData:
    """Time-stamped data of one trial (times in s, positions in m, any common time origin)."""

    name: str
    """Trial name (the bag's name)."""
    condition: str
    """Condition label, e.g. ``cgail`` or ``centerline``."""
    tip_t: FloatArray
    """``(K,)`` tip pose times, non-decreasing."""
    tip_p: FloatArray
    """``(K, 3)`` tip positions (EM tracker)."""
    goal_t: FloatArray
    """``(G,)`` goal (target) message times, non-decreasing."""
    goal_p: FloatArray
    """``(G, 3)`` goal positions."""
    path_t: FloatArray
    """``(P,)`` planned-path message times, non-decreasing."""
    paths: tuple[FloatArray, ...]
    """``P`` planned paths, each ``(N_i, 3)`` waypoints."""


@dataclass(frozen=True)
class TrialMetrics:
    """Metrics of one trial (SI units: m, s, 1/m)."""

    name: str
    condition: str
    samples: int
    """Tip poses in the trial window."""
    tracking_mean: float
    tracking_std: float
    tracking_max: float
    targeting_error: float
    duration: float
    success: bool
    time_to_target: float
    """Seconds from t_0 to the first sample within epsilon; NaN if never reached."""
    timed_out: bool
    """The recording went on past the time limit (the window was cut)."""
    curvature_mean: float
    curvature_std: float
    path_length: float
    """Length (m) of the last desired path used."""


@dataclass(frozen=True)
class KruskalResult:
    """Kruskal-Wallis test of one metric across conditions."""

    metric: str
    statistic: float
    pvalue: float
    """NaN when the test is undefined (fewer than 2 conditions, or all values equal)."""

    @property
    def significant(self) -> bool:
        """True when p < 0.05 (paper's level)."""
        return bool(self.pvalue < ALPHA)


def _check_times(name: str, t: FloatArray, p: FloatArray) -> None:
    if t.ndim != 1 or p.ndim != 2 or p.shape != (len(t), 3):
        raise MetricsError(f'{name}: expected times (K,) and positions (K, 3), '
                           f'found {t.shape} and {p.shape}')
    if len(t) > 1 and np.any(np.diff(t) < 0.0):
        raise MetricsError(f'{name}: times must be non-decreasing')


def smoothed_positions(t: FloatArray, p: FloatArray, window_s: float) -> FloatArray:
    """Positions ``p`` (N, 3) at times ``t`` (N,) smoothed in time by a Savitzky-Golay cubic over
    ``window_s`` seconds (module docstring, Curvature). ``window_s == 0``, no time step, or
    fewer samples than a cubic window of 5: ``p`` as it is."""
    if window_s <= 0.0 or len(p) < 5:
        return p
    dt = float(np.median(np.diff(t)))
    if not dt > 0.0:
        return p
    from scipy.signal import savgol_filter

    window = max(5, round(window_s / dt) | 1)
    window = min(window, len(p) if len(p) % 2 else len(p) - 1)
    return np.asarray(savgol_filter(p, window, 3, axis=0, mode='interp'), dtype=np.float64)


def compute_trial_metrics(trial: TrialData, config: MetricsConfig | None = None) -> TrialMetrics:
    """Compute the metrics of one trial (see the module docstring for the definitions).

    Raises:
        MetricsError: No tip pose, no goal, no path, or no tip pose after the first goal/path.
    """
    cfg = config or MetricsConfig()
    tip_t = np.asarray(trial.tip_t, dtype=np.float64)
    tip_p = np.asarray(trial.tip_p, dtype=np.float64)
    goal_t = np.asarray(trial.goal_t, dtype=np.float64)
    goal_p = np.asarray(trial.goal_p, dtype=np.float64)
    _check_times('tip poses', tip_t, tip_p)
    _check_times('goals', goal_t, goal_p)
    where = f'trial {trial.name!r}'
    if len(tip_t) == 0:
        raise MetricsError(f'{where}: expected tip poses, found none')
    if len(goal_t) == 0:
        raise MetricsError(f'{where}: expected at least one goal (target), found none')
    if len(trial.paths) == 0 or len(trial.paths) != len(trial.path_t):
        raise MetricsError(f'{where}: expected at least one planned path with a time, found '
                           f'{len(trial.paths)} paths and {len(trial.path_t)} times')
    # NaN poses (tracker dropouts) carry no position: leave them out.
    finite = np.all(np.isfinite(tip_p), axis=1) & np.isfinite(tip_t)
    tip_t, tip_p = tip_t[finite], tip_p[finite]
    finite = np.all(np.isfinite(goal_p), axis=1) & np.isfinite(goal_t)
    goal_t, goal_p = goal_t[finite], goal_p[finite]
    if len(tip_t) == 0:
        raise MetricsError(f'{where}: expected finite tip poses, found only NaN')
    if len(goal_t) == 0:
        raise MetricsError(f'{where}: expected a finite goal, found only NaN')

    start = np.searchsorted(tip_t, goal_t[0], side='left')
    if start >= len(tip_t):
        raise MetricsError(f'{where}: expected tip poses after the first goal, found none')
    t0 = float(tip_t[start])
    end = np.searchsorted(tip_t, t0 + cfg.time_limit, side='right')
    timed_out = bool(end < len(tip_t))
    t = tip_t[start:end]
    p = tip_p[start:end]

    gi = np.searchsorted(goal_t, t, side='right') - 1
    to_goal = np.linalg.norm(goal_p[gi] - p, axis=1)
    reached = np.flatnonzero(to_goal <= cfg.success_radius)
    success = bool(len(reached) > 0)
    time_to_target = float(t[reached[0]] - t0) if success else math.nan

    path_t = np.asarray(trial.path_t, dtype=np.float64)
    pi = np.searchsorted(path_t, t, side='right') - 1
    stale = path_t < goal_t[0]  # planned before this trial's goal: an earlier trial's path
    pi[(pi >= 0) & stale[pi]] = -1
    errors = np.full(len(t), np.nan)
    length = math.nan
    for k in np.unique(pi[pi >= 0]):
        sel = pi == k
        try:
            desired = fit_path(trial.paths[int(k)], cfg.path_fit)
        except PathFitError as exc:
            raise MetricsError(f'{where}: planned path #{k} (t = {path_t[k]:.3f} s) cannot be '
                               f'used as the desired path: {exc}') from None
        errors[sel], _ = closest_points(p[sel], desired)
        length = polyline_length(desired)
    tracked = errors[np.isfinite(errors)]
    if len(tracked) == 0:
        raise MetricsError(f'{where}: expected tip poses after the first planned path '
                           f'stamped at or after the first goal, found none')

    curv = np.zeros(0)
    smooth = smoothed_positions(t, p, cfg.curvature_smoothing)
    if polyline_length(smooth) >= 2.0 * cfg.curvature_spacing:
        curv = discrete_curvature(resample_by_arc_length(smooth, cfg.curvature_spacing))
    return TrialMetrics(
        name=trial.name,
        condition=trial.condition,
        samples=len(t),
        tracking_mean=float(np.mean(tracked)),
        tracking_std=float(np.std(tracked)),
        tracking_max=float(np.max(tracked)),
        targeting_error=float(np.min(to_goal)),
        duration=float(t[-1] - t0),
        success=success,
        time_to_target=time_to_target,
        timed_out=timed_out,
        curvature_mean=float(np.mean(curv)) if len(curv) else math.nan,
        curvature_std=float(np.std(curv)) if len(curv) else math.nan,
        path_length=length,
    )


#: Metrics compared across conditions: attribute name -> (label, unit, scale from SI).
COMPARED_METRICS: Mapping[str, tuple[str, str, float]] = {
    'tracking_mean': ('tracking error T_r', 'mm', 1e3),
    'targeting_error': ('targeting error T_a', 'mm', 1e3),
    'duration': ('duration T', 's', 1.0),
    'curvature_mean': ('curvature', 'mm^-1', 1e-3),
}


def group_by_condition(trials: Sequence[TrialMetrics]) -> dict[str, list[TrialMetrics]]:
    """Trials grouped by condition, conditions in first-seen order."""
    groups: dict[str, list[TrialMetrics]] = {}
    for trial in trials:
        groups.setdefault(trial.condition, []).append(trial)
    return groups


def kruskal_by_condition(
    trials: Sequence[TrialMetrics], metrics: Sequence[str] = tuple(COMPARED_METRICS)
) -> list[KruskalResult]:
    """Kruskal-Wallis H test of each metric between the conditions' per-trial values.

    Returns NaN statistic/p-value for a metric when fewer than two conditions have finite
    values or when all values are identical (the test is undefined there).
    """
    groups = group_by_condition(trials)
    results = []
    for metric in metrics:
        samples = []
        for members in groups.values():
            values = np.array([getattr(m, metric) for m in members], dtype=np.float64)
            values = values[np.isfinite(values)]
            if len(values):
                samples.append(values)
        stat, pvalue = math.nan, math.nan
        pooled = np.concatenate(samples) if samples else np.zeros(0)
        if len(samples) >= 2 and np.ptp(pooled) > 0.0:
            from scipy.stats import kruskal  # slow import (~1 s): only when comparing

            res = kruskal(*samples)
            stat, pvalue = float(res.statistic), float(res.pvalue)
        results.append(KruskalResult(metric, stat, pvalue))
    return results


# ----------------------------------------------------------------------------------------------
# 95 % confidence intervals (the evaluation's tables)

def wilson_interval(successes: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a proportion ``successes / n`` (95 % by default): unlike the
    normal approximation it stays inside [0, 1] and is not empty at 0 or n successes
    (Wilson 1927; Brown, Cai & DasGupta 2001 recommend it for small n). It is
    ``scipy.stats.binomtest(successes, n).proportion_ci(level, 'wilson')``, which agrees with the
    closed form to 4e-16 over every ``successes <= n <= 300``. ``(nan, nan)`` for ``n == 0``."""
    if n < 0 or not 0 <= successes <= n:
        raise MetricsError(f"wilson_interval: expected 0 <= successes <= n, found {successes} "
                           f"of {n}")
    if n == 0:
        return math.nan, math.nan
    from scipy.stats import binomtest  # slow import (~1 s): only when a table needs it

    ci = binomtest(successes, n).proportion_ci(confidence_level=level, method="wilson")
    return float(ci.low), float(ci.high)


def _percentile_bootstrap(data: tuple[NDArray[np.float64], ...], statistic: Callable[..., Any],
                          resamples: int, seed: int, level: float) -> tuple[float, float]:
    """``scipy.stats.bootstrap``'s percentile interval, its draws seeded ``seed``: the rows
    of ``default_rng(seed).integers(0, n, (resamples, n))`` index the (paired) samples."""
    from scipy.stats import bootstrap  # slow import (~1 s): only when a table needs it

    res = bootstrap(data, statistic, n_resamples=resamples, method="percentile",
                    confidence_level=level, paired=len(data) > 1, vectorized=True,
                    rng=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def bootstrap_interval(values: Sequence[float], statistic: str = "median",
                       resamples: int = 2000, seed: int = 0,
                       level: float = 0.95) -> tuple[float, float]:
    """Percentile-bootstrap interval of a sample's median or mean
    (``scipy.stats.bootstrap(method='percentile')``): ``resamples`` draws with replacement from
    a generator seeded ``seed`` (so the interval is a function of the values), the
    ``(1 - level) / 2`` and ``(1 + level) / 2`` quantiles of the statistic. ``(nan, nan)`` for
    an empty sample; a single value is its own interval (scipy asks for two or more)."""
    if statistic not in ("median", "mean"):
        raise MetricsError(f"bootstrap_interval: expected statistic 'median' or 'mean', found "
                           f"{statistic!r}")
    x = np.asarray(values, dtype=np.float64)
    if x.size == 0:
        return math.nan, math.nan
    if x.size == 1:
        return float(x[0]), float(x[0])
    return _percentile_bootstrap((x,), np.median if statistic == "median" else np.mean,
                                 resamples, seed, level)


def cliffs_delta(a: Sequence[float], b: Sequence[float]) -> float:
    """Cliff's delta of two samples, ``P(a > b) - P(a < b)`` over all pairs (finite values
    only): the effect size that goes with a rank test such as Kruskal-Wallis (Cliff 1993), in
    [-1, 1], independent of the scale and of outliers. NaN when a sample is empty."""
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    x, y = x[np.isfinite(x)], y[np.isfinite(y)]
    if x.size == 0 or y.size == 0:
        return math.nan
    diff = x[:, None] - y[None, :]
    return float((np.count_nonzero(diff > 0) - np.count_nonzero(diff < 0)) / diff.size)


def cliffs_magnitude(delta: float) -> str:
    """Romano et al. (2006)'s labels of ``|delta|``: negligible < 0.147 <= small < 0.33 <=
    medium < 0.474 <= large."""
    if not math.isfinite(delta):
        return "n/a"
    d = abs(delta)
    return ("negligible" if d < 0.147 else "small" if d < 0.33
            else "medium" if d < 0.474 else "large")


def cluster_bootstrap_rate(groups: Sequence[Sequence[bool]], resamples: int = 2000,
                           seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    """Interval of a pooled success rate whose trials come in clusters (the trials of one
    anatomy are not independent: they share its geometry): resample whole clusters with
    replacement, pool their trials, take the quantiles of the pooled rate
    (``scipy.stats.bootstrap(method='percentile', paired=True)`` over the clusters' hits and
    sizes, seeded ``seed``). ``(nan, nan)`` without trials; one cluster is its own rate."""
    sizes = np.array([len(g) for g in groups], dtype=np.float64)
    if sizes.sum() == 0:
        return math.nan, math.nan
    hits = np.array([int(np.sum(g)) for g in groups], dtype=np.float64)
    if len(groups) == 1:
        return float(hits[0] / sizes[0]), float(hits[0] / sizes[0])

    def pooled_rate(h: NDArray[np.float64], s: NDArray[np.float64],
                    axis: int = -1) -> NDArray[np.float64]:
        return np.asarray(h.sum(axis=axis) / np.maximum(s.sum(axis=axis), 1))

    # (paired: each draw takes a cluster's hits and size together)
    return _percentile_bootstrap((hits, sizes), pooled_rate, resamples, seed, level)

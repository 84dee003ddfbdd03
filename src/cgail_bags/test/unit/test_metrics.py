"""Offline trial metrics (T_r, T_a, T, success, curvature) and Kruskal-Wallis, exact values."""

import math
from pathlib import Path

import numpy as np
import pytest

from cgail_bags.report import box_plots, markdown_report, write_csv
from cgail_planner.core.metrics import (
    compute_trial_metrics,
    kruskal_by_condition,
    MetricsConfig,
    MetricsError,
    TrialData,
)

LINE = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.1, 0.0, 0.0]])
GOAL = np.array([[0.1, 0.0, 0.0]])


def trial(tip_t, tip_p, goal_t=(0.0,), goal_p=GOAL, path_t=(0.0,), paths=(LINE,),
          name='t', condition='c') -> TrialData:
    return TrialData(name=name, condition=condition,
                     tip_t=np.asarray(tip_t, float), tip_p=np.asarray(tip_p, float),
                     goal_t=np.asarray(goal_t, float), goal_p=np.asarray(goal_p, float),
                     path_t=np.asarray(path_t, float), paths=tuple(paths))


def along_x(x, y=0.0, z=0.0) -> np.ndarray:
    x = np.asarray(x, float)
    return np.column_stack([x, np.full_like(x, y), np.full_like(x, z)])


def test_parallel_offset_gives_constant_tracking_error_and_known_targeting_error() -> None:
    t = np.arange(11.0)
    tip = along_x(np.linspace(0.0, 0.092, 11), y=0.002)
    m = compute_trial_metrics(trial(t, tip))
    assert m.samples == 11
    assert m.tracking_mean == pytest.approx(0.002, abs=1e-9)
    assert m.tracking_std == pytest.approx(0.0, abs=1e-9)
    assert m.tracking_max == pytest.approx(0.002, abs=1e-9)
    assert m.targeting_error == pytest.approx(math.hypot(0.008, 0.002), abs=1e-12)
    assert m.duration == 10.0
    assert m.success
    assert m.time_to_target == 10.0  # only the last sample is within 10 mm (17.3 mm before)
    assert not m.timed_out
    assert m.curvature_mean == pytest.approx(0.0, abs=1e-9)


def test_tracking_error_statistics_over_varying_offsets() -> None:
    offsets = np.array([0.001, 0.003, 0.002, 0.006])
    tip = np.column_stack([[0.01, 0.02, 0.03, 0.04], np.zeros(4), offsets])
    m = compute_trial_metrics(trial(np.arange(4.0), tip))
    assert m.tracking_mean == pytest.approx(0.003, abs=1e-9)
    assert m.tracking_std == pytest.approx(np.std(offsets), abs=1e-9)
    assert m.tracking_max == pytest.approx(0.006, abs=1e-9)
    assert not m.success
    assert math.isnan(m.time_to_target)


def test_samples_before_the_goal_and_after_the_time_limit_are_left_out() -> None:
    t = np.array([0.0, 1.0, 2.0, 100.0, 181.0, 200.0])
    tip = along_x([0.0, 0.01, 0.02, 0.03, 0.04, 0.1], y=0.001)
    m = compute_trial_metrics(trial(t, tip, goal_t=(1.0,), path_t=(1.0,)))
    # window: t0 = 1 s (first pose at/after the goal), up to 181 s inclusive
    assert m.samples == 4
    assert m.duration == 180.0
    assert m.timed_out
    assert not m.success  # the last pose reaches the target, but after the 3-minute limit
    assert m.targeting_error == pytest.approx(math.hypot(0.06, 0.001), abs=1e-12)


def test_moving_target_and_replanning_use_the_message_in_effect() -> None:
    other = np.array([[0.0, 0.01, 0.0], [0.1, 0.01, 0.0]])  # replanned 10 mm to the side
    t = np.array([0.0, 1.0, 2.0, 3.0])
    tip = along_x([0.0, 0.02, 0.04, 0.06], y=0.004)
    goals = np.array([[0.06, 0.05, 0.0], [0.06, 0.004, 0.0]])
    m = compute_trial_metrics(trial(t, tip, goal_t=(0.0, 2.5), goal_p=goals,
                                    path_t=(0.0, 1.5), paths=(LINE, other)))
    # T_r: 4 mm to the first path for t = 0, 1; 6 mm to the replanned path for t = 2, 3
    assert m.tracking_mean == pytest.approx(0.005, abs=1e-9)
    assert m.tracking_max == pytest.approx(0.006, abs=1e-9)
    # The target moved at 2.5 s onto the last pose: T_a = 0 and success at t = 3
    assert m.targeting_error == pytest.approx(0.0, abs=1e-12)
    assert m.time_to_target == 3.0


def test_nan_tip_poses_are_left_out() -> None:
    tip = along_x([0.0, 0.01, 0.02], y=0.001)
    tip[1] = np.nan
    m = compute_trial_metrics(trial([0.0, 1.0, 2.0], tip))
    assert m.samples == 2
    assert m.tracking_max == pytest.approx(0.001, abs=1e-9)


def test_samples_before_the_first_path_are_not_tracked() -> None:
    t = np.array([0.0, 1.0, 2.0])
    tip = along_x([0.0, 0.01, 0.02], y=0.0)
    tip[0, 1] = 0.05
    m = compute_trial_metrics(trial(t, tip, path_t=(0.5,)))
    assert m.tracking_max == pytest.approx(0.0, abs=1e-9)


def test_curvature_of_a_circular_trajectory_in_per_metre() -> None:
    phi = np.linspace(0.0, np.pi, 400)
    tip = np.column_stack([0.1 - 0.02 * np.sin(phi), 0.02 * (1 - np.cos(phi)), np.zeros(400)])
    m = compute_trial_metrics(trial(np.linspace(0, 20, 400), tip),
                              MetricsConfig(curvature_spacing=2e-3))
    assert m.curvature_mean == pytest.approx(50.0, rel=1e-3)  # 1 / 20 mm
    assert m.curvature_std < 0.05


@pytest.mark.parametrize(('kwargs', 'match'), [
    (dict(tip_t=[], tip_p=np.zeros((0, 3))), 'expected tip poses, found none'),
    (dict(goal_t=(), goal_p=np.zeros((0, 3))), 'expected at least one goal'),
    (dict(path_t=(), paths=()), 'expected at least one planned path'),
    (dict(goal_t=(50.0,)), 'expected tip poses after the first goal'),
    (dict(path_t=(50.0,)), 'expected tip poses after the first planned path'),
    (dict(tip_t=[1.0, 0.0]), 'times must be non-decreasing'),
    (dict(tip_p=np.full((2, 3), np.nan)), 'expected finite tip poses, found only NaN'),
    (dict(goal_p=np.full((1, 3), np.nan)), 'expected a finite goal, found only NaN'),
    (dict(paths=(np.zeros((0, 3)),)), r'planned path #0 \(t = 0.000 s\) cannot be used as the '
                                      'desired path: expected at least 2 distinct waypoints'),
])
def test_unusable_trials_raise(kwargs: dict, match: str) -> None:
    base = dict(tip_t=[0.0, 1.0], tip_p=along_x([0.0, 0.01]))
    base.update(kwargs)
    with pytest.raises(MetricsError, match=match):
        compute_trial_metrics(trial(**base))


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('time_limit', 0.0, 'time_limit must be a positive'),
    ('success_radius', -1.0, 'success_radius must be a positive'),
    ('curvature_spacing', float('nan'), 'curvature_spacing must be a positive'),
])
def test_config_validation(field: str, value: float, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        MetricsConfig(**{field: value})


def metrics_for(condition: str, offsets: list[float]) -> list:
    out = []
    for i, y in enumerate(offsets):
        tip = along_x(np.linspace(0.0, 0.1, 5), y=y)
        out.append(compute_trial_metrics(trial(np.arange(5.0) * (i + 1), tip,
                                               name=f'{condition}{i}', condition=condition)))
    return out


def test_kruskal_wallis_matches_the_rank_formula() -> None:
    trials = metrics_for('cgail', [0.001, 0.002, 0.003]) + metrics_for(
        'centerline', [0.004, 0.005, 0.006])
    result = {r.metric: r for r in kruskal_by_condition(trials)}
    # ranks 1..6, sums 6 and 15: H = 12/(6*7) (36/3 + 225/3) - 3*7 = 27/7
    h = 27.0 / 7.0
    assert result['tracking_mean'].statistic == pytest.approx(h, rel=1e-12)
    assert result['tracking_mean'].pvalue == pytest.approx(math.erfc(math.sqrt(h / 2)), rel=1e-9)
    assert result['tracking_mean'].significant
    # durations 4, 8, 12 in both groups: identical distributions, H = 0
    assert result['duration'].statistic == pytest.approx(0.0, abs=1e-12)
    assert not result['duration'].significant


def test_kruskal_is_undefined_for_one_condition_or_equal_values() -> None:
    one = kruskal_by_condition(metrics_for('cgail', [0.001, 0.002]))
    assert all(math.isnan(r.pvalue) for r in one)
    same = metrics_for('a', [0.002]) + metrics_for('b', [0.002])
    result = {r.metric: r for r in kruskal_by_condition(same)}
    assert math.isnan(result['tracking_mean'].pvalue)


def test_markdown_report_and_box_plot(tmp_path: Path) -> None:
    trials = metrics_for('cgail', [0.001, 0.002]) + metrics_for('centerline', [0.004])
    tests = kruskal_by_condition(trials)
    text = markdown_report(trials, tests)
    assert '| cgail0 | cgail | 5 | 1.00 | 0.00 | 1.00 |' in text
    assert '| cgail | 2 | 100% | 1.50 ± 0.71 |' in text  # sample std of 1 and 2 mm
    assert '| centerline | 1 | 100% | 4.00 |' in text
    # H = (9/2 + 9) - 12; Cliff's delta: both cgail trials below the centerline one
    assert '| tracking error T_r | 1.500 | 0.2207 | no | -1.00 (large) |' in text
    assert '| cgail | 34%-100% |' in text  # Wilson interval of 2 / 2
    # ours: (4 - 1.5) / 4 = 62 % better than the centerline, beside the paper's 40 %
    assert '| tracking error T_r | 5.18 ± 3.48 | 40% | 1.50 ± 0.71 | 4.00 | 62% |' in text
    png = box_plots(trials, tests, tmp_path / 'plots' / 'box.png')
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    rows = write_csv(trials, tmp_path / 'm.csv').read_text().splitlines()
    assert rows[0].startswith('name,condition,samples,tracking_mean,')
    assert rows[1].startswith('cgail0,cgail,5,0.001')
    assert len(rows) == 4


def test_cliffs_delta_counts_the_pairs_and_labels_the_magnitude() -> None:
    from cgail_planner.core.metrics import cliffs_delta, cliffs_magnitude

    assert cliffs_delta([1, 2], [4]) == -1.0
    assert cliffs_delta([1, 2, 3], [2, 2, 2]) == 0.0  # one above, one below, one tie per b
    assert cliffs_delta([5, 6, float('nan')], [1, 5]) == pytest.approx(3 / 4)  # 3 > , 0 <, 1 =
    assert math.isnan(cliffs_delta([], [1.0]))
    assert [cliffs_magnitude(d) for d in (0.1, -0.2, 0.4, -0.9, math.nan)] == [
        'negligible', 'small', 'medium', 'large', 'n/a']


def test_paper_comparison_needs_both_conditions() -> None:
    trials = metrics_for('a', [0.001]) + metrics_for('b', [0.004])
    assert 'Side by side with the paper' not in markdown_report(trials, [])


def test_a_path_latched_from_an_earlier_trial_is_not_the_desired_path() -> None:
    # The previous trial's path (far away, stamped before this trial's goal) is delivered again
    # when the recorder subscribes (transient-local); this trial's path comes 0.5 s after the
    # goal. The samples before it are left out instead of measured against the old path.
    old = LINE + np.array([0.0, 0.05, 0.0])
    t = np.arange(0.0, 5.0, 0.25)
    tip = along_x(np.linspace(0.0, 0.05, len(t)), y=0.001)
    m = compute_trial_metrics(trial(t, tip, goal_t=(1.0,), path_t=(-60.0, 1.5),
                                    paths=(old, LINE)))
    assert m.tracking_max == pytest.approx(0.001, abs=1e-9)
    assert m.samples == int(np.sum(t >= 1.0))
    with pytest.raises(MetricsError, match='stamped at or after the first goal'):
        compute_trial_metrics(trial(t, tip, goal_t=(1.0,), path_t=(-60.0,), paths=(old,)))


# ----------------------------------------------------------------------------------------------
# 95 % intervals of the evaluation tables


def test_wilson_interval_matches_its_formula_and_stays_in_0_1() -> None:
    from cgail_planner.core.metrics import wilson_interval

    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = wilson_interval(100, 100)
    assert lo == pytest.approx(0.9630, abs=1e-4) and hi == 1.0
    assert all(math.isnan(x) for x in wilson_interval(0, 0))
    with pytest.raises(MetricsError, match="expected 0 <= successes <= n, found 11 of 10"):
        wilson_interval(11, 10)
    # scipy's interval is the closed form (Wilson 1927), for every count up to n = 60
    z = 1.959963984540054
    for n in range(1, 61):
        for k in range(n + 1):
            p = k / n
            centre = (p + z * z / (2 * n)) / (1 + z * z / n)
            half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
            assert wilson_interval(k, n) == pytest.approx(
                (max(0.0, centre - half), min(1.0, centre + half)), abs=1e-12)
    lo, hi = wilson_interval(5, 10, level=0.5)
    assert 0.2366 < lo < hi < 0.7634


def percentile_bootstrap(x: np.ndarray, statistic, seed: int = 0, resamples: int = 2000,
                         level: float = 0.95) -> tuple[float, float]:
    """The percentile bootstrap written out: ``resamples`` rows of indices drawn with
    replacement by ``default_rng(seed)``, the statistic of each row, its quantiles."""
    idx = np.random.default_rng(seed).integers(0, x.shape[-1], size=(resamples, x.shape[-1]))
    lo, hi = np.quantile(statistic(idx), [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def test_bootstrap_interval_is_seeded_and_brackets_the_statistic() -> None:
    from cgail_planner.core.metrics import bootstrap_interval

    x = np.random.default_rng(3).normal(50.0, 10.0, size=200)
    a, b = bootstrap_interval(x), bootstrap_interval(x)
    assert a == b and a[0] < np.median(x) < a[1] and a[1] - a[0] < 6.0
    lo, hi = bootstrap_interval(x, 'mean')
    assert lo < x.mean() < hi and (hi - lo) == pytest.approx(2 * 1.96 * 10 / np.sqrt(200),
                                                             rel=0.25)
    assert bootstrap_interval([4.0, 4.0]) == (4.0, 4.0)
    assert bootstrap_interval([7.0]) == (7.0, 7.0)
    assert all(math.isnan(v) for v in bootstrap_interval([]))
    # the same draws and quantiles as the percentile bootstrap written out, for any seed
    for seed in (0, 5):
        assert bootstrap_interval(x, seed=seed) == pytest.approx(
            percentile_bootstrap(x, lambda i: np.median(x[i], axis=1), seed), abs=1e-12)
        assert bootstrap_interval(x, 'mean', seed=seed) == pytest.approx(
            percentile_bootstrap(x, lambda i: x[i].mean(axis=1), seed), abs=1e-12)
    assert bootstrap_interval(x, seed=1) != a
    with pytest.raises(MetricsError, match="expected statistic 'median' or 'mean', found 'max'"):
        bootstrap_interval(x, 'max')


def test_the_rate_over_clusters_resamples_whole_clusters() -> None:
    from cgail_planner.core.metrics import cluster_bootstrap_rate, wilson_interval

    assert cluster_bootstrap_rate([[True] * 15] * 20) == (1.0, 1.0)
    # 16 anatomies always succeed, 4 always fail: 80 % pooled, but only 20 independent units
    groups = [[True] * 15] * 16 + [[False] * 15] * 4
    lo, hi = cluster_bootstrap_rate(groups)
    assert lo < 0.8 < hi
    wlo, whi = wilson_interval(240, 300)
    assert hi - lo > 2 * (whi - wlo)  # much wider than if the 300 trials were independent
    assert all(math.isnan(v) for v in cluster_bootstrap_rate([[], []]))
    assert cluster_bootstrap_rate([[True, False, False]]) == (1 / 3, 1 / 3)
    # whole clusters drawn as the percentile bootstrap written out draws them
    rng = np.random.default_rng(2)
    groups = [list(rng.random(int(rng.integers(0, 20))) < 0.6) for _ in range(12)]
    hits = np.array([sum(g) for g in groups])
    sizes = np.array([len(g) for g in groups])
    assert cluster_bootstrap_rate(groups, seed=4) == pytest.approx(percentile_bootstrap(
        hits, lambda i: hits[i].sum(axis=1) / np.maximum(sizes[i].sum(axis=1), 1), 4), abs=1e-12)

"""Markdown tables and box plots of trial metrics (the paper's Fig. "in-vitro comparison")."""

from __future__ import annotations

from collections.abc import Sequence
import math
from pathlib import Path

import numpy as np

from cgail_planner.core.metrics import (
    bootstrap_interval,
    cliffs_delta,
    cliffs_magnitude,
    COMPARED_METRICS,
    group_by_condition,
    KruskalResult,
    TrialMetrics,
    wilson_interval,
)


def _fmt(value: float, digits: int = 2) -> str:
    return 'n/a' if not math.isfinite(value) else f'{value:.{digits}f}'


#: The paper's in-vitro results (abstract and section V-B): C-GAIL path mean ± std and the
#: improvement over the centerline, (centerline - cgail) / centerline.
PAPER_IN_VITRO = {
    'targeting_error': (1.26, 0.55, 0.41),
    'tracking_mean': (5.18, 3.48, 0.40),
}


def _mean_std(values: Sequence[float], scale: float, digits: int) -> str:
    """Mean ± sample standard deviation (ddof 1) of the finite values; one value: itself."""
    arr = np.array(values, dtype=np.float64) * scale
    arr = arr[np.isfinite(arr)]
    if len(arr) == 0:
        return 'n/a'
    if len(arr) == 1:
        return f'{arr[0]:.{digits}f}'
    return f'{arr.mean():.{digits}f} ± {arr.std(ddof=1):.{digits}f}'


def paper_comparison(trials: Sequence[TrialMetrics]) -> list[str]:
    """Markdown lines comparing ours with the paper's in-vitro T_a and T_r (needs conditions
    ``cgail`` and ``centerline``; empty otherwise)."""
    groups = group_by_condition(trials)
    if 'cgail' not in groups or 'centerline' not in groups:
        return []
    lines = ['', '## Side by side with the paper (in vitro, C-GAIL path vs centerline)', '',
             '| metric | paper C-GAIL (mm) | paper improvement | ours C-GAIL (mm) '
             '| ours centerline (mm) | ours improvement |',
             '|---|---:|---:|---:|---:|---:|']
    for metric, (mean, std, gain) in PAPER_IN_VITRO.items():
        label = COMPARED_METRICS[metric][0]
        ours = [np.nanmean([getattr(m, metric) for m in groups[c]]) * 1e3
                for c in ('cgail', 'centerline')]
        improvement = (ours[1] - ours[0]) / ours[1] if ours[1] > 0.0 else math.nan
        lines.append(
            f'| {label} | {mean:.2f} ± {std:.2f} | {gain:.0%} '
            f'| {_mean_std([getattr(m, metric) for m in groups["cgail"]], 1e3, 2)} '
            f'| {_mean_std([getattr(m, metric) for m in groups["centerline"]], 1e3, 2)} '
            f'| {"n/a" if not math.isfinite(improvement) else f"{improvement:.0%}"} |')
    return lines


def markdown_report(trials: Sequence[TrialMetrics], tests: Sequence[KruskalResult]) -> str:
    """The per-trial table, the per-condition summary and the Kruskal-Wallis p-values."""
    lines = ['## Trials', '',
             '| trial | condition | samples | T_r mean (mm) | T_r std (mm) | T_r max (mm) '
             '| T_a (mm) | T (s) | success | curvature (mm^-1) |',
             '|---|---|---:|---:|---:|---:|---:|---:|---|---:|']
    for m in trials:
        success = 'yes' if m.success else ('no (time limit)' if m.timed_out else 'no')
        lines.append(
            f'| {m.name} | {m.condition} | {m.samples} | {_fmt(m.tracking_mean * 1e3)} '
            f'| {_fmt(m.tracking_std * 1e3)} | {_fmt(m.tracking_max * 1e3)} '
            f'| {_fmt(m.targeting_error * 1e3)} | {_fmt(m.duration, 1)} | {success} '
            f'| {_fmt(m.curvature_mean * 1e-3, 4)} ± {_fmt(m.curvature_std * 1e-3, 4)} |')
    lines += ['', '## Conditions (mean ± sample std over trials)', '',
              '| condition | trials | success rate | T_r (mm) | T_a (mm) | T (s) '
              '| curvature (mm^-1) |',
              '|---|---:|---:|---:|---:|---:|---:|']
    for condition, members in group_by_condition(trials).items():
        rate = sum(m.success for m in members) / len(members)
        lines.append(
            f'| {condition} | {len(members)} | {rate:.0%} '
            f'| {_mean_std([m.tracking_mean for m in members], 1e3, 2)} '
            f'| {_mean_std([m.targeting_error for m in members], 1e3, 2)} '
            f'| {_mean_std([m.duration for m in members], 1.0, 1)} '
            f'| {_mean_std([m.curvature_mean for m in members], 1e-3, 4)} |')
    lines += _confidence_lines(trials)
    groups = group_by_condition(trials)
    pair = (('cgail', 'centerline') if {'cgail', 'centerline'} <= set(groups)
            else tuple(groups)[:2] if len(groups) == 2 else None)
    effect = (f' | Cliff\'s delta ({pair[0]} vs {pair[1]}) |' if pair else ' |')
    lines += ['', '## Kruskal-Wallis test between conditions (significant: p < 0.05)', '',
              '| metric | H | p | significant' + effect,
              '|---|---:|---:|---|' + ('---|' if pair else '')]
    for test in tests:
        label = COMPARED_METRICS.get(test.metric, (test.metric, '', 1.0))[0]
        verdict = 'n/a' if not math.isfinite(test.pvalue) else (
            'yes' if test.significant else 'no')
        row = f'| {label} | {_fmt(test.statistic, 3)} | {_fmt(test.pvalue, 4)} | {verdict} |'
        if pair:
            d = cliffs_delta([getattr(m, test.metric) for m in groups[pair[0]]],
                             [getattr(m, test.metric) for m in groups[pair[1]]])
            row += f' {_fmt(d, 2)} ({cliffs_magnitude(d)}) |'
        lines.append(row)
    if pair:
        lines += ['', f"Cliff's delta: P({pair[0]} > {pair[1]}) - P({pair[0]} < {pair[1]}) "
                  'over all pairs of trials (negative: smaller for the first; magnitude after '
                  'Romano et al. 2006).']
    lines += paper_comparison(trials)
    return '\n'.join(lines) + '\n'


CSV_FIELDS = ('name', 'condition', 'samples', 'tracking_mean', 'tracking_std', 'tracking_max',
              'targeting_error', 'duration', 'success', 'time_to_target', 'timed_out',
              'curvature_mean', 'curvature_std', 'path_length')


def _ci(values: Sequence[float], scale: float, digits: int) -> str:
    """Percentile-bootstrap 95 % interval of the mean (finite values), ``lo-hi``."""
    arr = np.array(values, dtype=np.float64) * scale
    arr = arr[np.isfinite(arr)]
    if len(arr) < 2:
        return 'n/a'
    lo, hi = bootstrap_interval(arr.tolist(), statistic='mean')
    return f'{lo:.{digits}f}-{hi:.{digits}f}'


def _confidence_lines(trials: Sequence[TrialMetrics]) -> list[str]:
    """Per condition: the 95 % intervals of the success rate (Wilson) and of the mean T_r, T_a
    and T (percentile bootstrap, 2,000 resamples, seeded: a function of the values)."""
    lines = ['', '## 95 % confidence intervals (success: Wilson; means: percentile bootstrap)',
             '', '| condition | success rate | T_r mean (mm) | T_a mean (mm) | T mean (s) |',
             '|---|---:|---:|---:|---:|']
    for condition, members in group_by_condition(trials).items():
        lo, hi = wilson_interval(sum(m.success for m in members), len(members))
        lines.append(f'| {condition} | {lo:.0%}-{hi:.0%} '
                     f'| {_ci([m.tracking_mean for m in members], 1e3, 2)} '
                     f'| {_ci([m.targeting_error for m in members], 1e3, 2)} '
                     f'| {_ci([m.duration for m in members], 1.0, 1)} |')
    return lines


def write_csv(trials: Sequence[TrialMetrics], path: Path) -> Path:
    """Per-trial metrics in SI units (m, s, 1/m), one row per trial."""
    import csv

    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open('w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(CSV_FIELDS)
        for m in trials:
            writer.writerow([getattr(m, f) for f in CSV_FIELDS])
    return path


def box_plots(trials: Sequence[TrialMetrics], tests: Sequence[KruskalResult],
              path: Path) -> Path:
    """Write one box plot per compared metric (conditions side by side) to a PNG."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    groups = group_by_condition(trials)
    pvalues = {t.metric: t.pvalue for t in tests}
    metrics = list(COMPARED_METRICS.items())
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.0 * len(metrics), 4.0))
    for ax, (metric, (label, unit, scale)) in zip(np.atleast_1d(axes), metrics, strict=True):
        data = []
        for members in groups.values():
            values = np.array([getattr(m, metric) for m in members], dtype=np.float64) * scale
            data.append(values[np.isfinite(values)])
        ax.boxplot(data, tick_labels=list(groups), showmeans=True, showfliers=False)
        for i, values in enumerate(data, start=1):
            ax.scatter(np.full(len(values), i), values, s=12, alpha=0.6, zorder=3)
        pvalue = pvalues.get(metric, math.nan)
        mark = ' *' if math.isfinite(pvalue) and pvalue < 0.05 else ''
        ptext = f'p = {pvalue:.3g}{mark}' if math.isfinite(pvalue) else 'p = n/a'
        ax.set_title(f'{label}\n(Kruskal-Wallis {ptext})', fontsize=10)
        ax.set_ylabel(unit)
        ax.grid(axis='y', alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

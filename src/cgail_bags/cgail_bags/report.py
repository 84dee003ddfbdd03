"""Markdown tables and box plots of trial metrics (the paper's Fig. "in-vitro comparison")."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import fields
import math
from pathlib import Path
from typing import Any

import numpy as np

from cgail_planner.core.metrics import (
    bootstrap_interval,
    cliffs_delta,
    cliffs_magnitude,
    COMPARED_METRICS,
    group_by_condition,
    kruskal_by_condition,
    KruskalResult,
    MetricsConfig,
    MetricsError,
    TrialMetrics,
    wilson_interval,
)


def _fmt(value: float, digits: int = 2) -> str:
    return 'n/a' if not math.isfinite(value) else f'{value:.{digits}f}'


def _pvalue(p: float, digits: int = 4) -> str:
    """A p-value with ``digits`` decimals, in scientific notation below ``10**-digits`` (never
    a bare 0)."""
    if math.isfinite(p) and 0.0 <= p < 10.0 ** -digits:
        return f'{p:.1e}'
    return _fmt(p, digits)


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


def _improvement(treated: Sequence[float], reference: Sequence[float]) -> str:
    """``(reference - treated) / reference`` of the means (finite values), as a percentage;
    ``n/a`` when the reference mean is not positive."""
    ref = float(np.nanmean(reference))
    gain = (ref - float(np.nanmean(treated))) / ref if ref > 0.0 else math.nan
    return 'n/a' if not math.isfinite(gain) else f'{gain:.0%}'


def _finite(members: Sequence[TrialMetrics], metric: str, scale: float) -> np.ndarray:
    """The finite values of ``metric`` over ``members``, times ``scale`` (a box's data)."""
    values = np.array([getattr(m, metric) for m in members], dtype=np.float64) * scale
    return values[np.isfinite(values)]


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
        cgail, centerline = ([getattr(m, metric) for m in groups[c]]
                             for c in ('cgail', 'centerline'))
        lines.append(
            f'| {label} | {mean:.2f} ± {std:.2f} | {gain:.0%} '
            f'| {_mean_std(cgail, 1e3, 2)} | {_mean_std(centerline, 1e3, 2)} '
            f'| {_improvement(cgail, centerline)} |')
    return lines


def markdown_report(trials: Sequence[TrialMetrics], tests: Sequence[KruskalResult],
                    config: MetricsConfig | None = None) -> str:
    """The per-trial table, the per-condition summary and the Kruskal-Wallis p-values
    (``config``: the metrics' settings, named in the note on the curvature)."""
    cfg = config or MetricsConfig()
    lines = ['## Trials', '',
             f'Curvature: of the tip\'s path smoothed in time (Savitzky-Golay cubic over '
             f'{cfg.curvature_smoothing:g} s) and resampled every {cfg.curvature_spacing * 1e3:g} '
             'mm, mean ± std of the Menger curvature (cgail_planner.core.metrics).', '',
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
        row = f'| {label} | {_fmt(test.statistic, 3)} | {_pvalue(test.pvalue)} | {verdict} |'
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


def read_csv(path: Path) -> list[TrialMetrics]:
    """The trials of a ``metrics.csv`` written by :func:`write_csv` (a session's or
    ``cgail bag metrics``'). Raises :class:`MetricsError` naming the file, the row and what was
    wrong (missing file or column, a value that is not a number or a boolean)."""
    import csv

    if not Path(path).is_file():
        raise MetricsError(f'{path}: expected a metrics.csv (cgail session / cgail bag metrics '
                           f'output), found no file')
    with Path(path).open(newline='') as stream:
        rows = list(csv.reader(stream))
    if not rows or tuple(rows[0]) != CSV_FIELDS:
        raise MetricsError(f'{path}: expected the header {",".join(CSV_FIELDS)}, found '
                           f'{",".join(rows[0]) if rows else "an empty file"}')
    kinds = {f.name: f.type for f in fields(TrialMetrics)}
    trials = []
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(CSV_FIELDS):
            raise MetricsError(f'{path}:{line}: expected {len(CSV_FIELDS)} fields, found '
                               f'{len(row)}')
        values: dict[str, Any] = {}
        for name, text in zip(CSV_FIELDS, row, strict=True):
            kind = kinds[name]
            try:
                if kind == 'bool':
                    if text not in ('True', 'False'):
                        raise ValueError(text)
                    values[name] = text == 'True'
                elif kind == 'int':
                    values[name] = int(text)
                elif kind == 'float':
                    values[name] = float(text)
                else:
                    values[name] = text
            except ValueError:
                raise MetricsError(f'{path}:{line}: expected {name} to be {kind}, found '
                                   f'{text!r}') from None
        trials.append(TrialMetrics(**values))
    if not trials:
        raise MetricsError(f'{path}: expected at least one trial, found none')
    return trials


#: The metrics of a comparison between sessions (the paper's two in-vitro measures).
SESSION_METRICS = ('tracking_mean', 'targeting_error')


def session_comparison(sessions: Mapping[str, Sequence[TrialMetrics]],
                       pair: tuple[str, str] = ('cgail', 'centerline')) -> str:
    """Markdown: per session (e.g. plant x mode) and condition, the trials, the success rate
    with its Wilson interval, and T_r and T_a as mean ± sample std with the percentile-bootstrap
    interval of the mean; then per session the comparison of ``pair``: the improvement of the
    first over the second, the Kruskal-Wallis p and Cliff's delta; the paper's row last."""
    lines = ['| session | condition | trials | success [95 % CI] | T_r (mm) [95 % CI] '
             '| T_a (mm) [95 % CI] |', '|---|---|---:|---|---|---|']
    for label, trials in sessions.items():
        for condition, members in group_by_condition(trials).items():
            wins = sum(m.success for m in members)
            lo, hi = wilson_interval(wins, len(members))
            cells = [f'{_mean_std([getattr(m, k) for m in members], 1e3, 2)} '
                     f'[{_ci([getattr(m, k) for m in members], 1e3, 2)}]'
                     for k in SESSION_METRICS]
            lines.append(f'| {label} | {condition} | {len(members)} '
                         f'| {wins / len(members):.0%} [{lo:.0%}-{hi:.0%}] | {cells[0]} '
                         f'| {cells[1]} |')
    paper = PAPER_IN_VITRO
    lines.append(f'| paper (in vitro) | {pair[0]} | 10 | 100% '
                 f'| {paper["tracking_mean"][0]:.2f} ± {paper["tracking_mean"][1]:.2f} '
                 f'| {paper["targeting_error"][0]:.2f} ± {paper["targeting_error"][1]:.2f} |')
    lines += ['', f'{pair[0]} against {pair[1]} (improvement: ({pair[1]} - {pair[0]}) / '
              f'{pair[1]} of the means; Kruskal-Wallis p; Cliff\'s delta, negative: smaller '
              f'for {pair[0]}):', '',
              '| session | T_r improvement | T_r p | T_r delta | T_a improvement | T_a p '
              '| T_a delta |', '|---|---:|---:|---|---:|---:|---|']
    for label, trials in sessions.items():
        groups = group_by_condition(trials)
        if not set(pair) <= set(groups):
            continue
        tests = {t.metric: t for t in kruskal_by_condition(
            [m for c in pair for m in groups[c]], SESSION_METRICS)}
        cells = []
        for k in SESSION_METRICS:
            a = [getattr(m, k) for m in groups[pair[0]]]
            b = [getattr(m, k) for m in groups[pair[1]]]
            d = cliffs_delta(a, b)
            cells += [_improvement(a, b), _pvalue(tests[k].pvalue, 3),
                      f'{_fmt(d, 2)} ({cliffs_magnitude(d)})']
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    lines.append(f'| paper (in vitro; p not given in numbers) | {paper["tracking_mean"][2]:.0%} '
                 f'| - | - | {paper["targeting_error"][2]:.0%} | - | - |')
    return '\n'.join(lines) + '\n'


def session_box_plots(sessions: Mapping[str, Sequence[TrialMetrics]], path: Path) -> Path:
    """One panel per :data:`SESSION_METRICS`: a box per session and condition, grouped by
    session, with the trials as points."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(SESSION_METRICS),
                             figsize=(max(6.0, 1.3 * sum(len(group_by_condition(t))
                                                         for t in sessions.values())) + 1.0,
                                      4.2), squeeze=False)
    colours: dict[str, str] = {}
    for ax, metric in zip(axes[0], SESSION_METRICS, strict=True):
        label, unit, scale = COMPARED_METRICS[metric]
        pos, ticks = 1.0, []
        for trials in sessions.values():
            first = pos
            for condition, members in group_by_condition(trials).items():
                values = _finite(members, metric, scale)
                colour = colours.setdefault(condition, f'C{len(colours)}')
                ax.boxplot([values], positions=[pos], widths=0.7, showmeans=True,
                           showfliers=False, patch_artist=True,
                           boxprops={'facecolor': colour, 'alpha': 0.35})
                ax.scatter(np.full(len(values), pos), values, s=9, alpha=0.6, zorder=3,
                           color=colour)
                pos += 1.0
            ticks.append(0.5 * (first + pos - 1.0))
            pos += 0.6
        ax.set_xticks(ticks, list(sessions), rotation=20, ha='right', fontsize=8)
        ax.set_title(label, fontsize=10)
        ax.set_ylabel(unit)
        ax.grid(axis='y', alpha=0.3)
    from matplotlib.patches import Patch

    fig.legend(handles=[Patch(color=c, alpha=0.5, label=name) for name, c in colours.items()],
               loc='upper right', fontsize=8)
    fig.tight_layout(rect=(0, 0, 0.92, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def box_plots(trials: Sequence[TrialMetrics], tests: Sequence[KruskalResult],
              path: Path) -> Path:
    """Write one box plot per compared metric (conditions side by side) to a PNG, and a last
    panel with each condition's success rate and its 95 % Wilson interval (a success is 0 or
    1: a box of it would say nothing)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    groups = group_by_condition(trials)
    pvalues = {t.metric: t.pvalue for t in tests}
    metrics = list(COMPARED_METRICS.items())
    fig, axes = plt.subplots(1, len(metrics) + 1, figsize=(4.0 * (len(metrics) + 1), 4.0))
    axes = np.atleast_1d(axes)
    # many or long condition names: slanted, or they run into each other
    slant = len(groups) > 2 or any(len(c) > 10 for c in groups)
    ax = axes[-1]
    for i, members in enumerate(groups.values(), start=1):
        wins = sum(bool(m.success) for m in members)
        low, high = wilson_interval(wins, len(members))
        rate = wins / len(members)
        ax.bar(i, 100.0 * rate, width=0.6, alpha=0.6)
        ax.errorbar(i, 100.0 * rate, yerr=[[100.0 * (rate - low)], [100.0 * (high - rate)]],
                    fmt='none', ecolor='black', capsize=4)
    ax.set_xticks(range(1, len(groups) + 1), list(groups))
    ax.set_ylim(0.0, 105.0)
    ax.set_title('success rate\n(95 % Wilson interval)', fontsize=10)
    ax.set_ylabel('%')
    ax.grid(axis='y', alpha=0.3)
    for ax, (metric, (label, unit, scale)) in zip(axes[:-1], metrics, strict=True):
        data = [_finite(members, metric, scale) for members in groups.values()]
        ax.boxplot(data, tick_labels=list(groups), showmeans=True, showfliers=False)
        for i, values in enumerate(data, start=1):
            ax.scatter(np.full(len(values), i), values, s=12, alpha=0.6, zorder=3)
        pvalue = pvalues.get(metric, math.nan)
        mark = ' *' if math.isfinite(pvalue) and pvalue < 0.05 else ''
        ptext = f'p = {pvalue:.3g}{mark}' if math.isfinite(pvalue) else 'p = n/a'
        ax.set_title(f'{label}\n(Kruskal-Wallis {ptext})', fontsize=10)
        ax.set_ylabel(unit)
        ax.grid(axis='y', alpha=0.3)
    if slant:
        for ax in axes:
            plt.setp(ax.get_xticklabels(), rotation=30, ha='right')
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

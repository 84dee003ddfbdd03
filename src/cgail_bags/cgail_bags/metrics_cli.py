"""``cgail bag metrics``: the paper's in-vitro metrics from trial bags, a markdown table and box
plots.

    cgail bag metrics bags/fixtures            # every bag in the directory
    cgail bag metrics runs/cgail runs/centerline -o out   # dir = condition
    cgail bag metrics trial1 trial2 --condition cgail     # label given

A trial is one bag (directory with metadata.yaml or a bare .mcap). A directory argument that is
not itself a bag holds one bag per trial. The condition of a trial is, first match wins:
``--condition``, the bag's ``custom_data`` ``condition`` (``cgail bag record --condition``), the
name of
the directory argument holding it, else ``unlabelled``. Metric definitions:
:mod:`cgail_planner.core.metrics`. Writes ``<out>/metrics.md``,
``<out>/metrics.csv`` (per trial, SI units) and ``<out>/metrics_boxplot.png`` and prints the
table; exit status 2 on an unreadable bag or a trial that cannot be evaluated.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
import sys

from cgail_bags.errors import BagError
from cgail_bags.reader import find_trials, read_trial, TrialTopics
from cgail_bags.report import box_plots, markdown_report, write_csv
from cgail_planner.core.metrics import (
    compute_trial_metrics,
    kruskal_by_condition,
    MetricsConfig,
    MetricsError,
    TrialMetrics,
)
from cgail_planner.core.path_fit import PathFitConfig
from cgail_sim.cli_help import tool_parser


def evaluate_bags(
    paths: Sequence[Path | str],
    config: MetricsConfig | None = None,
    condition: str | None = None,
    topics: TrialTopics | None = None,
) -> list[TrialMetrics]:
    """Metrics of every trial bag found in ``paths`` (see the module docstring).

    Raises:
        BagError: A bag cannot be read or lacks a needed topic.
        MetricsError: A trial cannot be evaluated.
    """
    results = []
    for bag, group in find_trials(paths):
        trial = read_trial(bag, condition=condition, topics=topics, group=group)
        try:
            results.append(compute_trial_metrics(trial, config))
        except MetricsError as exc:
            raise MetricsError(f'{bag}: {exc}') from None
    return results


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail bag metrics``."""
    parser = tool_parser('bag metrics', __doc__, details=True)
    parser.add_argument('bags', nargs='+', type=Path, help='trial bags or directories of bags')
    parser.add_argument('-o', '--output', type=Path, default=Path('runs', 'metrics'),
                        help='directory for metrics.md and metrics_boxplot.png')
    parser.add_argument('--condition', default=None, help='condition label of all given bags')
    parser.add_argument('--time-limit', type=float, default=180.0,
                        help='maximum operation time in s (default 180)')
    parser.add_argument('--epsilon', type=float, default=10.0,
                        help='success radius around the target in mm (default 10)')
    parser.add_argument('--path-spacing', type=float, default=0.5,
                        help='arc-length step of the resampled desired path in mm (default 0.5)')
    parser.add_argument('--curvature-spacing', type=float, default=3.0,
                        help='arc-length step of the smoothed trajectory for curvature in mm '
                             '(default 3)')
    parser.add_argument('--curvature-smoothing', type=float, default=2.0,
                        help='window in s of the Savitzky-Golay cubic that smooths the tip '
                             'positions in time before the curvature (default 2; 0: none, '
                             "the curvature of the tracker's noise)")
    parser.add_argument('--no-plot', action='store_true', help='skip the box plots')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail bag metrics``; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        config = MetricsConfig(time_limit=args.time_limit, success_radius=args.epsilon * 1e-3,
                               path_fit=PathFitConfig(spacing=args.path_spacing * 1e-3),
                               curvature_spacing=args.curvature_spacing * 1e-3,
                               curvature_smoothing=args.curvature_smoothing)
    except ValueError as exc:
        parser.error(str(exc))
    try:
        trials = evaluate_bags(args.bags, config, condition=args.condition)
    except (BagError, MetricsError) as exc:
        print(f'cgail bag metrics: error: {exc}', file=sys.stderr)
        return 2
    tests = kruskal_by_condition(trials)
    text = markdown_report(trials, tests, config)
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / 'metrics.md').write_text('# Offline metrics\n\n' + text)
    write_csv(trials, args.output / 'metrics.csv')
    print(text)
    print(f'cgail bag metrics: wrote {args.output / "metrics.md"} and '
          f'{args.output / "metrics.csv"}')
    if not args.no_plot:
        png = box_plots(trials, tests, args.output / 'metrics_boxplot.png')
        print(f'cgail bag metrics: wrote {png}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

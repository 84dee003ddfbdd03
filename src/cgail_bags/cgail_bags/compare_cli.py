"""``cgail bag compare``: several in-vitro sessions side by side (plants, modes, seeds).

    cgail bag compare identified/static=runs/s16/identified_static \\
        ideal/static=runs/s16/ideal_static -o runs/s16/compare

Each argument is ``LABEL=DIR`` (or just ``DIR``, labelled by its name): the output directory of
a ``cgail session`` (or of ``cgail bag metrics``), whose ``metrics.csv`` holds one row per trial.
Writes ``<out>/compare.md`` (per session and condition: trials, success with its Wilson
interval, T_r and T_a as mean ± std with the bootstrap interval of the mean; per session the
C-GAIL path against the centerline: improvement, Kruskal-Wallis p and Cliff's delta; the paper's
numbers last) and ``<out>/compare_boxplot.png``, and prints the tables. The metrics are read,
not recomputed, so comparing is instant; exit status 2 with one line on a missing or malformed
input.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
import sys

from cgail_bags.report import read_csv, session_box_plots, session_comparison
from cgail_planner.core.metrics import MetricsError
from cgail_sim.cli_help import tool_parser


def parse_session(spec: str) -> tuple[str, Path]:
    """``LABEL=DIR`` or ``DIR`` -> (label, directory)."""
    label, sep, where = spec.partition('=')
    if not sep:
        label, where = Path(spec).name, spec
    if not label or not where:
        raise MetricsError(f'session {spec!r}: expected LABEL=DIR or DIR')
    return label, Path(where)


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail bag compare``."""
    p = tool_parser('bag compare', __doc__, details=True)
    p.add_argument('sessions', nargs='+', metavar='LABEL=DIR',
                   help='session output directories (holding metrics.csv), optionally labelled')
    p.add_argument('-o', '--output', type=Path, default=Path('runs/session_compare'),
                   help='directory for compare.md and compare_boxplot.png')
    p.add_argument('--no-plot', action='store_true', help='skip the box plots')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail bag compare``; returns the exit status."""
    args = build_parser().parse_args(argv)
    sessions = {}
    try:
        for spec in args.sessions:
            label, where = parse_session(spec)
            if label in sessions:
                raise MetricsError(f'session label {label!r} given twice: expected distinct '
                                   'labels (LABEL=DIR)')
            sessions[label] = read_csv(where / 'metrics.csv')
    except MetricsError as exc:
        print(f'cgail bag compare: error: {exc}', file=sys.stderr)
        return 2
    text = session_comparison(sessions)
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / 'compare.md').write_text('# In-vitro sessions compared\n\n' + text)
    print(text)
    written = [args.output / 'compare.md']
    if not args.no_plot:
        written.append(session_box_plots(sessions, args.output / 'compare_boxplot.png'))
    print('cgail bag compare: wrote ' + ' and '.join(str(p) for p in written))
    return 0


if __name__ == '__main__':
    sys.exit(main())

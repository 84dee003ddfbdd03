"""``cgail pivot-calibrate``: :mod:`em_tracker.cli.pivot_calibrate` on the one command line.

The rig's calibration commands belong to ``em_tracker``: a lean rig install has them as
the ``pivot_calibrate`` console script, without ``cgail``. This is the same command, with the
same arguments and exit status, and its help in ``cgail``'s form.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from cgail_sim.cli_help import tool_parser
from em_tracker.cli import pivot_calibrate as _tool


def build_parser() -> argparse.ArgumentParser:
    """``cgail pivot-calibrate``'s parser: the command's arguments, its docstring as the help."""
    parser = tool_parser('pivot-calibrate', _tool.__doc__, details=True)
    _tool.add_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command (exit status as :func:`em_tracker.cli.pivot_calibrate.main`)."""
    return _tool.main(None if argv is None else list(argv), parser=build_parser())

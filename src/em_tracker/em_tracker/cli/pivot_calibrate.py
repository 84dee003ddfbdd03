"""``pivot_calibrate``: the sensor -> tip tool transform from a recorded pivoting motion.

    cgail pivot-calibrate ...       # the same command on a full workspace
    ros2 run em_tracker pivot_calibrate poses.csv -o calibration.yaml [--shaft-axis 0,0,1]
    ros2 run em_tracker pivot_calibrate bags/pivot_run --topic em_tracker/tip_pose -o ...

Solves the pivot calibration (prints the tip offset, the pivot point and the residual RMS) and
writes ``tool_transform: [tx ty tz qx qy qz qw]`` (``T_sensor_tip``, m; tip frame +y along the
shaft towards the tip, see :mod:`em_tracker.core.calibration`) for the ``aurora`` node into the
parameters file (other entries of an existing file are kept).

Record the poses of the sensor itself: a bag of ``em_tracker/tip_pose`` qualifies while the
node's ``tool_transform`` is the identity (its default; with a tool transform the topic carries
the tip's pose, not the sensor's). Any fixed registration only moves the pivot point.

Exit status: 0 written; 1 refused (residual above ``--max-residual-mm`` without ``--force``); 2
bad input (missing or malformed file, NaN, too little rotation). Nothing is written unless the
status is 0.
"""

from __future__ import annotations

import argparse
from datetime import datetime
import math
from pathlib import Path
import sys

import numpy as np

from em_tracker.cli.files import read_poses, run_command, write_parameters
from em_tracker.core.calibration import pivot_calibration, PivotConfig, sensor_to_tip_transform
from em_tracker.core.errors import CalibrationError
from em_tracker.core.pose import Registration

PROG = 'pivot_calibrate'
#: Shortest tip offset whose direction is taken as the shaft axis (``--shaft-axis offset``), m.
MIN_AXIS_OFFSET_M = 0.003


def _axis(text: str) -> str | tuple[float, float, float]:
    if text == 'offset':
        return text
    try:
        x, y, z = (float(v) for v in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'offset' or x,y,z, found {text!r}") from None
    if not all(math.isfinite(v) for v in (x, y, z)) or x == y == z == 0.0:
        raise argparse.ArgumentTypeError(f'expected a finite non-zero x,y,z, found {text!r}')
    return x, y, z


def build_parser() -> argparse.ArgumentParser:
    """The parser of the ``pivot_calibrate`` console script."""
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The command's arguments, on ``p`` (also ``cgail pivot-calibrate``'s parser)."""
    p.add_argument('poses', type=Path,
                   help='CSV (x_mm y_mm z_mm qx qy qz qw) or rosbag2 bag of sensor poses')
    p.add_argument('-o', '--output', type=Path, required=True,
                   help='ROS 2 parameters file to write (updated if it exists)')
    p.add_argument('--topic', default='em_tracker/tip_pose',
                   help='PoseStamped topic when reading a bag (default: %(default)s)')
    p.add_argument('--shaft-axis', type=_axis, default='offset',
                   help="shaft direction towards the tip in the sensor frame, x,y,z; 'offset' "
                        '(default): the direction of the recovered tip offset')
    p.add_argument('--node', default='aurora', help='node name in the file (default: aurora)')
    p.add_argument('--min-spread-deg', type=float,
                   default=math.degrees(PivotConfig.min_spread_rad),
                   help='refuse a rotation spread below this (default: %(default)s)')
    p.add_argument('--max-residual-mm', type=float,
                   default=PivotConfig.max_residual_rms_m * 1e3,
                   help='refuse a residual RMS above this unless --force (default: '
                        '%(default)s)')
    p.add_argument('--force', action='store_true', help='write even when the residual is high')


def run(args: argparse.Namespace, config: PivotConfig) -> int:
    """Calibrate, print, write; returns the exit status.

    Raises:
        InputFileError, CalibrationError: bad input (nothing written).
    """
    rotations, positions = read_poses(args.poses, args.topic)
    result = pivot_calibration(rotations, positions, config)
    offset = result.tip_offset_m
    length = float(np.linalg.norm(offset))
    print(f'poses: {len(rotations)}, rotation spread {math.degrees(result.spread_rad):.1f} deg')
    print(f'tip offset (sensor frame): {np.round(offset * 1e3, 2).tolist()} mm, '
          f'|offset| {length * 1e3:.2f} mm')
    print(f'pivot (tracker frame): {np.round(result.pivot_m * 1e3, 2).tolist()} mm')
    print(f'residual RMS {result.residual_rms_m * 1e3:.2f} mm')
    if args.shaft_axis == 'offset':
        if length < MIN_AXIS_OFFSET_M:
            raise CalibrationError(
                f'tip offset {length * 1e3:.2f} mm is too short to give the shaft direction: '
                f'expected at least {MIN_AXIS_OFFSET_M * 1e3:g} mm; pass --shaft-axis x,y,z')
        axis = offset
    else:
        axis = np.asarray(args.shaft_axis, dtype=float)
        if length >= MIN_AXIS_OFFSET_M:
            angle = math.degrees(math.acos(float(np.clip(
                axis @ offset / (np.linalg.norm(axis) * length), -1.0, 1.0))))
            print(f'angle between the shaft axis and the offset: {angle:.1f} deg')
    if result.residual_too_high and not args.force:
        print(f'{PROG}: refused: residual RMS {result.residual_rms_m * 1e3:.2f} mm above '
              f'{args.max_residual_mm:g} mm (tip slipping in the divot?); nothing written '
              '(--force writes it)', file=sys.stderr)
        return 1
    transform = Registration(sensor_to_tip_transform(offset, axis))
    comment = (f'{datetime.now().isoformat(timespec="seconds")} from {args.poses}: '
               f'{len(rotations)} poses, |offset| {length * 1e3:.2f} mm, residual RMS '
               f'{result.residual_rms_m * 1e3:.2f} mm')
    write_parameters(args.output, args.node, {'tool_transform': transform.to_flat()},
                     [comment], tool=PROG)
    print(f'wrote {args.node}.tool_transform to {args.output}')
    return 0


def main(argv: list[str] | None = None,
         parser: argparse.ArgumentParser | None = None) -> int:
    """Run the command on ``argv`` with ``parser`` (default :func:`build_parser`'s)."""
    parser = parser or build_parser()
    args = parser.parse_args(argv)
    return run_command(parser.prog, parser, args, lambda: PivotConfig(
        min_spread_rad=math.radians(args.min_spread_deg),
        max_residual_rms_m=args.max_residual_mm * 1e-3), run)


if __name__ == '__main__':
    sys.exit(main())

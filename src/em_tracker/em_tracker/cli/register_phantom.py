"""``register_phantom``: the ``aurora -> phantom`` registration from touched fiducials.

    cgail register-phantom ...       # the same command on a full workspace
    ros2 run em_tracker register_phantom fiducials.csv -o calibration.yaml \\
        [--trajectory traced.csv --mesh lumen.stl --mesh-unit mm] [--force]

Registers the touched fiducials on their model positions (paired points; prints FRE and the
leave-one-out TRE), optionally refines on the lumen wall with a traced trajectory (ICP; prints
its RMS), and writes ``registration: [tx ty tz qx qy qz qw]`` for the ``aurora`` node into the
parameters file (other entries of an existing file are kept). Start the node with it after the
defaults: ``--params-file config/aurora.yaml --params-file calibration.yaml``. File formats:
:mod:`em_tracker.cli.files`.

Exit status: 0 written; 1 refused (FRE above ``--max-fre-mm`` or ICP not converged, without
``--force``); 2 bad input (missing or malformed file, NaN, degenerate fiducials). Nothing is
written unless the status is 0.
"""

from __future__ import annotations

import argparse
from datetime import datetime
import math
from pathlib import Path
import sys

from em_tracker.cli.files import (
    read_fiducials,
    read_surface,
    read_trajectory,
    run_command,
    UNITS,
    write_parameters,
)
from em_tracker.core.registration import PairedPointConfig, refine_icp, register_paired_points

PROG = 'register_phantom'


def _mm(value_m: float) -> str:
    return 'n/a' if math.isnan(value_m) else f'{value_m * 1e3:.2f} mm'


def build_parser() -> argparse.ArgumentParser:
    """The parser of the ``register_phantom`` console script."""
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The command's arguments, on ``p`` (also ``cgail register-phantom``'s parser)."""
    p.add_argument('fiducials', type=Path,
                   help='CSV (model_x_mm..., tracker_x_mm...) or YAML of the fiducial pairs')
    p.add_argument('-o', '--output', type=Path, required=True,
                   help='ROS 2 parameters file to write (updated if it exists)')
    p.add_argument('--trajectory', type=Path,
                   help='CSV (x_mm y_mm z_mm) of the tip traced along the wall, aurora frame')
    p.add_argument('--mesh', type=Path,
                   help='lumen wall in the phantom frame: .stl/.ply/.obj or .npz')
    p.add_argument('--mesh-unit', choices=sorted(UNITS), default='mm',
                   help='length unit of --mesh (default: mm)')
    p.add_argument('--node', default='aurora', help='node name in the file (default: aurora)')
    p.add_argument('--max-fre-mm', type=float, default=PairedPointConfig.max_fre_m * 1e3,
                   help='refuse above this FRE unless --force (default: %(default)s)')
    p.add_argument('--min-line-distance-mm', type=float,
                   default=PairedPointConfig.min_line_distance_m * 1e3,
                   help='smallest RMS distance of the fiducials from their best-fit line '
                        '(default: %(default)s)')
    p.add_argument('--force', action='store_true',
                   help='write even when FRE is too high or ICP did not converge')


def run(args: argparse.Namespace, config: PairedPointConfig) -> int:
    """Register, print, write; returns the exit status.

    Raises:
        InputFileError, CalibrationError: bad input (nothing written).
    """
    model, tracker, names = read_fiducials(args.fiducials)
    paired = register_paired_points(model, tracker, config)
    print(f'fiducials: {len(names)}, FRE {_mm(paired.fre_m)}, TRE (leave-one-out) '
          f'{_mm(paired.tre_m)}')
    for name, res, loo in zip(names, paired.residuals_m, paired.loo_errors_m, strict=True):
        print(f'  {name}: residual {_mm(res)}, leave-one-out {_mm(loo)}')
    registration = paired.registration
    comments = [f'{datetime.now().isoformat(timespec="seconds")} from {args.fiducials}: '
                f'FRE {_mm(paired.fre_m)}, TRE {_mm(paired.tre_m)} ({len(names)} fiducials)']
    refused = []
    if paired.fre_too_high:
        refused.append(f'FRE {_mm(paired.fre_m)} above {args.max_fre_mm:g} mm (check the '
                       'fiducial with the largest leave-one-out error)')
    if args.trajectory is not None:
        points = read_trajectory(args.trajectory)
        surface = read_surface(args.mesh, args.mesh_unit)
        icp = refine_icp(points, surface, paired.registration)
        print(f'ICP: {len(points)} points, {int(icp.inliers.sum())} inliers, RMS '
              f'{_mm(icp.rms_m)}, {icp.iterations} iterations'
              f'{"" if icp.converged else " (NOT converged)"}, correction '
              f'{_mm(icp.correction_m)} / {math.degrees(icp.correction_rad):.2f} deg')
        registration = icp.registration
        comments.append(f'ICP on {args.mesh} with {args.trajectory}: RMS {_mm(icp.rms_m)}, '
                        f'{int(icp.inliers.sum())}/{len(points)} inliers')
        if not icp.converged:
            refused.append(f'ICP did not converge in {icp.iterations} iterations')
    if refused and not args.force:
        print(f'{PROG}: refused: {"; ".join(refused)}; nothing written (--force writes it)',
              file=sys.stderr)
        return 1
    write_parameters(args.output, args.node, {'registration': registration.to_flat()},
                     comments, tool=PROG)
    print(f'wrote {args.node}.registration to {args.output}')
    return 0


def main(argv: list[str] | None = None,
         parser: argparse.ArgumentParser | None = None) -> int:
    """Run the command on ``argv`` with ``parser`` (default :func:`build_parser`'s)."""
    parser = parser or build_parser()
    args = parser.parse_args(argv)
    if (args.trajectory is None) != (args.mesh is None):
        parser.error('--trajectory and --mesh go together')
    return run_command(parser.prog, parser, args, lambda: PairedPointConfig(
        min_line_distance_m=args.min_line_distance_mm * 1e-3,
        max_fre_m=args.max_fre_mm * 1e-3), run)


if __name__ == '__main__':
    sys.exit(main())

"""Calibration procedures on the simulated rig, scripted as a rig team runs them on the real one.

    python -m em_tracker.sim.procedures --out /tmp/rig [--seed 1] [--no-noise]

The rig (:class:`SimulatedRig`): a :class:`~em_tracker.hw.sim_aurora.SimAurora` whose ground
truth (:class:`~em_tracker.hw.sim_aurora.SimGroundTruth`: the phantom's placement in the field
generator's frame, the sensor's mounting behind the tip, the Aurora's noise) is hidden from the
host. The host reads it as on the rig: ndicapi over the pty, and the node's
:class:`~em_tracker.hw.tracker_loop.TrackerLoop` validating and converting every frame. The
device clock is simulated and advanced one frame per poll, so a recording depends on the truth,
the motion and the seed only, never on the machine's load.

Motions are the tip's pose in the phantom frame (mm, NDI quaternion order); the simulated
Aurora turns them into the sensor's pose in the tracker frame. Tip frame as in
:mod:`em_tracker.core.calibration`: +y along the shaft towards the tip.

* :func:`record_pivot`: the tip rests in a divot on the phantom's lid while the hand sweeps the
  shaft +-30 deg in one plane, then in the perpendicular one, rolling it +-15 deg throughout
  (5 s, 200 frames): the sensor poses go to the CSV ``pivot_calibrate`` reads.
* :func:`record_fiducials`: with the calibrated ``tool_transform``, the tip is held 0.5 s in
  each of the 8 divots of the phantom box (:data:`FIDUCIALS`), the shaft 15 deg off the face's
  normal and wobbling +-3 deg; the mean tip position of each hold goes to the CSV
  ``register_phantom`` reads.
* :func:`rehearse`: both, with the two commands in between (what the command line runs);
  :func:`tool_errors` and :func:`registration_errors` compare what they wrote with the truth.

The phantom (phantom frame, mm) is a box around ``cgail_planner``'s default anatomy (x -30..33,
y -30..60, z -75..125 mm), 10 to 15 mm clear of it, lid at y = 75 mm, with the divots on its
lid, sides and ends (8, not coplanar, 60 to 130 mm from the centre).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import math
from pathlib import Path
import sys
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
import yaml

from em_tracker.cli import pivot_calibrate, register_phantom
from em_tracker.cli.files import write_fiducials, write_poses
from em_tracker.core.config import TrackerConfig
from em_tracker.core.errors import CalibrationError, DeviceError
from em_tracker.core.pose import Registration, TipPose
from em_tracker.core.registration import AURORA_ORIENTATION_RMS_RAD, AURORA_POSITION_RMS_M
from em_tracker.hw.aurora import AuroraSettings, NdiAurora
from em_tracker.hw.sim_aurora import PoseSource, SimAurora, SimGroundTruth
from em_tracker.hw.tracker_loop import TrackerLoop

FloatArray = NDArray[np.float64]

#: Frame rate of the simulated Aurora, Hz (the real one's).
FRAME_RATE_HZ = 40.0
#: Corners of the phantom box, mm (phantom frame).
BOX_MIN_MM = np.array([-45.0, -45.0, -90.0])
BOX_MAX_MM = np.array([50.0, 75.0, 140.0])
#: Centre of the phantom box, mm: where the registration error is quoted.
PHANTOM_CENTRE_MM = (BOX_MIN_MM + BOX_MAX_MM) / 2.0
#: The pivot divot on the lid, mm.
PIVOT_DIVOT_MM = np.array([5.0, 75.0, 25.0])


class Fiducial(NamedTuple):
    """A divot of the phantom box."""

    name: str
    position_mm: tuple[float, float, float]
    """Model position (phantom frame), mm."""
    normal: tuple[float, float, float]
    """Outward unit normal of its face: the pointer comes in against it."""


FIDUCIALS = (
    Fiducial('lid_1', (-35.0, 75.0, -80.0), (0.0, 1.0, 0.0)),
    Fiducial('lid_2', (40.0, 75.0, -80.0), (0.0, 1.0, 0.0)),
    Fiducial('lid_3', (40.0, 75.0, 130.0), (0.0, 1.0, 0.0)),
    Fiducial('lid_4', (-35.0, 75.0, 130.0), (0.0, 1.0, 0.0)),
    Fiducial('left', (-45.0, 15.0, 30.0), (-1.0, 0.0, 0.0)),
    Fiducial('right', (50.0, -20.0, -30.0), (1.0, 0.0, 0.0)),
    Fiducial('head', (0.0, -25.0, 140.0), (0.0, 0.0, 1.0)),
    Fiducial('foot', (10.0, 40.0, -90.0), (0.0, 0.0, -1.0)),
)
"""The phantom's fiducial divots (see the module docstring)."""

#: The Aurora 6DOF sensor's noise in :class:`SimGroundTruth` terms (0.48 mm / 0.30 deg RMS).
AURORA_NOISE = {'position_noise_mm': AURORA_POSITION_RMS_M * 1e3,
                'orientation_noise_deg': math.degrees(AURORA_ORIENTATION_RMS_RAD)}


def _wxyz(rot: Rotation) -> FloatArray:
    x, y, z, w = rot.as_quat(canonical=True)
    return np.array([w, x, y, z])


def _shaft_into(normal: Sequence[float]) -> Rotation:
    """Tip orientation with the shaft (+y) pointing into a face of outward ``normal``."""
    rot, _ = Rotation.align_vectors([-np.asarray(normal, dtype=float)], [[0.0, 1.0, 0.0]])
    return rot


def _across(normal: Sequence[float]) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors perpendicular to ``normal`` and to each other."""
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    seed = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, seed)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def hold(position_mm: Sequence[float], quat_wxyz: Sequence[float]) -> PoseSource:
    """A tip held still at one pose."""
    pos, quat = np.asarray(position_mm, dtype=float), np.asarray(quat_wxyz, dtype=float)
    return lambda t_s: (pos.copy(), quat.copy())


def pivot_motion(divot_mm: Sequence[float], normal: Sequence[float], duration_s: float, *,
                 sweep_deg: float = 30.0, roll_deg: float = 15.0) -> PoseSource:
    """The tip in a divot, the shaft swept to +``sweep_deg`` and -``sweep_deg`` off the
    normal in one plane during the first half of ``duration_s``, in the perpendicular plane
    during the second, and rolled +-``roll_deg`` about itself throughout."""
    divot = np.asarray(divot_mm, dtype=float)
    base = _shaft_into(normal)
    u1, u2 = _across(normal)
    sweep, roll = math.radians(sweep_deg), math.radians(roll_deg)

    def motion(t_s: float) -> tuple[FloatArray, FloatArray]:
        phase = min(max(t_s / duration_s, 0.0), 1.0)
        swing = sweep * math.sin(4.0 * math.pi * phase)
        axis = u1 if phase < 0.5 else u2
        turn = Rotation.from_rotvec(swing * axis) * base * Rotation.from_rotvec(
            [0.0, roll * math.sin(2.0 * math.pi * phase), 0.0])
        return divot.copy(), _wxyz(turn)
    return motion


def touch_motion(fiducial: Fiducial, *, tilt_deg: float = 15.0, wobble_deg: float = 3.0,
                 azimuth_rad: float = 0.0) -> PoseSource:
    """The tip held in a divot, the shaft ``tilt_deg`` off the face's normal (towards
    ``azimuth_rad`` about it) and wobbling +-``wobble_deg`` at 2 Hz, as a hand does."""
    u1, u2 = _across(fiducial.normal)
    lean = math.cos(azimuth_rad) * u1 + math.sin(azimuth_rad) * u2
    base = Rotation.from_rotvec(math.radians(tilt_deg) * lean) * _shaft_into(fiducial.normal)
    position = np.asarray(fiducial.position_mm, dtype=float)

    def motion(t_s: float) -> tuple[FloatArray, FloatArray]:
        w = 2.0 * math.pi * 2.0 * t_s
        wobble = math.radians(wobble_deg) * (math.sin(w) * u1 + math.cos(w) * u2)
        return position.copy(), _wxyz(Rotation.from_rotvec(wobble) * base)
    return motion


class SimulatedRig:
    """The bench: a simulated Aurora with a hidden ground truth on a pty, read by the host's
    ndicapi + :class:`TrackerLoop` on a simulated clock advanced one frame per poll.

    Args:
        truth: the hidden placement, mounting and noise.
        link_path: optional stable symlink to the pty (as ``sim_aurora --link``).
    """

    def __init__(self, truth: SimGroundTruth, *, link_path: str | None = None) -> None:
        self.truth = truth
        self.time_s = 0.0
        self.aurora = SimAurora(hold((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),
                                frame_rate_hz=FRAME_RATE_HZ, link_path=link_path,
                                clock=lambda: self.time_s, truth=truth).start()

    def __enter__(self) -> SimulatedRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the simulated Aurora."""
        self.aurora.close()

    def record(self, motion: PoseSource, frames: int,
               tool_transform: Registration | None = None) -> list[TipPose]:
        """Connect (INIT ... TSTART), poll ``frames`` consecutive frames while the tip follows
        ``motion`` (time from TSTART), disconnect (TSTOP).

        Returns:
            What the host's loop produced for each frame, tracker frame (identity
            registration): the sensor's pose, or the tip's with ``tool_transform``.

        Raises:
            DeviceError: the host did not start tracking, or lost or rejected a frame.
        """
        self.aurora.pose_source = motion
        poses: list[TipPose] = []
        config = TrackerConfig(port=self.aurora.port, rate_hz=FRAME_RATE_HZ, poll_mode='clock',
                               tool_transform=tool_transform or Registration.identity())
        loop = TrackerLoop(NdiAurora(AuroraSettings(port=self.aurora.port)), config,
                           lambda pose, _t: poses.append(pose))
        try:
            loop.step(self.time_s)  # connects: TSTART at this clock time
            start = self.time_s
            for k in range(frames if loop.tracking else 0):
                self.time_s = start + (k + 0.5) / FRAME_RATE_HZ  # mid-frame k
                loop.step(self.time_s)
        finally:
            loop.stop()
            self.time_s += 1.0  # (the team moves to the next step)
        if len(poses) != frames:
            raise DeviceError(f'expected {frames} valid frames from the simulated Aurora, found '
                              f'{len(poses)} (last error: {loop.health.last_error or "none"})')
        return poses


def record_pivot(rig: SimulatedRig, path: Path, *, frames: int = 200,
                 divot_mm: Sequence[float] = tuple(PIVOT_DIVOT_MM), sweep_deg: float = 30.0,
                 roll_deg: float = 15.0) -> Path:
    """Record a pivoting motion (:func:`pivot_motion`) into the CSV ``pivot_calibrate`` reads
    (the sensor's poses, tracker frame); returns ``path``."""
    motion = pivot_motion(divot_mm, (0.0, 1.0, 0.0), frames / FRAME_RATE_HZ,
                          sweep_deg=sweep_deg, roll_deg=roll_deg)
    poses = rig.record(motion, frames)
    write_poses(path, np.array([p.position_m for p in poses]),
                np.array([p.quat_xyzw for p in poses]),
                [f'simulated rig: pivot in the divot at {[float(v) for v in divot_mm]} mm '
                 f'(phantom frame), +-{sweep_deg:g} deg in two planes, +-{roll_deg:g} deg roll, '
                 f'{frames} frames'])
    return path


def record_fiducials(rig: SimulatedRig, path: Path, tool_transform: Registration, *,
                     fiducials: Sequence[Fiducial] = FIDUCIALS,
                     frames_per_touch: int = 20) -> Path:
    """Touch every fiducial with the calibrated tip (:func:`touch_motion`, the lean turning
    from one divot to the next) and write the mean tip position of each hold (tracker frame)
    with its model position into the CSV ``register_phantom`` reads; returns ``path``."""
    tracker = []
    for i, fiducial in enumerate(fiducials):
        motion = touch_motion(fiducial, azimuth_rad=2.0 * math.pi * i / len(fiducials))
        poses = rig.record(motion, frames_per_touch, tool_transform)
        tracker.append(np.mean([p.position_m for p in poses], axis=0))
    write_fiducials(path, [f.name for f in fiducials],
                    np.array([f.position_mm for f in fiducials]) * 1e-3, np.array(tracker),
                    [f'simulated rig: each divot held {frames_per_touch} frames with the '
                     'calibrated tip; model in the phantom frame, tracker in the aurora frame'])
    return path


def example_truth(seed: int, *, noise: bool = True) -> SimGroundTruth:
    """A hidden truth drawn from ``seed``: the phantom turned at random with its centre 230 to
    330 mm in front of the field generator (the Aurora's cube volume), the sensor 10 to 15 mm
    behind the tip on the shaft axis, its z along the shaft (NDI 6DOF sensors), rolled at
    random and tilted up to 5 deg; with the Aurora's noise (:data:`AURORA_NOISE`) unless
    ``noise`` is false. The noise uses ``seed`` too."""
    rng = np.random.default_rng(seed)
    rot = Rotation.random(random_state=rng)
    centre = np.array([rng.uniform(-60.0, 60.0), rng.uniform(-60.0, 60.0),
                       rng.uniform(-330.0, -230.0)])
    placement = np.eye(4)
    placement[:3, :3] = rot.as_matrix()
    placement[:3, 3] = centre - rot.apply(PHANTOM_CENTRE_MM)
    axis = rng.normal(size=3)
    mount = (Rotation.from_rotvec(math.radians(rng.uniform(0.0, 5.0)) * axis
                                  / np.linalg.norm(axis))
             * Rotation.from_euler('z', rng.uniform(0.0, 2.0 * math.pi))
             * Rotation.from_euler('x', math.pi / 2.0))  # tip +y -> sensor +z
    mounting = np.eye(4)
    mounting[:3, :3] = mount.as_matrix()
    mounting[:3, 3] = mount.apply([0.0, rng.uniform(10.0, 15.0), 0.0])  # tip offset, sensor frame
    return SimGroundTruth(phantom_in_tracker=placement, tip_in_sensor=mounting, seed=seed,
                          **(AURORA_NOISE if noise else {}))


class ToolErrors(NamedTuple):
    """How far a ``tool_transform`` is from the hidden mounting."""

    tip_offset_mm: float
    """``|t_found - t_true|`` of ``T_sensor_tip`` (the tip offset, sensor frame), mm."""
    shaft_axis_deg: float
    """Angle between the found and the true tip +y axis (the shaft), sensor frame, deg."""


def tool_errors(truth: SimGroundTruth, tool_transform: Registration) -> ToolErrors:
    """Compare ``pivot_calibrate``'s tool transform with the hidden mounting."""
    true, found = truth.tool_transform_m(), tool_transform.matrix
    cos_axis = float(np.clip(found[:3, 1] @ true[:3, 1], -1.0, 1.0))
    return ToolErrors(tip_offset_mm=float(np.linalg.norm(found[:3, 3] - true[:3, 3])) * 1e3,
                      shaft_axis_deg=math.degrees(math.acos(cos_axis)))


class RegistrationErrors(NamedTuple):
    """How far a ``registration`` is from the hidden placement."""

    centre_mm: float
    """Error at :data:`PHANTOM_CENTRE_MM`: where the found registration maps the tracker point
    that is truly the centre, mm."""
    rotation_deg: float
    """Rotation angle of ``R_found R_true^T``, deg."""


def registration_errors(truth: SimGroundTruth, registration: Registration
                        ) -> RegistrationErrors:
    """Compare ``register_phantom``'s registration with the hidden placement."""
    true, found = truth.registration_m(), registration.matrix
    centre = np.append(PHANTOM_CENTRE_MM * 1e-3, 1.0)
    mapped = found @ np.linalg.solve(true, centre)
    turn = Rotation.from_matrix(found[:3, :3] @ true[:3, :3].T)
    return RegistrationErrors(centre_mm=float(np.linalg.norm(mapped[:3] - centre[:3])) * 1e3,
                              rotation_deg=math.degrees(turn.magnitude()))


def read_calibration(path: Path, node: str = 'aurora') -> dict[str, Registration]:
    """The transforms in a parameters file written by the commands (name -> transform)."""
    params = yaml.safe_load(path.read_text())[node]['ros__parameters']
    return {name: Registration.from_flat(params[name], name=name)
            for name in ('registration', 'tool_transform') if name in params}


class Rehearsal(NamedTuple):
    """What :func:`rehearse` produced."""

    pivot_csv: Path
    fiducials_csv: Path
    params: Path
    """The parameters file both commands wrote (``aurora``: ``tool_transform``,
    ``registration``)."""
    tool_transform: Registration
    registration: Registration


def rehearse(truth: SimGroundTruth, out_dir: Path, *, pivot_frames: int = 200,
             frames_per_touch: int = 20, link_path: str | None = None) -> Rehearsal:
    """The whole calibration on the simulated rig, as on the real one: record the pivot, run
    ``pivot_calibrate``, touch the fiducials with its tool transform, run
    ``register_phantom``; every file in ``out_dir``.

    Raises:
        CalibrationError: a command exited non-zero (its message is on stderr).
        DeviceError: see :meth:`SimulatedRig.record`.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    params = out_dir / 'calibration.yaml'
    params.unlink(missing_ok=True)
    with SimulatedRig(truth, link_path=link_path) as rig:
        pivot_csv = record_pivot(rig, out_dir / 'pivot.csv', frames=pivot_frames)
        status = pivot_calibrate.main([str(pivot_csv), '-o', str(params)])
        if status != 0:
            raise CalibrationError(f'pivot_calibrate: expected exit status 0, found {status}')
        tool = read_calibration(params)['tool_transform']
        fiducials_csv = record_fiducials(rig, out_dir / 'fiducials.csv', tool,
                                         frames_per_touch=frames_per_touch)
        status = register_phantom.main([str(fiducials_csv), '-o', str(params)])
        if status != 0:
            raise CalibrationError(f'register_phantom: expected exit status 0, found {status}')
    return Rehearsal(pivot_csv, fiducials_csv, params, tool,
                     read_calibration(params)['registration'])


def main(argv: Sequence[str] | None = None) -> int:
    """Rehearse the calibration on a simulated rig with a hidden truth; print the errors."""
    parser = argparse.ArgumentParser(prog='python -m em_tracker.sim.procedures',
                                     description=main.__doc__)
    parser.add_argument('--out', type=Path, required=True,
                        help='directory for pivot.csv, fiducials.csv and calibration.yaml')
    parser.add_argument('--seed', type=int, default=1,
                        help='seed of the hidden truth and the noise (default: %(default)s)')
    parser.add_argument('--no-noise', action='store_true', help='a noiseless Aurora')
    args = parser.parse_args(argv)
    truth = example_truth(args.seed, noise=not args.no_noise)
    try:
        result = rehearse(truth, args.out)
    except (CalibrationError, DeviceError) as exc:
        print(f'procedures: error: {exc}', file=sys.stderr)
        return 2
    tool = tool_errors(truth, result.tool_transform)
    reg = registration_errors(truth, result.registration)
    print(f'recovered vs hidden: tip offset {tool.tip_offset_mm:.3f} mm, shaft axis '
          f'{tool.shaft_axis_deg:.2f} deg; registration {reg.centre_mm:.3f} mm at the phantom '
          f'centre, {reg.rotation_deg:.3f} deg')
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""Tool calibration: pivot calibration of the tip offset and the sensor -> tip transform.

Frames (metres): the Aurora reports the sensor pose in the tracker frame ``aurora`` as
``(R_i, t_i)`` (sensor -> aurora). The tip frame is fixed to the catheter tip:

* origin at the tip (the point that rests in the divot while pivoting);
* **+y along the shaft, pointing towards the tip** (the catheter heading: the planner and the
  GUI take the tip's +y axis as the heading);
* x, z: the sensor's x, z turned by the smallest rotation that takes the sensor's +y onto the
  shaft axis (the roll about the shaft is not observable from a pivot and is not used).

The tool transform ``T_sensor_tip`` maps tip-frame points to the sensor frame; its translation
is the tip offset. The tip pose in the phantom is then ``T_phantom_aurora @ T_aurora_sensor @
T_sensor_tip``.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from em_tracker.core.errors import CalibrationError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PivotConfig:
    """Acceptance limits of :func:`pivot_calibration`."""

    min_spread_rad: float = math.radians(5.0)
    """Smallest rotation spread accepted, rad; (0, pi/2]. The spread is ``s_min / sqrt(N)``
    with ``s_min`` the smallest singular value of the stacked ``R_i - mean(R)``: about the RMS
    tilt, across the poses, about axes perpendicular to the worst-determined direction of the
    offset. The offset's standard error is about ``sigma / (spread sqrt(N))`` with ``sigma``
    the per-axis position noise (0.28 mm for the Aurora): 0.6 mm for 30 poses at 5 deg, 0.17
    mm at the ~17 deg of a +-30 deg pivot."""
    max_residual_rms_m: float = 1.5e-3
    """A residual RMS above this raises ``residual_too_high``, m; (0, 0.1]. Aurora noise alone
    gives about 0.5 mm; more means the tip slipped in the divot or the tool is not rigid."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_spread_rad) and 0.0 < self.min_spread_rad <= math.pi / 2):
            raise ValueError(f'min_spread_rad must be in (0, pi/2], found '
                             f'{self.min_spread_rad!r}')
        if not (math.isfinite(self.max_residual_rms_m) and 0.0 < self.max_residual_rms_m <= 0.1):
            raise ValueError(f'max_residual_rms_m must be in (0, 0.1], found '
                             f'{self.max_residual_rms_m!r}')


@dataclass(frozen=True)
class PivotResult:
    """Outcome of :func:`pivot_calibration`."""

    tip_offset_m: FloatArray
    """(3,) sensor -> tip translation in the sensor frame, m."""
    pivot_m: FloatArray
    """(3,) pivot point (the divot) in the tracker frame, m."""
    residual_rms_m: float
    """RMS over the poses of ``|R_i p_tool + t_i - p_pivot|``, m."""
    spread_rad: float
    """Rotation spread of the poses (see :attr:`PivotConfig.min_spread_rad`), rad."""
    residual_too_high: bool
    """``residual_rms_m > max_residual_rms_m``: re-record before using the offset."""


def _as_poses(rotations: object, translations_m: object) -> tuple[FloatArray, FloatArray]:
    rot = np.asarray(rotations, dtype=float)
    pos = np.asarray(translations_m, dtype=float)
    if rot.ndim != 3 or rot.shape[1:] != (3, 3) or pos.shape != (len(rot), 3):
        raise CalibrationError(f'expected (N, 3, 3) rotations and (N, 3) translations, found '
                               f'{rot.shape} and {pos.shape}')
    if not (np.all(np.isfinite(rot)) and np.all(np.isfinite(pos))):
        raise CalibrationError('expected finite poses, found NaN/inf')
    err = np.abs(np.einsum('nij,nkj->nik', rot, rot) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((err > 1e-6) | (np.linalg.det(rot) < 0))
    if bad.size:
        raise CalibrationError(f'expected rotation matrices (orthonormal, det +1), found pose '
                               f'{int(bad[0])} is not')
    return rot, pos


def rotation_spread(rotations: FloatArray) -> float:
    """``s_min(stack(R_i - mean R)) / sqrt(N)``: see :attr:`PivotConfig.min_spread_rad`."""
    centred = rotations - rotations.mean(axis=0)
    s = np.linalg.svd(centred.reshape(-1, 3), compute_uv=False)
    # small angles: |(R_i - R_mean) x| ~ tilt angle perpendicular to x; report it as an angle
    return float(math.asin(min(1.0, float(s[-1]) / math.sqrt(len(rotations)))))


def pivot_calibration(rotations: object, translations_m: object,
                      config: PivotConfig | None = None) -> PivotResult:
    """Tip offset and pivot point from a pivoting motion, by linear least squares.

    Each pose keeps the tip on the fixed pivot: ``R_i p_tool + t_i = p_pivot``, stacked as
    ``[R_i  -I] [p_tool; p_pivot] = -t_i`` and solved in the least-squares sense.

    Args:
        rotations: (N, 3, 3) sensor orientations (sensor -> tracker), N >= 3.
        translations_m: (N, 3) sensor positions in the tracker frame, m.
        config: acceptance limits (defaults: :class:`PivotConfig`).

    Raises:
        CalibrationError: bad or non-finite poses, fewer than 3, or a rotation spread below
            ``min_spread_rad`` (the offset is then not determined); one line.
    """
    cfg = config or PivotConfig()
    rot, pos = _as_poses(rotations, translations_m)
    if len(rot) < 3:
        raise CalibrationError(f'expected at least 3 pivoting poses, found {len(rot)}')
    spread = rotation_spread(rot)
    if spread < cfg.min_spread_rad:
        raise CalibrationError(
            f'pivoting poses turn too little to fix the tip offset: expected a rotation '
            f'spread of at least {math.degrees(cfg.min_spread_rad):.1f} deg, found '
            f'{math.degrees(spread):.2f} deg; pivot the tool further (+-20..30 deg) in both '
            'directions')
    n = len(rot)
    a = np.zeros((3 * n, 6))
    a[:, :3] = rot.reshape(-1, 3)
    a[:, 3:] = -np.tile(np.eye(3), (n, 1))
    sol = np.asarray(np.linalg.lstsq(a, -pos.reshape(-1), rcond=None)[0], dtype=np.float64)
    offset, pivot = sol[:3], sol[3:]
    resid = np.linalg.norm(rot @ offset + pos - pivot, axis=1)
    rms = float(np.sqrt(np.mean(resid ** 2)))
    return PivotResult(tip_offset_m=offset, pivot_m=pivot, residual_rms_m=rms,
                       spread_rad=spread, residual_too_high=rms > cfg.max_residual_rms_m)


def sensor_to_tip_transform(tip_offset_m: object, shaft_axis: object) -> FloatArray:
    """The tool transform ``T_sensor_tip`` (4x4): tip frame -> sensor frame.

    Tip frame (see the module docstring): origin at the tip, +y along the shaft towards the
    tip, x/z the sensor's turned by the smallest rotation taking sensor +y onto the shaft.

    Args:
        tip_offset_m: (3,) sensor -> tip translation in the sensor frame, m
            (:attr:`PivotResult.tip_offset_m`).
        shaft_axis: (3,) direction of the shaft towards the tip, sensor frame (any length > 0);
            for a sensor on the shaft axis behind the tip, the offset's own direction.

    Raises:
        CalibrationError: non-finite values or a zero shaft axis.
    """
    offset = np.asarray(tip_offset_m, dtype=float)
    axis = np.asarray(shaft_axis, dtype=float)
    if offset.shape != (3,) or axis.shape != (3,) or not (np.all(np.isfinite(offset))
                                                          and np.all(np.isfinite(axis))):
        raise CalibrationError(f'expected finite 3-vectors for the offset and the shaft axis, '
                               f'found {offset.tolist()} and {axis.tolist()}')
    norm = float(np.linalg.norm(axis))
    if norm < 1e-9:
        raise CalibrationError(f'expected a non-zero shaft axis, found {axis.tolist()}')
    y_axis = axis / norm
    if float(y_axis[1]) < -1.0 + 1e-12:  # antiparallel: turn half a turn about z
        rot = np.diag([-1.0, -1.0, 1.0])
    else:
        rot, _ = Rotation.align_vectors(y_axis[None, :], np.array([[0.0, 1.0, 0.0]]))
        rot = rot.as_matrix()
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = offset
    return out

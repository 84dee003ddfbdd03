"""Pose maths of the tracker: NDI -> ROS conventions, registration, validation.

Conventions: the Aurora reports the sensor pose in the field-generator frame ``aurora`` as a
quaternion in NDI order ``(q0, qx, qy, qz)`` (scalar first) and a position in mm. ROS wants
``(x, y, z, w)`` and metres. The registration ``aurora -> phantom`` is a rigid transform
``T_phantom_aurora`` (maps points in the aurora frame to the phantom frame); the tool transform
``T_sensor_tip`` maps points in the tip frame (origin at the tip, +y along the shaft towards the
tip; see :mod:`em_tracker.core.calibration`) to the sensor frame. The published tip pose is
``T_phantom_aurora @ T_aurora_sensor @ T_sensor_tip`` (:func:`tip_pose_in_phantom`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math

import numpy as np
from scipy.spatial.transform import Rotation

from cgail_node_utils.rotations import matrix_to_quat, quat_to_matrix

MM_TO_M = 1e-3


def ndi_quat_to_ros(quat_wxyz: Sequence[float] | np.ndarray) -> np.ndarray:
    """Reorder an NDI quaternion ``(q0, qx, qy, qz)`` to ROS ``(x, y, z, w)``."""
    w, x, y, z = (float(v) for v in quat_wxyz)
    return np.array([x, y, z, w])


def mm_to_m(values_mm: Sequence[float] | np.ndarray) -> np.ndarray:
    """Convert millimetres to metres."""
    return np.asarray(values_mm, dtype=float) * MM_TO_M


def quat_xyzw_to_matrix(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion in ROS order ``(x, y, z, w)`` (scipy ``Rotation``;
    one finite quaternion: :mod:`cgail_node_utils.rotations`, the same bits, faster)."""
    arr = np.asarray(q, dtype=float)
    if arr.shape == (4,) and np.isfinite(arr).all():
        return np.array(quat_to_matrix(*arr.tolist()))
    return np.asarray(Rotation.from_quat(arr).as_matrix())


def matrix_to_quat_xyzw(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix (scipy
    ``Rotation``; ``rot`` must be a rotation, it is not re-orthogonalised; one finite matrix:
    :mod:`cgail_node_utils.rotations`, the same bits, faster)."""
    arr = np.asarray(rot, dtype=float)
    if arr.shape == (3, 3) and np.isfinite(arr).all():
        return np.array(matrix_to_quat(arr.tolist()))
    return np.asarray(Rotation.from_matrix(arr, assume_valid=True).as_quat(canonical=True))


def _rigid(matrix: object, name: str) -> np.ndarray:
    """``matrix`` as a float 4x4 array, checked to be a rigid transform.

    Raises:
        ValueError: not a finite 4x4 matrix, last row not ``[0, 0, 0, 1]``, or a rotation
            block that is not orthonormal with det +1; the message starts with ``name``.
    """
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f'{name} must be a finite 4x4 matrix, found {matrix!r}')
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        raise ValueError(f'{name} last row must be [0, 0, 0, 1], found {m[3]}')
    rot = m[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise ValueError(f'{name} rotation must be orthonormal with det +1, '
                         f'found {rot.tolist()}')
    return m


@dataclass(frozen=True)
class Registration:
    """A rigid transform as a 4x4 homogeneous matrix (metres): the registration ``aurora ->
    phantom`` (``T_phantom_aurora``), and in the same form the tool transform ``sensor -> tip``
    (``T_sensor_tip``).

    Attributes:
        matrix: the transform; rotation block orthonormal with det +1, last row 0 0 0 1.
    """

    matrix: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, 'matrix', _rigid(self.matrix, 'registration'))

    @classmethod
    def identity(cls) -> Registration:
        """The identity registration (phantom frame = field-generator frame)."""
        return cls(np.eye(4))

    @classmethod
    def from_flat(cls, values: Sequence[float], *, name: str = 'registration') -> Registration:
        """Build from 16 row-major values (4x4) or 7 values ``[tx ty tz qx qy qz qw]`` (m).

        Args:
            values: the 16 or 7 values.
            name: what the values are (the parameter's name), for the error messages.

        Raises:
            ValueError: wrong length, non-unit quaternion or non-rigid matrix.
        """
        vals = [float(v) for v in values]
        if len(vals) == 16:
            return cls(_rigid(np.array(vals).reshape(4, 4), name))
        if len(vals) == 7:
            q = np.array(vals[3:])
            norm = float(np.linalg.norm(q))
            if not math.isfinite(norm) or abs(norm - 1.0) > 1e-3:
                raise ValueError(f'{name} quaternion must have unit norm, found {norm!r}')
            m = np.eye(4)
            m[:3, :3] = quat_xyzw_to_matrix(q / norm)
            m[:3, 3] = vals[:3]
            return cls(_rigid(m, name))
        raise ValueError(f'{name} must have 16 values (4x4 row-major) or 7 values '
                         f'(tx ty tz qx qy qz qw), found {len(vals)}')

    def apply(self, position_m: np.ndarray, quat_xyzw: np.ndarray) -> tuple[np.ndarray,
                                                                             np.ndarray]:
        """Map a pose from the aurora frame to the phantom frame."""
        rot = self.matrix[:3, :3]
        pos = rot @ np.asarray(position_m, dtype=float) + self.matrix[:3, 3]
        quat = matrix_to_quat_xyzw(rot @ quat_xyzw_to_matrix(quat_xyzw))
        return pos, quat

    def inverse(self) -> Registration:
        """The inverse transform (``phantom -> aurora`` of a registration)."""
        rot = self.matrix[:3, :3]
        m = np.eye(4)
        m[:3, :3] = rot.T
        m[:3, 3] = -rot.T @ self.matrix[:3, 3]
        return Registration(m)

    def to_flat(self) -> list[float]:
        """The 7 values ``[tx ty tz qx qy qz qw]`` (m, quaternion with ``qw >= 0``) that
        :meth:`from_flat` reads back: the form of the ``registration`` parameter."""
        quat = matrix_to_quat_xyzw(self.matrix[:3, :3])
        return [float(v) for v in (*self.matrix[:3, 3], *quat)]


#: Orientation variance of :func:`pose_covariance`, rad^2: the Aurora reports no orientation
#: uncertainty, so the orientation is marked as not estimated with a variance far above any real
#: one (a fusing filter then gives it no weight).
ORIENTATION_VARIANCE_UNKNOWN_RAD2 = 1e6


def pose_covariance(rms_error_m: float) -> np.ndarray:
    """The 6x6 covariance of a tip pose from the Aurora's RMS error (``geometry_msgs``
    layout: x, y, z, then rotation about X, Y, Z; row-major when flattened).

    Model: the RMS error NDI reports with each transform (the residual of its field-model fit)
    is taken as the RMS of the 3-D position error, ``E|e|^2 = rms^2``, isotropic with
    uncorrelated axes: each position axis has variance ``rms^2 / 3``. An isotropic covariance is
    unchanged by the registration's rotation, so it holds in the phantom frame too. Not included:
    the registration's own error, and the tip offset's lever arm on the (unreported) orientation
    error; the orientation block is :data:`ORIENTATION_VARIANCE_UNKNOWN_RAD2` on the diagonal.

    Raises:
        ValueError: ``rms_error_m`` negative or not finite.
    """
    if not (math.isfinite(rms_error_m) and rms_error_m >= 0.0):
        raise ValueError(f'expected a finite, non-negative RMS error, found {rms_error_m!r} m')
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * rms_error_m ** 2 / 3.0
    cov[3:, 3:] = np.eye(3) * ORIENTATION_VARIANCE_UNKNOWN_RAD2
    return cov


@dataclass(frozen=True)
class TipPose:
    """A validated tip pose in the phantom frame, SI units.

    Attributes:
        position_m: (3,) position, m.
        quat_xyzw: (4,) unit quaternion, ROS order.
        rms_error_m: RMS fit error reported by the tracker, m.
    """

    position_m: np.ndarray
    quat_xyzw: np.ndarray
    rms_error_m: float


def tip_pose_in_phantom(sensor_position_m: np.ndarray, sensor_quat_xyzw: np.ndarray,
                        registration: Registration, tool_transform: Registration
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The tip pose in the phantom frame, ``T_phantom_aurora @ T_aurora_sensor @ T_sensor_tip``.

    With ``(R_reg, t_reg)`` the registration, ``(R_s, p_s)`` the sensor pose in the aurora
    frame and ``(R_tool, t_tool)`` the tool transform: position ``R_reg (p_s + R_s t_tool) +
    t_reg``, orientation ``R_reg R_s R_tool``.

    Args:
        sensor_position_m: (3,) sensor position in the aurora frame, m.
        sensor_quat_xyzw: (4,) unit quaternion of the sensor in the aurora frame, ROS order.
        registration: ``aurora -> phantom``.
        tool_transform: ``sensor -> tip`` (identity: the sensor is the tip).

    Returns:
        ``(position_m, quat_xyzw)`` of the tip in the phantom frame, ``qw >= 0``.
    """
    rot_s = quat_xyzw_to_matrix(sensor_quat_xyzw)
    rot_reg, t_reg = registration.matrix[:3, :3], registration.matrix[:3, 3]
    rot_tool, t_tool = tool_transform.matrix[:3, :3], tool_transform.matrix[:3, 3]
    position = rot_reg @ (np.asarray(sensor_position_m, dtype=float) + rot_s @ t_tool) + t_reg
    return position, matrix_to_quat_xyzw(rot_reg @ rot_s @ rot_tool)


def convert_sample(quat_wxyz: Sequence[float], position_mm: Sequence[float], error_mm: float,
                   registration: Registration, *, max_abs_position_m: float,
                   tool_transform: Registration | None = None) -> TipPose:
    """Turn one NDI transform into a :class:`TipPose` of the tip in the phantom frame.

    Args:
        quat_wxyz: NDI quaternion (q0, qx, qy, qz).
        position_mm: position in the field-generator frame, mm.
        error_mm: RMS error, mm.
        registration: ``aurora -> phantom``.
        max_abs_position_m: reject sensor positions farther than this from the field
            generator, m.
        tool_transform: ``sensor -> tip``; ``None`` is the identity (the sensor pose).

    Raises:
        ValueError: NaN/inf values, a quaternion far from unit norm, or a position outside the
            plausible volume; the message names the value found and what was expected.
    """
    # (the checks on plain floats, once per tracker frame: numpy's reductions and norm on 3 and 4
    # values cost more than the sample's arithmetic; they only decide pass or fail, and the
    # norm is the one np.linalg.norm computes, sqrt of the dot)
    q = np.asarray(quat_wxyz, dtype=float)
    p = np.asarray(position_mm, dtype=float)
    if q.shape != (4,) or p.shape != (3,):
        raise ValueError(f'expected 4 quaternion and 3 position values, found {q.shape}, '
                         f'{p.shape}')
    q_list, p_list = q.tolist(), p.tolist()
    if not (all(map(math.isfinite, q_list)) and all(map(math.isfinite, p_list))
            and math.isfinite(error_mm)):
        raise ValueError(f'expected finite pose values, found q={q_list} '
                         f'p={p_list} error={error_mm!r}')
    norm = math.sqrt(float(q @ q))
    if abs(norm - 1.0) > 0.01:
        raise ValueError(f'expected a unit quaternion (|q| within 0.01 of 1), found |q|={norm}')
    p_m = mm_to_m(p)
    if max(map(abs, p_m.tolist())) > max_abs_position_m:
        raise ValueError(f'expected |x|,|y|,|z| <= {max_abs_position_m} m, found '
                         f'{p_m.tolist()}')
    if error_mm < 0:
        raise ValueError(f'expected a non-negative RMS error, found {error_mm!r} mm')
    tool = Registration.identity() if tool_transform is None else tool_transform
    pos, quat = tip_pose_in_phantom(p_m, ndi_quat_to_ros(q / norm), registration, tool)
    return TipPose(position_m=pos, quat_xyzw=quat, rms_error_m=float(error_mm) * MM_TO_M)

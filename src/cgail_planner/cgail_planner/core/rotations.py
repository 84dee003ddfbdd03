"""Rotations of the planner package: quaternions, rotation vectors and pose checks.

All of it goes through :class:`scipy.spatial.transform.Rotation`, except one rotation's
quaternion <-> matrix, which :mod:`cgail_node_utils.rotations` computes bit-identically in
plain floats (a tenth of the time, once per message); quaternions are in ROS order
``(x, y, z, w)``, returned with ``w >= 0``. Inputs from outside (messages, files) are checked
here and refused with :class:`~cgail_planner.core.errors.InvalidInputError`. (The numba kernels
write their few rotation products out; ``test_ftl_model.py`` holds them equal to these.)
"""

from __future__ import annotations

from collections.abc import Sequence
import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cgail_node_utils.rotations import matrix_to_quat, quat_to_matrix
from cgail_planner.core.errors import InvalidInputError

FloatArray = NDArray[np.float64]

#: Largest deviation from a unit norm (quaternions) or from orthogonality (matrices) accepted.
UNIT_TOLERANCE = 1e-3


def quaternion_to_matrix(q: Sequence[float] | FloatArray) -> FloatArray:
    """(3, 3) rotation matrix of a unit quaternion ``(x, y, z, w)`` (normalised first).

    Raises:
        InvalidInputError: not 4 finite values, or a norm not within 1e-3 of 1.
    """
    arr = np.asarray(q, dtype=np.float64).reshape(-1)
    if arr.shape != (4,) or not np.isfinite(arr).all():
        raise InvalidInputError(f"orientation must be a unit quaternion (x, y, z, w), found "
                                f"{arr.tolist()}")
    n = float(np.linalg.norm(arr))
    if abs(n - 1.0) > UNIT_TOLERANCE:
        raise InvalidInputError(f"orientation must be a unit quaternion, found {arr.tolist()} "
                                f"(norm {n:.4g})")
    return np.array(quat_to_matrix(*(arr / n).tolist()))  # = Rotation.from_quat(.).as_matrix()


def pose_from_quaternion(position: Sequence[float], q: Sequence[float]
                         ) -> tuple[FloatArray, FloatArray]:
    """``(position (3,), rotation (3, 3))`` of a position and a unit quaternion ``(x, y, z, w)``:
    :func:`quaternion_to_matrix` then :func:`validate_pose`, the same arrays bit for bit.

    A message's pose is converted and checked once per message in two nodes (planner and
    operator, 40 Hz each); on one pose numpy's array set-up dominates, so the checks of finite
    values and of a proper rotation run on plain floats here (they only decide pass or fail),
    and only the quaternion's norm stays numpy's (BLAS's dot, whose rounding the rotation
    depends on). Anything but 3 + 4 finite values takes the general path, for its errors.

    Raises:
        InvalidInputError: as :func:`quaternion_to_matrix` and :func:`validate_pose`.
    """
    if len(position) == 3 and len(q) == 4:
        px, py, pz = position
        x, y, z, w = q
        isfinite = math.isfinite
        if (isfinite(px) and isfinite(py) and isfinite(pz) and isfinite(x) and isfinite(y)
                and isfinite(z) and isfinite(w)):
            arr = np.array((x, y, z, w), dtype=np.float64)
            n = math.sqrt(float(arr @ arr))  # = np.linalg.norm(arr), the same bits
            if abs(n - 1.0) <= UNIT_TOLERANCE:
                rows = quat_to_matrix(x / n, y / n, z / n, w / n)
                if _proper_rotation(rows):
                    return (np.array((px, py, pz), dtype=np.float64),
                            np.array(rows, dtype=np.float64))
    return validate_pose(np.asarray(position, dtype=np.float64), quaternion_to_matrix(q))


def _proper_rotation(m: Sequence[Sequence[float]]) -> bool:
    """Whether the 3 rows ``m`` pass :func:`validate_pose`'s test: ``|m^T m - I| <=``
    :data:`UNIT_TOLERANCE` everywhere and ``det(m) >= 0`` (plain floats)."""
    (a, b, c), (d, e, f), (g, h, i) = m
    cols = ((a, d, g), (b, e, h), (c, f, i))
    for j in range(3):
        u = cols[j]
        for k in range(j, 3):
            v = cols[k]
            dot = u[0] * v[0] + u[1] * v[1] + u[2] * v[2]
            if not abs(dot - (1.0 if j == k else 0.0)) <= UNIT_TOLERANCE:
                return False
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) >= 0.0


def matrix_to_quaternion(r: FloatArray) -> FloatArray:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix, or ``(N, 4)`` of
    ``(N, 3, 3)``. ``r`` must be a rotation (as every pose here is: checked or composed of
    rotations); it is not re-orthogonalised (scipy's ``assume_valid``, 3x faster)."""
    if isinstance(r, np.ndarray) and r.shape == (3, 3) and np.isfinite(r).all():
        return np.array(matrix_to_quat(r.tolist()))  # one rotation: the same bits, faster
    return np.asarray(Rotation.from_matrix(np.asarray(r, dtype=np.float64), assume_valid=True)
                      .as_quat(canonical=True), dtype=np.float64)


def rotvec_to_matrix(w: FloatArray) -> FloatArray:
    """(3, 3) rotation matrix of the rotation vector ``w`` (axis times angle, rad)."""
    return np.asarray(Rotation.from_rotvec(np.asarray(w, dtype=np.float64)).as_matrix(),
                      dtype=np.float64)


def rotate_onto(a: FloatArray, b: FloatArray) -> FloatArray:
    """The smallest rotation (3, 3) taking unit vector ``a`` onto unit vector ``b``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return np.eye(3)
    angle = math.atan2(s, float(a @ b))
    return rotvec_to_matrix(axis / s * angle)


def validate_pose(position: FloatArray, rotation: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Check a tip pose: a finite (3,) position and a proper rotation matrix (tolerance 1e-3).

    Raises:
        InvalidInputError: naming what is wrong.
    """
    p = np.asarray(position, dtype=np.float64)
    r = np.asarray(rotation, dtype=np.float64)
    if p.shape != (3,) or r.shape != (3, 3):
        raise InvalidInputError(f"tip pose must be a (3,) position and a (3, 3) rotation, found "
                                f"{p.shape} and {r.shape}")
    if not (np.isfinite(p).all() and np.isfinite(r).all()):
        raise InvalidInputError(f"tip pose must be finite, found position {p.tolist()} "
                                "or a rotation with NaN/inf")
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > UNIT_TOLERANCE or np.linalg.det(r) < 0.0:
        raise InvalidInputError(f"tip orientation must be a rotation (unit quaternion), found "
                                f"orthogonality error {err:.3g}")
    return p, r

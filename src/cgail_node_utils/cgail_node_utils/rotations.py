"""One rotation at a time, in plain Python floats, bit-identical to scipy's ``Rotation``.

The nodes convert one pose per message (a quaternion to a matrix and back); scipy's
``Rotation`` costs 10-18 us per call for that, most of it array set-up. These two functions do
the same floating-point operations in the same order as scipy's single-rotation path
(``Rotation.from_quat(q).as_matrix()`` and ``Rotation.from_matrix(m, assume_valid=True)
.as_quat(canonical=True)``), so they return the same bits in a tenth of the time;
``test_rotations.py`` holds them equal on random and edge-case rotations. Quaternions are in
ROS order ``(x, y, z, w)``. Inputs are not checked: the callers check them (and fall back to
scipy for anything but one finite rotation).
"""

from __future__ import annotations

from collections.abc import Sequence
import math

Matrix = tuple[tuple[float, float, float], tuple[float, float, float],
               tuple[float, float, float]]


def quat_to_matrix(x: float, y: float, z: float, w: float) -> Matrix:
    """Rows of the rotation matrix of the quaternion ``(x, y, z, w)``, normalised first
    (``Rotation.from_quat(q).as_matrix()``)."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return ((x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)),
            (2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)),
            (2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2))


def matrix_to_quat(m: Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)``, canonical (``w >= 0``; at ``w == 0`` the first
    non-zero of x, y, z positive), of the rotation matrix ``m`` (3 rows of 3), which is not
    re-orthogonalised (``Rotation.from_matrix(m, assume_valid=True).as_quat(canonical=True)``:
    Shepperd's method on the largest of the diagonal and the trace)."""
    trace = m[0][0] + m[1][1] + m[2][2]
    choice, best = 0, m[0][0]
    for c, value in ((1, m[1][1]), (2, m[2][2]), (3, trace)):
        if value > best:  # the first largest, as numpy's argmax
            choice, best = c, value
    q = [0.0, 0.0, 0.0, 0.0]
    if choice != 3:
        i = choice
        j = (i + 1) % 3
        k = (j + 1) % 3
        q[i] = 1 - trace + 2 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
        q[3] = m[k][j] - m[j][k]
    else:
        q[0] = m[2][1] - m[1][2]
        q[1] = m[0][2] - m[2][0]
        q[2] = m[1][0] - m[0][1]
        q[3] = 1 + trace
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    x, y, z, w = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    if w < 0 or (w == 0 and (x < 0 or (x == 0 and (y < 0 or (y == 0 and z < 0))))):
        return -x, -y, -z, -w
    return x, y, z, w

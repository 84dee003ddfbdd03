"""The planner package's rotation helpers (scipy ``Rotation``): quaternions, rotation vectors,
pose checks."""

import math
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cgail_planner.core.errors import InvalidInputError
from cgail_planner.core.rotations import (
    matrix_to_quaternion,
    pose_from_quaternion,
    quaternion_to_matrix,
    rotate_onto,
    rotvec_to_matrix,
    validate_pose,
)


@pytest.mark.parametrize('q', [(0, 0, 0, 1), (0.5, 0.5, 0.5, 0.5), (0.1, -0.7, 0.2, 0.67823299),
                               (0.3, 0.1, -0.2, -0.9)])
def test_quaternion_round_trip_with_w_non_negative(q) -> None:
    q = np.array(q, dtype=float) / np.linalg.norm(q)
    r = quaternion_to_matrix(q)
    assert r.T @ r == pytest.approx(np.eye(3), abs=1e-12) and np.linalg.det(r) > 0
    back = matrix_to_quaternion(r)
    assert back[3] >= 0.0
    np.testing.assert_allclose(back, q if q[3] >= 0 else -q, rtol=0, atol=1e-12)


def test_a_batch_of_matrices_gives_a_batch_of_quaternions() -> None:
    r = Rotation.random(5, random_state=1)
    np.testing.assert_allclose(matrix_to_quaternion(r.as_matrix()),
                               r.as_quat(canonical=True), rtol=0, atol=1e-12)


@pytest.mark.parametrize(('q', 'match'), [((0, 0, 0, 2.0), r'unit quaternion.*\(norm 2\)'),
                                          ((0, 0, np.nan, 1), 'unit quaternion'),
                                          ((0, 0, 1), r'unit quaternion \(x, y, z, w\)')])
def test_a_quaternion_that_is_not_a_unit_one_is_refused(q, match) -> None:
    with pytest.raises(InvalidInputError, match=match):
        quaternion_to_matrix(q)


def test_rotvec_and_rotate_onto() -> None:
    r = rotvec_to_matrix(np.array([0.0, 0.0, math.pi / 2]))
    assert r @ np.array([1.0, 0.0, 0.0]) == pytest.approx([0.0, 1.0, 0.0])
    a = np.array([0.0, 1.0, 0.0])
    b = np.array([0.6, 0.0, 0.8])
    m = rotate_onto(a, b)
    assert m @ a == pytest.approx(b) and m @ np.cross(a, b) == pytest.approx(np.cross(a, b))
    assert rotate_onto(a, a) == pytest.approx(np.eye(3))


@pytest.mark.parametrize(('p', 'r', 'match'), [
    ((0, 0, np.inf), np.eye(3), 'tip pose must be finite'),
    ((0, 0), np.eye(3), r'must be a \(3,\) position and a \(3, 3\) rotation'),
    ((0, 0, 0), np.diag([1.0, 1.0, -1.0]), 'tip orientation must be a rotation'),
])
def test_validate_pose_refuses_what_is_not_a_pose(p, r, match) -> None:
    with pytest.raises(InvalidInputError, match=match):
        validate_pose(np.array(p, dtype=float), r)


def test_pose_from_quaternion_is_quaternion_to_matrix_then_validate_pose() -> None:
    # the plain-float checks decide pass or fail only: the arrays are the general path's
    rng = np.random.default_rng(7)
    for k in range(300):
        q = rng.normal(size=4)
        q *= (1.0 + (rng.uniform(-2e-3, 2e-3) if k % 3 == 0 else 0.0)) / np.linalg.norm(q)
        p = tuple(rng.normal(size=3).tolist())
        try:
            want = validate_pose(np.array(p), quaternion_to_matrix(q))
        except InvalidInputError as exc:
            with pytest.raises(InvalidInputError, match=re.escape(str(exc))):
                pose_from_quaternion(p, tuple(q.tolist()))
            continue
        got = pose_from_quaternion(p, tuple(q.tolist()))
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


@pytest.mark.parametrize(('p', 'q', 'match'), [
    ((0.0, 0.0, np.inf), (0.0, 0.0, 0.0, 1.0), 'tip pose must be finite'),
    ((0.0, 0.0, 0.0), (0.0, 0.0, np.nan, 1.0), 'unit quaternion'),
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 2.0), r'unit quaternion.*\(norm 2\)'),
])
def test_pose_from_quaternion_refuses_what_is_not_a_pose(p, q, match) -> None:
    with pytest.raises(InvalidInputError, match=match):
        pose_from_quaternion(p, q)

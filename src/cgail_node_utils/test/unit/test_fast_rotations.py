"""The plain-float rotations return scipy's bits (the nodes' results must not change)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cgail_node_utils.rotations import matrix_to_quat, quat_to_matrix


def _matrices() -> np.ndarray:
    rng = np.random.default_rng(7)
    rots = Rotation.random(20000, random_state=3).as_matrix()
    small = Rotation.from_rotvec(rng.normal(size=(500, 3)) * 1e-9).as_matrix()
    axes = rng.normal(size=(500, 3))
    half_turns = Rotation.from_rotvec(np.pi * axes / np.linalg.norm(axes, axis=1)[:, None])
    exact = [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
             np.diag([-1.0, -1.0, 1.0]), np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0],
                                                   [0.0, 0.0, -1.0]]),
             np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])]
    composed = rots[:2000] @ rots[2000:4000]  # products: not exactly orthogonal
    return np.concatenate([rots, small, half_turns.as_matrix(), np.array(exact), composed])


def test_matrix_to_quat_is_bit_identical_to_scipy() -> None:
    for m in _matrices():
        want = Rotation.from_matrix(m, assume_valid=True).as_quat(canonical=True)
        got = np.array(matrix_to_quat(m.tolist()))
        assert got.tobytes() == want.tobytes(), (m, want, got)


@pytest.mark.parametrize('scale', [1.0, 1e-3, 7.5])
def test_quat_to_matrix_is_bit_identical_to_scipy(scale: float) -> None:
    rng = np.random.default_rng(11)
    quats = rng.normal(size=(20000, 4))
    quats[:10000] /= np.linalg.norm(quats[:10000], axis=1)[:, None]  # near-unit, as in use
    quats = np.concatenate([quats * scale, np.eye(4), -np.eye(4)])
    for q in quats:
        want = Rotation.from_quat(q).as_matrix()
        got = np.array(quat_to_matrix(*q.tolist()))
        assert got.tobytes() == want.tobytes(), (q, want, got)

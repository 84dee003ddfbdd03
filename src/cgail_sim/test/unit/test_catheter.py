"""Follow-the-leader catheter kinematics (paper section III-A)."""

import math

import numpy as np
import pytest

from cgail_sim.ftl_model import (
    action_to_command,
    bend_limit,
    bend_rotation,
    CatheterBatch,
    CatheterConfig,
    command_to_action,
    frame_from_heading,
)

CFG = CatheterConfig()
DL = CFG.max_step_insertion  # 0.5 mm


def make_batch(n: int = 1, capacity: int = 8) -> CatheterBatch:
    batch = CatheterBatch(n, CFG, capacity=capacity)
    rot = frame_from_heading(np.array([0.0, 0.0, 1.0]))
    for i in range(n):
        batch.reset_env(i, np.zeros(3), rot, np.array([0.0, 0.0, -0.02]))
    return batch


def heading_change(r0: np.ndarray, r1: np.ndarray) -> float:
    return math.acos(float(np.clip(r0[:, 1] @ r1[:, 1], -1.0, 1.0)))


def test_defaults_match_paper() -> None:
    assert CFG.theta_max == pytest.approx(math.pi / 2)
    assert CFG.segment_length == 0.05
    assert CFG.outer_diameter == 0.007
    assert CFG.max_insertion_speed == 0.005
    assert CFG.max_step_insertion == pytest.approx(0.0005)
    assert bend_limit(0.0005, CFG.theta_max, CFG.segment_length) == pytest.approx(
        math.radians(0.9))


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [("theta_max", 0.0, "theta_max must be in"), ("dt", 10.0, "dt must be in"),
     ("segment_length", float("nan"), "segment_length"), ("outer_diameter", -1.0, "outer")],
)
def test_config_rejects(field: str, value: float, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        CatheterConfig(**{field: value})


def test_action_map_exact() -> None:
    alpha, gamma, dl = action_to_command(np.array([0.5, -1.0, 1.0]), math.pi / 2, 0.05, 0.0005)
    lim = math.pi / 2 * 0.0005 / 0.05
    assert float(dl) == pytest.approx(0.0005)
    assert float(alpha) == pytest.approx(0.5 * lim)
    assert float(gamma) == pytest.approx(-lim)
    # clipping and zero insertion => zero bend
    alpha, gamma, dl = action_to_command(np.array([3.0, -3.0, 0.0]), math.pi / 2, 0.05, 0.0005)
    assert (float(alpha), float(gamma), float(dl)) == (0.0, 0.0, 0.0)
    a = np.array([[0.3, -0.7, 0.4], [1.0, 1.0, -1.0]])
    back = command_to_action(*action_to_command(a, 1.2, 0.05, 0.0005), 1.2, 0.05, 0.0005)
    np.testing.assert_allclose(back, a)


def test_bend_rotation_is_rx_then_rz() -> None:
    a, g = 0.3, -0.2
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    rz = np.array([[math.cos(g), -math.sin(g), 0], [math.sin(g), math.cos(g), 0], [0, 0, 1]])
    np.testing.assert_allclose(bend_rotation(np.array(a), np.array(g)), rx @ rz, atol=1e-15)


def test_straight_insertion_moves_along_heading() -> None:
    batch = make_batch()
    for _ in range(10):
        batch.step(np.zeros(1), np.zeros(1), np.full(1, DL))
    np.testing.assert_allclose(batch.tip_position[0], [0.0, 0.0, 10 * DL], atol=1e-15)
    assert batch.n_nodes[0] == 12
    assert batch.inserted_length[0] == pytest.approx(0.02 + 10 * DL)


def test_no_step_bends_more_than_theta_t() -> None:
    rng = np.random.default_rng(0)
    batch = make_batch(4, capacity=4)
    for _ in range(200):
        a = rng.uniform(-3.0, 3.0, size=(4, 3))  # also out-of-range requests
        alpha, gamma, dl = action_to_command(a, batch.theta_max, CFG.segment_length, DL)
        r0 = batch.tip_rotation.copy()
        al, ga, applied = batch.step(alpha * 5.0, gamma * 5.0, dl * 5.0)  # ask for too much
        lim = bend_limit(np.abs(dl * 5.0).clip(max=DL), batch.theta_max, CFG.segment_length)
        assert np.all(np.abs(applied) <= DL + 1e-15)
        assert np.all(np.abs(al) <= lim + 1e-15)
        assert np.all(np.abs(ga) <= lim + 1e-15)
        r1 = batch.tip_rotation
        for i in range(4):
            if applied[i] > 0:
                # heading change of Rx(a)Rz(g) is acos(cos a cos g) <= the bend magnitude
                assert heading_change(r0[i], r1[i]) <= math.hypot(al[i], ga[i]) + 1e-9
                np.testing.assert_allclose(r1[i].T @ r1[i], np.eye(3), atol=1e-12)
    assert batch.capacity >= int(batch.n_nodes.max())  # grew as needed


def test_zero_insertion_gives_zero_bend() -> None:
    batch = make_batch()
    r0 = batch.tip_rotation.copy()
    p0 = batch.tip_position.copy()
    al, ga, dl = batch.step(np.full(1, 0.5), np.full(1, 0.5), np.zeros(1))
    assert (al[0], ga[0], dl[0]) == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(batch.tip_rotation, r0)
    np.testing.assert_array_equal(batch.tip_position, p0)


def test_full_bend_follows_minimum_radius_arc() -> None:
    """Constant maximal alpha traces a circle of radius L / theta_max (31.8 mm)."""
    batch = make_batch(capacity=16)
    lim = bend_limit(DL, CFG.theta_max, CFG.segment_length)
    n = 100
    for _ in range(n):
        batch.step(np.full(1, 10.0), np.zeros(1), np.full(1, DL))
    # heading turned by n * lim about x_A; chord of a circle with R = DL / (2 sin(lim/2))
    heading = batch.tip_rotation[0][:, 1]
    assert math.acos(heading @ np.array([0.0, 0.0, 1.0])) == pytest.approx(n * lim, rel=1e-9)
    radius = DL / (2 * math.sin(lim / 2))
    assert radius == pytest.approx(CFG.segment_length / CFG.theta_max, rel=1e-4)
    chord = np.linalg.norm(batch.tip_position[0])
    # the first node sits at the start; every step adds a chord of the circle
    assert chord == pytest.approx(2 * radius * math.sin(n * lim / 2), rel=1e-6)


def test_retraction_retraces_body() -> None:
    batch = make_batch(capacity=4)
    rng = np.random.default_rng(1)
    positions = [batch.tip_position[0].copy()]
    for _ in range(40):
        a = rng.uniform(-1, 1, size=3)
        a[2] = 1.0
        batch.step(*[np.atleast_1d(x) for x in action_to_command(a, CFG.theta_max,
                                                                  CFG.segment_length, DL)])
        positions.append(batch.tip_position[0].copy())
    # retract by exactly 10 steps (bends requested but ignored)
    for _ in range(10):
        al, ga, dl = batch.step(np.full(1, 1.0), np.full(1, 1.0), np.full(1, -DL))
        assert (al[0], ga[0]) == (0.0, 0.0)
        assert dl[0] == pytest.approx(-DL)
    np.testing.assert_allclose(batch.tip_position[0], positions[30], atol=1e-12)
    # half a step lands mid-segment
    batch.step(np.zeros(1), np.zeros(1), np.full(1, -DL / 2))
    np.testing.assert_allclose(batch.tip_position[0], 0.5 * (positions[29] + positions[30]),
                               atol=1e-12)
    # re-inserting continues from there
    batch.step(np.zeros(1), np.zeros(1), np.full(1, DL / 2))
    assert batch.inserted_length[0] == pytest.approx(0.02 + 30 * DL)


def test_retraction_stops_at_introducer_end() -> None:
    batch = make_batch()
    batch.step(np.zeros(1), np.zeros(1), np.full(1, DL))
    travelled = 0.0
    for _ in range(60):
        travelled += float(batch.step(np.zeros(1), np.zeros(1), np.full(1, -DL))[2][0])
    assert travelled == pytest.approx(-(0.02 + DL))
    np.testing.assert_allclose(batch.tip_position[0], [0.0, 0.0, -0.02], atol=1e-15)
    assert batch.n_nodes[0] == 1


def test_theta_max_curriculum() -> None:
    batch = make_batch()
    batch.set_theta_max(math.pi / 4)
    al, _, _ = batch.step(np.full(1, 1.0), np.zeros(1), np.full(1, DL))
    assert al[0] == pytest.approx(math.pi / 4 * DL / CFG.segment_length)
    with pytest.raises(ValueError, match="theta_max must be in"):
        batch.set_theta_max(-0.1)


def test_body_points_spacing() -> None:
    batch = make_batch(capacity=4)
    for _ in range(40):
        batch.step(np.zeros(1), np.zeros(1), np.full(1, DL))
    pts = batch.body_points(0, 0.005)
    np.testing.assert_allclose(pts[0], [0.0, 0.0, -0.02])
    np.testing.assert_allclose(pts[-1], batch.tip_position[0])
    gaps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert np.all(gaps <= 0.02 + 1e-12)
    assert len(pts) >= 0.04 / 0.02


def test_frame_from_heading() -> None:
    rot = frame_from_heading(np.array([0.0, 2.0, 0.0]))
    np.testing.assert_allclose(rot[:, 1], [0, 1, 0])
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-15)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="heading must be"):
        frame_from_heading(np.zeros(3))

"""Guidance geometry: next waypoint on the path and the suggested bend, exact values."""

import math

import numpy as np
import pytest

from cgail_planner.core.guidance import GuidanceConfig, PathFollower, suggested_bend

L = 0.05
EYE = np.eye(3)


def straight_path(length: float = 0.1, n: int = 101) -> np.ndarray:
    return np.column_stack([np.zeros(n), np.linspace(0.0, length, n), np.zeros(n)])


@pytest.mark.parametrize(('waypoint', 'expected'), [
    # straight ahead: no bend
    ((0.0, 0.02, 0.0), (0.0, 0.0, 0.0)),
    # 45 deg towards +z at 10 mm: |bend| = 2 sin(45) / 0.01 * 0.05 = 7.07 -> capped at pi/2,
    # all of it about x_A (alpha > 0 turns y_A towards z_A)
    ((0.0, 0.01, 0.01), (math.pi / 2, 0.0, math.pi / 4)),
    # towards -x_A: gamma > 0 turns y_A towards -x_A
    ((-0.01, 0.01, 0.0), (0.0, math.pi / 2, math.pi / 4)),
    # behind the tip: the full bend towards it
    ((0.0, -0.01, 0.001), (math.pi / 2, 0.0, math.atan2(0.001, -0.01))),
])
def test_suggested_bend_exact(waypoint, expected) -> None:
    alpha, gamma, theta = suggested_bend(np.zeros(3), EYE, np.array(waypoint), L, math.pi / 2)
    assert (alpha, gamma, theta) == pytest.approx(expected, abs=1e-12)


def test_suggested_bend_magnitude_is_arc_curvature_times_l() -> None:
    # waypoint at 100 mm, 0.1 rad off the heading towards +x: kappa = 2 sin(0.1) / 0.1
    d = 0.1
    th = 0.1
    wp = np.array([d * math.sin(th), d * math.cos(th), 0.0])
    alpha, gamma, theta = suggested_bend(np.zeros(3), EYE, wp, L, math.pi / 2)
    assert theta == pytest.approx(th, abs=1e-12)
    assert alpha == pytest.approx(0.0, abs=1e-15)
    assert gamma == pytest.approx(-2.0 * math.sin(th) / d * L, rel=1e-12)


def test_constant_bend_arc_passes_through_the_waypoint() -> None:
    """Integrating the FTL kinematics with the suggested bend lands on the waypoint."""
    wp = np.array([0.012, 0.05, -0.007])
    alpha, gamma, _ = suggested_bend(np.zeros(3), EYE, wp, L, math.pi / 2)
    from cgail_sim.ftl_model import bend_rotation
    p, r = np.zeros(3), EYE.copy()
    dl = 1e-5
    best = np.inf
    for _ in range(10000):
        r = r @ bend_rotation(np.array(alpha * dl / L), np.array(gamma * dl / L))
        p = p + dl * r[:, 1]
        best = min(best, float(np.linalg.norm(p - wp)))
    assert best < 2e-4  # small-angle composition of Rx, Rz: 0.2 mm over 52 mm


def test_suggested_bend_in_a_rotated_frame() -> None:
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # y_A = -x world
    p = np.array([0.1, 0.2, 0.3])
    wp = p + rot @ np.array([0.0, 0.01, 0.01])
    alpha, gamma, theta = suggested_bend(p, rot, wp, L, 0.3)
    assert (alpha, gamma, theta) == pytest.approx((0.3, 0.0, math.pi / 4), abs=1e-12)


def test_next_waypoint_is_lookahead_ahead_of_the_projection() -> None:
    f = PathFollower(straight_path(), GuidanceConfig(lookahead=0.010))
    g = f.guide(np.array([0.002, 0.0305, 0.0]), EYE)
    assert g.next_waypoint == pytest.approx([0.0, 0.0405, 0.0], abs=1e-12)
    assert g.cross_track == pytest.approx(0.002, abs=1e-12)
    assert g.arc_position == pytest.approx(0.0305, abs=1e-12)
    assert g.remaining == pytest.approx(0.0695, abs=1e-12)
    # the waypoint is 10 mm ahead and 2 mm towards -x: gamma > 0 (towards -x_A), alpha 0
    th = math.atan2(0.002, 0.010)
    assert g.heading_error == pytest.approx(th, abs=1e-12)
    assert g.bend[0] == pytest.approx(0.0, abs=1e-15)
    # 2 sin(th) / |d| * L = 1.92 rad: capped at max_bend
    assert g.bend[1] == pytest.approx(math.pi / 2, rel=1e-12)


def test_next_waypoint_clamps_at_the_path_end() -> None:
    f = PathFollower(straight_path(), GuidanceConfig(lookahead=0.010))
    g = f.guide(np.array([0.0, 0.095, 0.0]), EYE)
    assert g.next_waypoint == pytest.approx([0.0, 0.1, 0.0], abs=1e-12)
    assert g.remaining == pytest.approx(0.005, abs=1e-12)


def test_projection_follows_a_folded_path_in_order() -> None:
    # a U-turn: out along +y then back along +y at x = 10 mm; the tip near the return leg
    # projects on the return leg only if it got there by following the path
    n = 50
    out = np.column_stack([np.zeros(n), np.linspace(0, 0.05, n), np.zeros(n)])
    back = np.column_stack([np.full(n, 0.01), np.linspace(0.05, 0, n), np.zeros(n)])
    f = PathFollower(np.vstack([out, back]), GuidanceConfig(search_window=0.005))
    s_prev = 0.0
    for y in np.linspace(0.0, 0.05, 26):
        _, s, _ = f.project(np.array([0.004, y, 0.0]))
        assert s >= s_prev - 1e-12
        s_prev = s
    assert s_prev < 0.06  # still on the outbound leg, not jumped to the return leg


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('lookahead', 0.0, r'lookahead must be in \(0.0, 0.2\], found 0.0'),
    ('segment_length', 1.0, r'segment_length must be in \[0.001, 0.5\], found 1.0'),
    ('max_bend', 2.0, r'max_bend must be in'),
    ('search_window', float('nan'), r'search_window must be in'),
])
def test_config_rejects_bad_values(field, value, match) -> None:
    with pytest.raises(ValueError, match=match):
        GuidanceConfig(**{field: value})


@pytest.mark.parametrize('path', [np.zeros((1, 3)), np.zeros((5, 2)), np.zeros((3, 3)),
                                  np.array([[0, 0, 0], [np.nan, 0, 0.0]])])
def test_follower_rejects_bad_paths(path) -> None:
    with pytest.raises(ValueError, match='path must'):
        PathFollower(path)

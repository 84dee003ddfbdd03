"""The pure-pursuit rule and its numba rollout (cgail_learning/pursuit.py) against the catheter
model's numpy forms."""

import numpy as np
import pytest

from cgail_learning.pursuit import carrot, rollout
from cgail_sim.config import CatheterConfig
from cgail_sim.ftl_model import action_to_command, advance_batch, steer_nb, steer_towards


def _arc(n: int = 80) -> np.ndarray:
    """A planar quarter circle of radius 60 mm, 1 mm apart, from the origin along +y."""
    s = np.arange(n) * 0.001
    th = s / 0.06
    return np.column_stack([0.06 * (1 - np.cos(th)), 0.06 * np.sin(th), np.zeros(n)])


def test_the_carrot_is_lookahead_past_the_furthest_reached_and_never_goes_back():
    pts = _arc()
    target = pts[-1] + [0.0, 0.0, 0.02]
    c, prog, final = carrot(pts[10] + [0, 0, 0.001], pts, 0, 6, target, 0.005)
    assert (prog, final) == (10, False) and np.allclose(c, pts[16])
    c, prog, final = carrot(pts[3], pts, 10, 6, target, 0.005)  # behind: keeps its progress
    assert (prog, final) == (10, False) and np.allclose(c, pts[16])


@pytest.mark.parametrize('where', ['near the target', 'near the end'])
def test_the_carrot_is_the_target_near_it_or_near_the_polyline_end(where):
    pts = _arc()
    if where == 'near the target':
        target, p, prog = pts[30] + [0.002, 0, 0], pts[28], 0
    else:
        target, p, prog = pts[-1] + [0, 0, 0.05], pts[60], 73  # 73 + 6 >= 79 - 1
    c, _, final = carrot(p, pts, prog, 6, target, 0.005)
    assert final and np.array_equal(c, target)


def test_steer_nb_is_steer_towards():
    rng = np.random.default_rng(3)
    cfg = CatheterConfig()
    for _ in range(50):
        q, _r = np.linalg.qr(rng.normal(size=(3, 3)))
        R = q * np.sign(np.linalg.det(q))
        p, goal = rng.normal(size=3) * 0.01, rng.normal(size=3) * 0.02
        ref = steer_towards(p, R, goal, cfg)
        limit = cfg.theta_max * cfg.max_step_insertion / cfg.segment_length
        assert np.allclose(steer_nb(p, R, goal, limit), ref[:2], rtol=0, atol=1e-12)


def test_rollout_is_the_step_by_step_pursuit_of_the_catheter_model():
    """The kernel against a plain numpy loop: constant bends held, then the pursuit."""
    cfg = CatheterConfig()
    pts = _arc()
    target = pts[-1] + [0.004, 0.0, 0.0]
    first = np.array([[1.0, 0.0, 1.0], [-0.5, 0.5, 1.0], [0.0, 0.0, 1.0]])
    hold = np.array([8, 16, 0])
    p0, R0 = np.zeros(3), np.eye(3)
    tips, acts = rollout(p0, R0, first, hold, pts, 0, 6, target, 0.035, cfg, cfg.theta_max,
                         60, 20)
    assert tips.shape == (3, 60, 3) and acts.shape == (3, 20, 3)
    p, R = np.repeat(p0[None], 3, 0), np.repeat(R0[None], 3, 0)
    progress = [0, 0, 0]
    for t in range(60):
        a = np.empty((3, 3))
        for k in range(3):
            c, progress[k], _ = carrot(p[k], pts, progress[k], 6, target, 0.035)
            a[k] = first[k] if t < hold[k] else steer_towards(p[k], R[k], c, cfg)
        al, ga, dl = action_to_command(a, cfg.theta_max, cfg.segment_length,
                                       cfg.max_step_insertion, cfg.forward_only)
        R, p = advance_batch(R, p, al, ga, dl)
        assert np.allclose(tips[:, t], p, rtol=0, atol=1e-9)
        if t < 20:
            assert np.allclose(acts[:, t], a, rtol=0, atol=1e-9)
    # the pure pursuit (sequence 2) stays on the arc and advances along it
    off = np.linalg.norm(tips[2][:, None] - pts[None], axis=2).min(axis=1)
    assert off.max() < 0.002 and np.linalg.norm(tips[2, -1] - pts[0]) > 0.025

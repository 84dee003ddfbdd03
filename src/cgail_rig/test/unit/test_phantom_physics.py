"""Phantom physics: constant-curvature FTL insertion, retraction, wall constraint, EM noise."""

import math

from flat_wall import FlatWall
import numpy as np
import pytest

from cgail_planner.core.rotations import rotate_onto
from cgail_rig.core.phantom import PhantomConfig, PhantomPhysics

L = 0.05


def physics(wall=None) -> PhantomPhysics:
    ph = PhantomPhysics(PhantomConfig(), wall)
    ph.reset(np.zeros(3), np.eye(3), np.array([0.0, -0.02, 0.0]))
    return ph


@pytest.mark.parametrize(('alpha', 'gamma', 'dl'), [(0.5, 0.0, 0.02), (0.0, -1.0, 0.03),
                                                     (0.6, 0.8, 0.01)])
def test_held_bend_turns_the_heading_by_bend_dl_over_l(alpha, gamma, dl) -> None:
    ph = physics()
    ph.step(0.02, 0.0, (alpha, gamma))          # first reading: the reference
    for k in range(1, 101):                     # the driver inserts dl at <= 5 mm/s
        ph.step(dl / 0.005 / 100, dl * k / 100, (alpha, gamma))
    heading = ph.tip_rotation[:, 1]
    turned = math.acos(float(np.clip(heading @ np.array([0.0, 1.0, 0.0]), -1, 1)))
    # sub-steps Rx(a k) Rz(g k) compose to a rotation of hypot(a, g) dl / L (to 2nd order in k)
    assert turned == pytest.approx(math.hypot(alpha, gamma) * dl / L, rel=2e-3)
    assert ph.inserted == pytest.approx(dl, abs=1e-12)


def test_pure_alpha_bend_follows_a_circle_of_radius_l_over_bend() -> None:
    ph = physics()
    ph.move(0.04, (1.0, 0.0))  # 40 mm on a circle of radius 50 mm about x, towards +z
    # 80 sub-steps of 0.5 mm, the heading turned by 0.5 mm / 50 mm before each: the exact chain
    k = np.arange(1, 81) * (0.0005 / L)
    expected = [0.0, 0.0005 * np.cos(k).sum(), 0.0005 * np.sin(k).sum()]
    assert ph.tip_position == pytest.approx(expected, abs=1e-12)
    # ... which lies within 0.2 mm of the circle of radius L / bend = 50 mm
    phi = 0.04 / L
    assert ph.tip_position == pytest.approx([0.0, L * math.sin(phi), L * (1 - math.cos(phi))],
                                            abs=2e-4)


def test_no_insertion_no_turn_and_retraction_slides_back() -> None:
    ph = physics()
    ph.step(0.02, 0.01, (1.0, 0.0))  # first reading: the reference, no motion
    ph.step(0.02, 0.01, (0.0, 1.5))  # bend changes without insertion: the tip does not move
    assert ph.tip_position == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)
    assert ph.tip_rotation[:, 1] == pytest.approx([0.0, 1.0, 0.0])
    ph.move(0.03, (0.0, 0.0))        # 30 mm straight
    ph.move(-0.02, (1.0, 1.0))       # retract 20 mm: straight back along the body, bend ignored
    assert ph.tip_position == pytest.approx([0.0, 0.01, 0.0], abs=1e-9)
    assert ph.tip_rotation[:, 1] == pytest.approx([0.0, 1.0, 0.0])


def test_retraction_slides_back_along_a_bent_introducer() -> None:
    """The phantom's body starts with the introducer it is given (a start's bent one) and
    retraction follows it to its proximal end."""
    intro = np.array([[0.01, -0.03, 0.0], [0.005, -0.02, 0.0], [0.0, -0.01, 0.0]])
    ph = PhantomPhysics(PhantomConfig(), None)
    ph.reset(np.zeros(3), np.eye(3), intro)
    assert np.array_equal(ph.catheter.body(0), np.vstack([intro, np.zeros(3)]))
    ph.move(-0.015, (0.0, 0.0))  # 10 mm back to intro[2], then 5 mm towards intro[1]
    seg = (intro[1] - intro[2]) / np.linalg.norm(intro[1] - intro[2])
    assert ph.tip_position == pytest.approx(intro[2] + 0.005 * seg, abs=1e-12)
    ph.move(-0.1, (0.0, 0.0))
    assert ph.tip_position == pytest.approx(intro[0], abs=1e-12)


def test_wall_pushes_the_tip_back_and_the_heading_slides_along_it() -> None:
    ph = physics(FlatWall())
    ph.move(0.05, (1.5, 0.0))  # bending towards +z into the wall
    assert ph.tip_position[2] <= 0.002 - ph.radius + 1e-12
    assert ph.contacts > 0
    assert ph.tip_rotation[:, 1][2] <= 1e-9  # no outward heading component left
    assert np.allclose(ph.tip_rotation.T @ ph.tip_rotation, np.eye(3), atol=1e-9)


def test_a_re_homed_driver_is_not_motion() -> None:
    ph = physics()
    ph.step(0.02, 0.22, (0.0, 0.0))   # reference
    ph.step(0.02, 0.2201, (0.0, 0.0))  # 0.1 mm in 20 ms (5 mm/s): motion
    assert ph.inserted == pytest.approx(0.0001)
    ph.step(0.02, 0.0, (0.0, 0.0))    # the driver restarted at 0: no 220 mm retraction
    assert ph.insertion_jumps == 1
    assert ph.tip_position == pytest.approx([0.0, 0.0001, 0.0], abs=1e-12)
    ph.step(0.02, 0.0001, (0.0, 0.0))  # and motion counts from the new reference
    assert ph.tip_position == pytest.approx([0.0, 0.0002, 0.0], abs=1e-12)


def test_em_noise_has_the_configured_rms() -> None:
    ph = physics()
    rng = np.random.default_rng(0)
    errs = np.array([ph.measured_pose(rng)[0] - ph.tip_position for _ in range(4000)])
    assert float(np.sqrt(np.mean(np.sum(errs ** 2, axis=1)))) == pytest.approx(0.0005, rel=0.05)


def test_rotate_onto() -> None:
    a = np.array([0.0, 1.0, 0.0])
    b = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    assert rotate_onto(a, b) @ a == pytest.approx(b)
    assert rotate_onto(a, a) == pytest.approx(np.eye(3))


def test_config_rejects_a_catheter_that_is_not_a_catheter_config() -> None:
    with pytest.raises(ValueError, match='catheter must be a CatheterConfig'):
        PhantomConfig(catheter=0.05)  # type: ignore[arg-type]


@pytest.mark.parametrize(('field', 'value'), [('max_jump', -1.0), ('em_noise_rms', -1.0),
                                              ('max_substep', 1.0)])
def test_config_rejects_bad_values(field, value) -> None:
    with pytest.raises(ValueError, match=field):
        PhantomConfig(**{field: value})


def test_step_rejects_a_bad_dt() -> None:
    with pytest.raises(ValueError, match='dt must be a positive'):
        physics().step(0.0, 0.0, (0.0, 0.0))


def test_deformable_wall_is_stepped_every_wall_dt_with_the_body() -> None:
    from cgail_sim.wall import DeformableWall

    class CountingWall(DeformableWall):
        def __init__(self) -> None:  # no anatomy: only the stepping is under test
            self.calls = []

        def reset(self) -> None:
            self.calls.clear()

        def step(self, t, dt, body_points, body_radius) -> None:
            self.calls.append((round(t, 9), round(dt, 9), len(body_points), body_radius))

        def tip_contact(self, tip, radius, dt):
            return FlatWall().tip_contact(tip - np.array([0.0, 0.0, 1.0]), radius, dt)

    wall = CountingWall()
    ph = PhantomPhysics(PhantomConfig(wall_dt=0.05), wall)
    ph.reset(np.zeros(3), np.eye(3), np.array([0.0, -0.02, 0.0]))
    for _ in range(10):
        ph.step(0.02, 0.0, (0.0, 0.0))
    # 10 x 20 ms: stepped at 60, 120 and 180 ms, each with the 3 accumulated ticks
    assert [c[:2] for c in wall.calls] == [(0.06, 0.06), (0.12, 0.06), (0.18, 0.06)]
    assert all(c[2] >= 2 and c[3] == pytest.approx(0.0035) for c in wall.calls)


@pytest.mark.parametrize('bend', [(0.5, -0.3), (0.0, 1.2), (-1.0, 0.0)])
def test_bench_fixture_tip_is_the_arc_of_the_bend_without_insertion(bend) -> None:
    """Clamped at the segment base: the tip is the constant-curvature arc of the bend (the
    model's own insertion of L at that bend), whatever the insertion; the rotation relative
    to the base is the rotation vector (alpha, ~0, gamma) that identify_pam reads."""
    from pam_controller.core.identification import bend_from_rotations

    base_r = rotate_onto(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.6, 0.8]))
    ph = PhantomPhysics(PhantomConfig(fixture='bench'))
    ph.reset(np.array([0.01, 0.0, 0.0]), base_r, np.array([0.01, -0.02, 0.0]))
    assert ph.tip_position == pytest.approx([0.01, 0.6 * L, 0.8 * L], abs=1e-12)  # straight
    ph.step(0.02, 0.0, bend)
    ph.step(0.02, 0.004, bend)                  # an insertion is ignored on the bench
    assert ph.inserted == 0.0
    free = PhantomPhysics(PhantomConfig())
    free.reset(np.array([0.01, 0.0, 0.0]), base_r, np.array([0.01, -0.02, 0.0]))
    free.move(L, bend)                          # the same arc, inserted in free space
    assert ph.tip_position == pytest.approx(free.tip_position, abs=1e-12)
    np.testing.assert_allclose(ph.tip_rotation, free.tip_rotation, atol=1e-12)
    read = bend_from_rotations(base_r, ph.tip_rotation[None])[0]
    assert read == pytest.approx(bend, abs=1e-3 * max(1.0, abs(bend[0] * bend[1]) * 10))


def test_fixture_must_be_known() -> None:
    with pytest.raises(ValueError, match="fixture must be one of"):
        PhantomConfig(fixture='clamp')

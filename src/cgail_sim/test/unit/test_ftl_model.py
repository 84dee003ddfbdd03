"""The catheter model's forms agree: batched, single-pose and numba, step and observation.

Every form of :mod:`cgail_sim.ftl_model` is run on the same random inputs and compared:
the observations must be equal to the bit (float32), the steps to 1e-15 m (numpy's 3x3
products may round differently from the written-out numba sums). The rotation conventions are
held to scipy's ``Rotation`` (the owner of rotations). The contract round-trips through JSON.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cgail_sim.ftl_model import (
    action_to_command,
    advance_batch,
    advance_nb,
    advance_pose,
    advance_pose_steps,
    bend_limit,
    bend_rotation,
    CatheterBatch,
    CatheterConfig,
    command_nb,
    introducer_tail,
    N_RAYS,
    OBS_DIM,
    obs_layout,
    ObservationConfig,
    ObservationSpec,
    observe_batch,
    observe_nb,
    observe_pose,
    PolicyContract,
    RAY_DIRECTIONS,
    retract_chain,
    seed_body,
    segment_bend_step,
)

MODEL = CatheterConfig()
N = 64


@pytest.fixture(scope='module')
def poses():
    """N random tip poses, goals, hit distances and actions (some out of range)."""
    rng = np.random.default_rng(11)
    p = rng.normal(0.0, 0.05, (N, 3))
    r = Rotation.random(N, random_state=12).as_matrix()
    goal = rng.normal(0.0, 0.05, (N, 3))
    hits = rng.uniform(-0.01, 0.06, (N, N_RAYS))
    act = rng.uniform(-1.3, 1.3, (N, 3))
    return p, r, goal, hits, act


@pytest.fixture(scope='module')
def spec():
    return ObservationSpec(origin=np.array([0.01, -0.02, 0.03]), d_max=0.27)


def test_observation_forms_are_equal_to_the_bit(poses, spec) -> None:
    p, r, goal, hits, _ = poses
    batch = observe_batch(spec, p, r, goal, hits)
    assert batch.dtype == np.float32 and batch.shape == (N, OBS_DIM)
    buf = np.empty(OBS_DIM)
    for i in range(N):
        single = observe_pose(spec, p[i], r[i], goal[i], hits[i])
        observe_nb(buf, p[i, 0], p[i, 1], p[i, 2], r[i], goal[i, 0], goal[i, 1], goal[i, 2],
                   hits[i], spec.origin, spec.position_scale, spec.d_max, spec.ray_length)
        assert np.array_equal(single, batch[i])
        assert np.array_equal(buf.astype(np.float32), batch[i])
        assert np.array_equal(buf, buf.astype(np.float32))  # already float32 values


def test_observation_follows_the_layout(poses, spec) -> None:
    p, r, goal, hits, _ = poses
    obs = observe_pose(spec, p[0], r[0], goal[0], hits[0])
    fields = {f.name: slice(f.start, f.stop) for f in obs_layout()}
    v = (goal[0] - p[0]) / spec.d_max
    np.testing.assert_allclose(obs[fields['tip_position']],
                               (p[0] - spec.origin) / spec.position_scale, rtol=1e-6)
    np.testing.assert_allclose(obs[fields['tip_x_axis']], r[0][:, 0], rtol=1e-6)
    np.testing.assert_allclose(obs[fields['tip_heading']], r[0][:, 1], rtol=1e-6)
    np.testing.assert_allclose(obs[fields['tip_z_axis']], r[0][:, 2], rtol=1e-6)
    np.testing.assert_allclose(obs[fields['target_distance']], [np.linalg.norm(v)], rtol=1e-6)
    np.testing.assert_allclose(obs[fields['target_vector']], v, rtol=1e-6)
    np.testing.assert_allclose(obs[fields['rays']], np.clip(hits[0] / spec.ray_length, 0, 1),
                               rtol=1e-6)


@pytest.mark.parametrize('forward_only', [False, True])
def test_command_forms_are_equal(poses, forward_only) -> None:
    act = poses[4]
    alpha, gamma, dl = action_to_command(act, MODEL.theta_max, MODEL.segment_length,
                                         MODEL.max_step_insertion, forward_only)
    for i in range(N):
        got = command_nb(act[i, 0], act[i, 1], act[i, 2], MODEL.theta_max,
                         MODEL.segment_length, MODEL.max_step_insertion, forward_only)
        assert got == (alpha[i], gamma[i], dl[i])
    assert (dl >= 0.0).all() if forward_only else (dl < 0.0).any()
    limit = bend_limit(dl, MODEL.theta_max, MODEL.segment_length)
    assert (np.abs(alpha) <= limit).all() and (np.abs(dl) <= MODEL.max_step_insertion).all()
    assert np.abs(alpha).max() == pytest.approx(limit[np.argmax(np.abs(alpha))])


def test_step_forms_are_equal(poses) -> None:
    p, r, _, _, act = poses
    alpha, gamma, dl = action_to_command(act, MODEL.theta_max, MODEL.segment_length,
                                         MODEL.max_step_insertion)
    dl = np.abs(dl)  # inserting steps
    r_b, p_b = advance_batch(r, p, alpha, gamma, dl)
    for i in range(N):
        p_s, r_s = advance_pose(p[i], r[i], alpha[i], gamma[i], dl[i])
        p_n, r_n = p[i].copy(), r[i].copy()
        advance_nb(p_n, r_n, alpha[i], gamma[i], dl[i])
        for pos, rot in ((p_s, r_s), (p_n, r_n)):
            np.testing.assert_allclose(pos, p_b[i], rtol=0, atol=1e-15)
            np.testing.assert_allclose(rot, r_b[i], rtol=0, atol=1e-15)


def test_steps_at_one_bend_are_the_single_steps_repeated(poses) -> None:
    # the same arithmetic with the bend matrix built once: equal arrays, not merely close
    p, r, _, _, act = poses
    alpha, gamma, _ = action_to_command(act, MODEL.theta_max, MODEL.segment_length,
                                        MODEL.max_step_insertion)
    for i in range(8):
        points, rot = advance_pose_steps(p[i], r[i], alpha[i], gamma[i], 5e-4, 30)
        pos, want_rot = p[i], r[i]
        want = [pos]
        for _ in range(30):
            pos, want_rot = advance_pose(pos, want_rot, alpha[i], gamma[i], 5e-4)
            want.append(pos)
        assert points.shape == (31, 3)
        assert np.array_equal(points, np.array(want)) and np.array_equal(rot, want_rot)


def test_a_single_catheter_steps_as_the_batch_does() -> None:
    # the one-catheter path (Python floats) against the batch path (forced by ``active``):
    # the same chains and returns, equal arrays, through insertions, retractions and clamps
    rng = np.random.default_rng(21)
    fast = CatheterBatch(1, MODEL, capacity=8)
    batch = CatheterBatch(1, MODEL, capacity=8)
    for cat in (fast, batch):
        cat.n_nodes[:] = 1  # a chain of one node at the origin
    everyone = np.array([True])
    for k in range(400):
        a, g = rng.uniform(-0.05, 0.05, 2)
        d = rng.choice([rng.uniform(-2e-3, 2e-3), 0.0, MODEL.max_step_insertion * 3])
        got = fast.step(np.array([a]), np.array([g]), np.array([d]))
        want = batch.step(np.array([a]), np.array([g]), np.array([d]), everyone)
        for x, y in zip(got, want, strict=True):
            assert np.array_equal(x, y), k
        assert np.array_equal(fast.n_nodes, batch.n_nodes)
        n = int(fast.n_nodes[0])
        assert np.array_equal(fast.positions[:, :n], batch.positions[:, :n])
        assert np.array_equal(fast.rotations[:, :n], batch.rotations[:, :n])
        assert np.array_equal(fast.arc[:, :n], batch.arc[:, :n])
    assert fast.capacity > 8  # it grew on the way


def test_the_bend_is_rx_then_rz_as_scipy_composes_it() -> None:
    rng = np.random.default_rng(3)
    a, g = rng.uniform(-1.5, 1.5, (2, 20))
    ref = Rotation.from_euler('XZ', np.column_stack([a, g])).as_matrix()  # intrinsic x, then z
    np.testing.assert_allclose(bend_rotation(a, g), ref, rtol=0, atol=1e-15)
    r = Rotation.random(random_state=4).as_matrix()
    p = np.zeros(3)
    advance_nb(p, r, a[0], g[0], 0.0)
    np.testing.assert_allclose(r, Rotation.random(random_state=4).as_matrix() @ ref[0],
                               rtol=0, atol=1e-15)


def test_segment_bend_is_the_normalised_action_of_the_bend() -> None:
    dl = 0.0003
    bend = (0.4, -2.0)  # the second beyond theta_max: saturates
    alpha, gamma = segment_bend_step(bend, dl, MODEL.theta_max, MODEL.segment_length)
    assert alpha == pytest.approx(0.4 * dl / MODEL.segment_length, rel=1e-15)
    assert gamma == -bend_limit(dl, MODEL.theta_max, MODEL.segment_length)
    a = np.array([bend[0] / MODEL.theta_max, -1.0, dl / MODEL.max_step_insertion])
    ref = action_to_command(a, MODEL.theta_max, MODEL.segment_length, MODEL.max_step_insertion)
    assert (alpha, gamma) == pytest.approx((float(ref[0]), float(ref[1])), rel=1e-15)


def chain(n_steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A straight body along +y: the introducer from y = -0.01, then n_steps of 0.5 mm."""
    positions, rotations, arc = np.zeros((n_steps + 2, 3)), np.zeros((n_steps + 2, 3, 3)), \
        np.zeros(n_steps + 2)
    seed_body(positions, rotations, arc, np.array([0.0, -0.01, 0.0]), np.zeros(3), np.eye(3))
    for k in range(n_steps):
        positions[2 + k] = [0.0, (k + 1) * 0.0005, 0.0]
        arc[2 + k] = arc[1 + k] + 0.0005
    return positions, rotations, arc


@pytest.mark.parametrize(('distance', 'n_left', 'tip_y', 'travelled'), [
    (0.0002, 6, 0.0018, 0.0002),      # onto the last segment: its distal node interpolated
    (0.0005, 5, 0.0015, 0.0005),      # exactly one node back: that node is the tip
    (0.0023, 2, -0.0003, 0.0023),     # past the start pose onto the introducer
    (0.05, 1, -0.01, 0.012),          # stops at the introducer's proximal end
])
def test_retraction_rule(distance, n_left, tip_y, travelled) -> None:
    positions, _, arc = chain(4)
    n, moved = retract_chain(positions, arc, 6, distance)
    assert (n, moved) == (n_left, pytest.approx(travelled, abs=1e-15))
    assert positions[n - 1] == pytest.approx([0.0, tip_y, 0.0], abs=1e-15)
    assert arc[n - 1] == pytest.approx(0.01 + tip_y, abs=1e-15)


def test_the_batched_body_retracts_by_the_rule() -> None:
    batch = CatheterBatch(1, MODEL, capacity=8)
    batch.reset_env(0, np.zeros(3), np.eye(3), np.array([0.0, -0.01, 0.0]))
    for _ in range(4):
        batch.step(np.zeros(1), np.zeros(1), np.full(1, 0.0005))
    positions, _, arc = chain(4)
    assert np.array_equal(batch.positions[0, :6], positions)
    assert np.array_equal(batch.arc[0, :6], arc)
    _, _, applied = batch.step(np.ones(1), np.ones(1), np.full(1, -0.0005))
    n, _ = retract_chain(positions, arc, 6, 0.0005)
    assert applied[0] == pytest.approx(-0.0005, abs=1e-15) and batch.n_nodes[0] == n == 5


def test_introducer_tail_runs_back_to_5_mm_beyond_the_exit_plane() -> None:
    exit_point, normal = np.array([0.0, -0.05, 0.0]), np.array([0.0, -1.0, 0.0])
    r = np.eye(3)
    assert introducer_tail(exit_point, normal, np.zeros(3), r) == pytest.approx([0, -0.055, 0])
    sideways = Rotation.from_euler('z', 90, degrees=True).as_matrix()  # heading -x
    assert introducer_tail(exit_point, normal, np.zeros(3), sideways) == \
        pytest.approx([0, -0.055, 0])


def test_observation_spec_round_trips_and_refuses_another_layout(spec) -> None:
    data = json.loads(json.dumps(spec.to_dict()))
    back = ObservationSpec.from_dict(data)
    assert back.same_as(spec) and back.dim == OBS_DIM
    assert np.array_equal(back.ray_directions, RAY_DIRECTIONS)
    data['fields'][0]['name'] = 'position'
    with pytest.raises(ValueError, match='observation layout: expected'):
        ObservationSpec.from_dict(data)
    with pytest.raises(ValueError, match='d_max must be in'):
        ObservationSpec(origin=np.zeros(3), d_max=0.0)
    with pytest.raises(ValueError, match='ray_directions must be'):
        ObservationSpec(origin=np.zeros(3), d_max=1.0, ray_directions=2 * RAY_DIRECTIONS)


def test_contract_round_trips_through_json(spec) -> None:
    c = PolicyContract(catheter=CatheterConfig(theta_max=math.radians(75)), observation=spec,
                       anatomy='elongated', mode='dynamic',
                       training={'curriculum_theta_max_deg': [90, 75]})
    back = PolicyContract.from_json(c.to_json())
    assert back.to_dict() == c.to_dict()
    assert back.catheter == c.catheter and back.observation.same_as(spec)
    with pytest.raises(ValueError, match="mode must be 'static' or 'dynamic'"):
        PolicyContract(catheter=MODEL, observation=spec, anatomy='default', mode='beating')
    with pytest.raises(ValueError, match='contract: expected JSON'):
        PolicyContract.from_json('{')


def test_the_ray_set_is_unit_vectors_in_rings() -> None:
    assert RAY_DIRECTIONS.shape == (25, 3) and not RAY_DIRECTIONS.flags.writeable
    np.testing.assert_allclose(np.linalg.norm(RAY_DIRECTIONS, axis=1), 1.0, atol=1e-15)
    polar = np.degrees(np.arccos(RAY_DIRECTIONS[:, 1]))
    assert polar == pytest.approx([0] + [30] * 8 + [60] * 8 + [90] * 8, abs=1e-9)
    assert ObservationConfig() == ObservationConfig(position_scale=0.15, ray_length=0.04)


def test_a_bent_introducer_seeds_its_nodes_with_rotations_along_it() -> None:
    """A body seeded with a bent introducer: its nodes, arc lengths along them, rotations that
    face along each segment (no twist), and the start pose last."""
    intro = np.array([[0.0, -0.03, 0.0], [0.0, -0.02, 0.0], [0.005, -0.01, 0.0]])
    positions, rotations, arc = np.zeros((6, 3)), np.zeros((6, 3, 3)), np.zeros(6)
    n = seed_body(positions, rotations, arc, intro, np.zeros(3), np.eye(3))
    assert n == 4
    assert np.array_equal(positions[:4], np.vstack([intro, np.zeros(3)]))
    seg = np.linalg.norm(np.diff(positions[:4], axis=0), axis=1)
    assert arc[:4] == pytest.approx(np.concatenate([[0.0], np.cumsum(seg)]), abs=1e-15)
    assert np.array_equal(rotations[3], np.eye(3))
    headings = [np.array([0.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.0]),
                np.array([0.5, 1.0, 0.0]) / math.sqrt(1.25)]
    for j, h in enumerate(headings):
        r = rotations[j]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(r[:, 1], h, atol=1e-12)
        np.testing.assert_allclose(r[:, 2], [0.0, 0.0, 1.0], atol=1e-12)  # turned about z only
    # retraction slides the tip back along the bent introducer to its proximal end
    before = arc.copy()
    k, moved = retract_chain(positions, arc, n, 0.012)
    assert (k, moved) == (3, pytest.approx(0.012, abs=1e-15))  # on the bent segment 1-2
    assert positions[k - 1] == pytest.approx(
        intro[1] + (before[3] - 0.012 - before[1]) * headings[2], abs=1e-12)
    k, moved = retract_chain(positions, arc, k, 1.0)
    assert k == 1 and positions[0] == pytest.approx(intro[0], abs=0)


def test_the_batch_grows_to_hold_a_long_introducer() -> None:
    intro = np.column_stack([np.zeros(12), np.linspace(-0.06, -0.005, 12), np.zeros(12)])
    batch = CatheterBatch(1, MODEL, capacity=4)
    batch.reset_env(0, np.zeros(3), np.eye(3), intro)
    assert batch.n_nodes[0] == 13 and batch.capacity >= 14
    assert np.array_equal(batch.body(0), np.vstack([intro, np.zeros(3)]))
    with pytest.raises(ValueError, match='introducer must not turn back on itself'):
        batch.reset_env(0, np.zeros(3), np.eye(3), np.array([[0.0, 0.03, 0.0],
                                                              [0.0, 0.02, 0.0]]))

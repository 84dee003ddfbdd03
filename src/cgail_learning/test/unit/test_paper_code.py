"""The ``paper_code`` env option set: each variant in its owner, tested on its own numbers.

The expected values come from ``docs/fidelity.md`` ("Numbers the option set needs"), from the
authors' scene (``shared/design/AUTHORS_SCENE.md``, named by its table and row) and files of
``chiaralambranzi/ral_pathplan@fe0d2618`` (named by path), or from geometry worked out by hand
(a straight tube of known radius), never from the code under test; every comparison has a
tolerance.
"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cgail_learning.config import config_from_dict
from cgail_learning.errors import ConfigError, LearningError
from cgail_learning.evaluate import evaluation_options, observation_at
from cgail_sim.config import EnvConfig, OPTION_SETS, PAPER_CODE_MAX_STEPS
from cgail_sim.env import CatheterNavEnv
from cgail_sim.ftl_model import (
    CatheterConfig,
    obs_layout,
    ObservationConfig,
    ObservationSpec,
    observe_batch,
    observe_pose,
    PolicyContract,
    PROBE_OFFSETS,
    PROBE_RANGE,
    quaternion_nb,
    sensor_points,
)
from cgail_sim.heartbeat import (
    Heartbeat,
    HeartbeatConfig,
    paper_code_breakpoints,
    paper_code_position,
)
from cgail_sim.reward import (
    bending_event,
    compute_reward,
    PAPER_CODE_REWARD,
    reached_target,
    RewardConfig,
    StepEvents,
    update_waypoints,
)
from cgail_sim.scenarios import (
    episode_bounds,
    paper_code_exit_box,
    PAPER_CODE_EXIT_MARGINS,
)
from cgail_sim.wall import StaticWall

PAPER = ObservationConfig(kind='paper_code')
TUBE_RADIUS = 0.0075  # m


@pytest.fixture(scope='module')
def paper_env() -> CatheterNavEnv:
    return CatheterNavEnv(EnvConfig.from_options('paper_code'))


@pytest.fixture(scope='module')
def tube() -> StaticWall:
    """A straight open tube of radius 7.5 mm along world y, from -60 to +60 mm (256 facets:
    the facets lie within 0.6 um of the circle)."""
    n, rings = 256, 25
    ang = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    ys = np.linspace(-0.06, 0.06, rings)
    verts = np.array([[TUBE_RADIUS * math.cos(a), y, TUBE_RADIUS * math.sin(a)]
                      for y in ys for a in ang])
    faces = []
    for k in range(rings - 1):
        for j in range(n):
            a, b = k * n + j, k * n + (j + 1) % n
            faces += [[a, b, a + n], [b, b + n, a + n]]
    faces = np.array(faces)
    return StaticWall(SimpleNamespace(vertices=verts, faces=faces,
                                      wall_face_mask=np.ones(len(faces), dtype=bool)))


def probe_values(wall: StaticWall, p_mm, r) -> np.ndarray:
    """The 16 observed probe values of tip pose ``[r | p]`` (p in mm) in ``wall``."""
    spec = ObservationSpec(origin=np.zeros(3), d_max=0.3, config=PAPER)
    p = 1e-3 * np.asarray(p_mm, dtype=float)
    readings = wall.distance(sensor_points(spec, p[None], r[None])[0], PROBE_RANGE)
    return observe_pose(spec, p, r, p + np.array([0.0, 0.05, 0.0]), readings)[11:]


# ------------------------------------------------------------------ observation
def test_probe_geometry_is_two_rings_of_eight_in_the_tip_frame() -> None:
    assert PROBE_OFFSETS.shape == (16, 3)
    np.testing.assert_allclose(PROBE_OFFSETS[0], [0.007, 0.001, 0.0], atol=1e-12)
    np.testing.assert_allclose(PROBE_OFFSETS[2], [0.0, 0.001, 0.007], atol=1e-12)  # 90 deg
    np.testing.assert_allclose(PROBE_OFFSETS[8], [0.009, 0.015, 0.0], atol=1e-12)
    np.testing.assert_allclose(PROBE_OFFSETS[12], [-0.009, 0.015, 0.0], atol=1e-12)  # 180 deg
    np.testing.assert_allclose(np.hypot(PROBE_OFFSETS[:, 0], PROBE_OFFSETS[:, 2]),
                               [0.007] * 8 + [0.009] * 8, atol=1e-12)


def test_probes_on_the_axis_of_a_straight_tube(tube) -> None:
    """Ring 0 (7 mm) is 0.5 mm from the 7.5 mm wall: it reads 0.5; ring 1 (9 mm) is 1.5 mm
    beyond it: it reads 1, as free space does."""
    values = probe_values(tube, [0.0, 0.0, 0.0], np.eye(3))
    np.testing.assert_allclose(values[:8], 0.5, atol=2e-3)
    np.testing.assert_allclose(values[8:], 1.0, atol=0.0)


@pytest.mark.parametrize(('rotation', 'expected'), [
    # tip 0.2 mm off the axis along world x, heading along the tube (y_A = world y)
    (np.eye(3), {0: 0.3, 4: 0.7, 2: 0.4971, 6: 0.4971}),
    # turned 90 deg about the heading: x_A = -world z, z_A = world x (Ry(+90 deg))
    (Rotation.from_euler('y', 90, degrees=True).as_matrix(),
     {2: 0.3, 6: 0.7, 0: 0.4971, 4: 0.4971}),
])
def test_probes_follow_the_tip_frame(tube, rotation, expected) -> None:
    """Off-axis by 0.2 mm: the probe towards the wall at 7.2 mm reads 0.3, the opposite one
    (6.8 mm) 0.7, the ones at 90 deg (sqrt(7^2 + 0.2^2) = 7.00286 mm) 0.4971."""
    values = probe_values(tube, [0.2, 0.0, 0.0], rotation)
    for j, want in expected.items():
        assert values[j] == pytest.approx(want, abs=2e-3), (j, values)
    np.testing.assert_allclose(values[8:], 1.0, atol=0.0)


def test_a_probe_reads_one_beyond_its_range(tube) -> None:
    """1.2 mm off the axis: the far probe is 1.7 mm from the wall, beyond 0.8 mm: 1; the near
    one is 8.2 mm out, 0.7 mm beyond the wall: 0.7 (the distance to the surface)."""
    values = probe_values(tube, [1.2, 0.0, 0.0], np.eye(3))
    assert values[4] == 1.0
    assert values[0] == pytest.approx(0.7, abs=2e-3)


def test_quaternion_is_x_y_z_w_with_w_non_negative() -> None:
    q = np.empty(4)
    quaternion_nb(Rotation.from_euler('z', 90, degrees=True).as_matrix(), q)
    np.testing.assert_allclose(q, [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    quaternion_nb(Rotation.from_euler('x', 270, degrees=True).as_matrix(), q)  # w < 0 flipped
    np.testing.assert_allclose(q, [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)], atol=1e-12)
    rots = Rotation.random(200, random_state=4)
    for m, want in zip(rots.as_matrix(), rots.as_quat(canonical=True), strict=True):
        quaternion_nb(m, q)
        np.testing.assert_allclose(q, want, atol=1e-12)
        assert q[3] >= 0.0


def test_paper_code_observation_layout_and_values() -> None:
    """Tip 10 mm from the origin in x, target 30 / 40 mm away in x / y: position (10, 0, 0) mm,
    direction (0.6, 0.8, 0), distance 50 mm / 50 mm = 1."""
    spec = ObservationSpec(origin=np.array([0.1, 0.2, 0.3]), d_max=0.3, config=PAPER)
    assert spec.dim == 27 and [f.name for f in obs_layout(16, 'paper_code')] == [
        'tip_position', 'tip_quaternion', 'target_direction', 'target_distance', 'probes']
    p = np.array([0.11, 0.2, 0.3])
    obs = observe_pose(spec, p, np.eye(3), p + np.array([0.03, 0.04, 0.0]),
                       np.full(16, np.inf))
    np.testing.assert_allclose(obs[0:3], [10.0, 0.0, 0.0], atol=1e-4)
    np.testing.assert_allclose(obs[3:7], [0.0, 0.0, 0.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(obs[7:10], [0.6, 0.8, 0.0], atol=1e-6)
    assert obs[10] == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_array_equal(obs[11:], 1.0)


def test_paper_code_observation_forms_agree() -> None:
    rng = np.random.default_rng(5)
    spec = ObservationSpec(origin=np.array([0.01, -0.02, 0.03]), d_max=0.27, config=PAPER)
    n = 16
    p = rng.normal(0.0, 0.05, (n, 3))
    r = Rotation.random(n, random_state=6).as_matrix()
    g = rng.normal(0.0, 0.05, (n, 3))
    d = np.where(rng.random((n, 16)) < 0.5, rng.uniform(0.0, 8e-4, (n, 16)), np.inf)
    batch = observe_batch(spec, p, r, g, d)
    assert batch.dtype == np.float32 and batch.shape == (n, 27)
    for i in range(n):
        assert np.array_equal(observe_pose(spec, p[i], r[i], g[i], d[i]), batch[i])
    fired = np.isfinite(d)
    np.testing.assert_allclose(batch[:, 11:][fired], 1e3 * d[fired], rtol=1e-6)
    assert (batch[:, 11:][~fired] == 1.0).all()


def test_the_env_observes_27_floats_and_passes_check_env(paper_env) -> None:
    from gymnasium.utils.env_checker import check_env

    assert paper_env.observation_space.shape == (27,)
    obs, _ = paper_env.reset(seed=0)
    eng = paper_env.engine
    np.testing.assert_allclose(obs[0:3], 1e3 * (eng.catheter.tip_position[0] - eng.spec.origin),
                               rtol=1e-6)
    check_env(paper_env, skip_render_check=True)


def test_evaluate_observes_the_paper_code_pose(paper_env) -> None:
    obs, _ = paper_env.reset(seed=1, options={'start': 0, 'target': 1})
    for _ in range(5):
        obs, *_ = paper_env.step(np.array([0.2, -0.3, 1.0], np.float32))
    eng = paper_env.engine
    mine = observation_at(paper_env, eng.catheter.tip_position[0].copy(),
                          eng.catheter.tip_rotation[0].copy())
    np.testing.assert_array_equal(mine, obs)


# ------------------------------------------------------------------ insertion
def test_forward_only_insertion_advances_on_a_negative_a2(paper_env) -> None:
    ours = CatheterNavEnv(EnvConfig())
    for env, sign in ((paper_env, 1.0), (ours, -1.0)):
        env.reset(seed=0, options={'start': 1, 'target': 0})
        tip0 = env.catheter.tip_position[0].copy()
        heading = env.catheter.tip_rotation[0][:, 1].copy()
        _, _, _, _, info = env.step(np.array([0.0, 0.0, -1.0], np.float32))
        assert info['insertion'] == pytest.approx(sign * 5e-4, abs=1e-12)
        moved = env.catheter.tip_position[0] - tip0
        np.testing.assert_allclose(moved, sign * 5e-4 * heading, atol=1e-9)
    assert CatheterConfig(forward_only=True) != CatheterConfig()


# ------------------------------------------------------------------ reward
def test_paper_code_reward_values() -> None:
    """Per 0.1 s decision: AUTHORS_SCENE.md, "Agent": ``DecisionRequester.DecisionPeriod`` 5
    and ``TakeActionsBetweenDecisions`` 1 at the 0.02 s physics step, so ``Planner.cs``'s
    -1e-5 (``FixedUpdate``) and +1e-5 (``OnActionReceived``) per physics step are paid 5 times
    a decision: -5e-5 and +5e-5. r_centerline +0.005 and the 0.5 bend threshold:
    ``Assets/Planner.cs`` (fidelity.md, "Numbers" 4)."""
    r = PAPER_CODE_REWARD
    assert (r.r_obst, r.r_exit, r.r_target) == (-1.0, -1.0, 1.0)
    assert r.r_step == pytest.approx(5 * -1e-5, rel=1e-12)
    assert r.r_bending == pytest.approx(5 * 1e-5, rel=1e-12)
    assert (r.r_centerline, r.bend_threshold, r.bend_rule) == (0.005, 0.5, 'action')
    events = StepEvents(collision=np.array([False, True, False]),
                        exited=np.array([False, False, True]),
                        success=np.array([True, False, False]),
                        new_waypoints=np.array([2, 0, 0]),
                        bending=np.array([True, False, False]))
    terms, done = compute_reward(events, r)
    np.testing.assert_allclose(terms.total, [1.0 - 5e-5 + 0.01 + 5e-5, -1.0 - 5e-5,
                                             -1.0 - 5e-5], atol=1e-12)
    assert done.all()


def test_paper_code_reach_radii() -> None:
    """AUTHORS_SCENE.md, "Colliders and radii": the ``Target`` sphere collider (radius 0.5 x
    scale 8 = 4 mm) touches the tip's (0.5 x scale 5 = 2.5 mm) at 6.5 mm between centres; a
    centreline waypoint (``Assets/Centerline.prefab``: radius 0.5 x scale 2 = 1 mm) at
    1 + 2.5 = 3.5 mm."""
    r = PAPER_CODE_REWARD
    assert r.epsilon == pytest.approx(0.5 * 8e-3 + 0.5 * 5e-3, abs=1e-12)
    assert r.waypoint_radius == pytest.approx(0.5 * 2e-3 + 0.5 * 5e-3, abs=1e-12)
    target = np.zeros((2, 3))
    tips = np.array([[0.0064, 0.0, 0.0], [0.0, 0.0066, 0.0]])
    np.testing.assert_array_equal(reached_target(tips, target, r), [True, False])
    waypoints = np.array([[[0.0034, 0.0, 0.0], [0.0, 0.0, 0.0036]]])
    reached = np.zeros((1, 2), dtype=bool)
    assert update_waypoints(np.zeros((1, 3)), waypoints, reached, r).tolist() == [1]
    np.testing.assert_array_equal(reached, [[True, False]])


def test_bending_on_the_action_fires_without_insertion() -> None:
    act = np.array([[0.6, 0.0, 0.0], [0.0, -0.55, 1.0], [0.45, -0.5, 1.0], [1.7, 0.0, -1.0]])
    zero = np.zeros(4)
    fired = bending_event(zero, zero, zero, PAPER_CODE_REWARD, act)
    np.testing.assert_array_equal(fired, [True, True, False, True])
    # ours: no bend is applied without insertion, so nothing fires
    assert not bending_event(zero, zero, zero, RewardConfig(), act).any()
    with pytest.raises(ValueError, match="bend_rule 'action' needs the actions, found None"):
        bending_event(zero, zero, zero, PAPER_CODE_REWARD)
    with pytest.raises(ValueError, match="bend_rule must be one of"):
        RewardConfig(bend_rule='applid')


def test_the_env_pays_the_paper_code_reward(paper_env) -> None:
    paper_env.reset(seed=0, options={'start': 0, 'target': 0})
    info = paper_env.step(np.array([0.6, 0.0, -1.0], np.float32))[4]
    assert info['reward_bending'] == pytest.approx(5e-5)
    waypoints = 0
    for _ in range(60):  # insert along the start heading: waypoints within 3.5 mm pay 0.005
        _, _, te, _, info = paper_env.step(np.array([0.0, 0.0, 1.0], np.float32))
        assert info['reward_centerline'] == pytest.approx(0.005 * info['new_waypoints'])
        assert info['reward_bending'] == 0.0
        waypoints += info['new_waypoints']
        assert not te
    assert waypoints >= 3


# ------------------------------------------------------------------ heartbeat
FIDELITY_BREAKPOINTS = [(0.0, 0.0), (0.10, 1.2767), (0.26, 3.3447), (0.30, 5.2382),
                        (0.42, 2.9281), (0.50, 2.0229), (0.56, 0.6528), (0.70, -1.9077)]


def test_heartbeat_breakpoints_are_the_fidelity_table() -> None:
    times, pos = paper_code_breakpoints()
    assert times[-1] == pytest.approx(0.74)
    assert 1e3 * pos[-1] == pytest.approx(-1.3970, abs=1e-4)  # just before the cycle ends
    for t, mm in FIDELITY_BREAKPOINTS:
        assert 1e3 * paper_code_position(t) == pytest.approx(mm, abs=1e-4), t
        if t > 0.0:  # (the cycle start is the jump back to 0: a later cycle's start time
            # lands on either side of it, by rounding)
            assert 1e3 * paper_code_position(t + 3 * 0.74) == pytest.approx(mm, abs=1e-4), t
    # linear in between, back to 0 at the cycle end
    assert 1e3 * paper_code_position(0.05) == pytest.approx(1.2767 / 2, abs=1e-4)
    assert 1e3 * paper_code_position(0.74 - 1e-9) == pytest.approx(-1.3970, abs=1e-4)
    assert 1e3 * paper_code_position(0.74 + 1e-9) == pytest.approx(0.0, abs=1e-4)


def test_paper_code_heartbeat_pushes_the_root_up_from_below() -> None:
    """AUTHORS_SCENE.md, "Heartbeat pusher": the ``Cylinder`` below the aortic root moves
    along its local +y, world (-0.29, 0.95, 0.10), up into the ascending aorta, and pushes the
    soft root: a one-sided push. So the annulus moves along +root_axis by the pusher's
    position where it is above rest (fidelity.md "Numbers" 5: +5.2382 mm at 0.30 s) and stays
    at rest while the pusher is below it (-1.9077 mm at 0.70 s)."""
    axis = np.array([0.0, 0.6, 0.8])
    hb = Heartbeat(axis, HeartbeatConfig(profile='paper_code'))
    assert hb.config.period == pytest.approx(0.74)
    np.testing.assert_allclose(hb.displacement(0.30), 5.2382e-3 * axis, atol=1e-7)
    np.testing.assert_allclose(hb.displacement(0.05), 0.5 * 1.2767e-3 * axis, atol=1e-7)
    np.testing.assert_allclose(hb.displacement(0.42 + 0.74), 2.9281e-3 * axis, atol=1e-7)
    # below rest from 0.56 + 0.6528 / 18.28874613 s = 0.5957 s to the cycle end: no pull
    for t in (0.60, 0.70, 0.74 - 1e-9, 0.74 * 2):
        np.testing.assert_allclose(hb.displacement(t), 0.0, atol=1e-12)
    assert hb.displacement(0.59) @ axis > 0.0
    assert min(hb.shape(0.01 * k) for k in range(148)) >= 0.0
    np.testing.assert_allclose(hb.peak_displacement, 5.2382e-3 * axis, atol=1e-7)
    with pytest.raises(ValueError, match="profile must be one of"):
        HeartbeatConfig(profile='sine')


def test_the_dynamic_paper_code_env_beats_with_the_profile() -> None:
    env = CatheterNavEnv(EnvConfig.from_options('paper_code', mode='dynamic'))
    wall = env.engine.walls[0]
    assert wall.heartbeat.config.profile == 'paper_code'
    np.testing.assert_allclose(wall.heartbeat.displacement(0.30),
                               5.2382e-3 * wall.heartbeat.root_axis, atol=1e-7)


# ------------------------------------------------------------------ episode end
def test_paper_code_has_a_step_limit_that_does_not_bind() -> None:
    """AUTHORS_SCENE.md, "Agent": ``MaxStep`` 0, no episode step limit. The longest episode
    the authors recorded ended at ``StepCount`` 18,668 physics steps
    (``Assets/OutPath/old1/distance.txt``), 3,734 decisions; the limit is 5x that."""
    cfg = EnvConfig.from_options('paper_code')
    assert cfg.max_steps == PAPER_CODE_MAX_STEPS >= 5 * math.ceil(18_668 / 5)
    assert EnvConfig().max_steps == 2000 and EnvConfig.from_options('ours').max_steps == 2000
    with pytest.raises(ValueError, match=r"env options 'paper_code' fix \['max_steps'\]"):
        EnvConfig.from_options('paper_code', max_steps=200)


def test_paper_code_exit_box_margins() -> None:
    """AUTHORS_SCENE.md, "Exit": the six ``Plane`` objects bound x -133..115, y -573..-287,
    z -184..55 (mm); ``Assets/centerline.txt`` (columns x, z, y: ``Planner.Start``) spans
    x -37.27..21.88, y -511.79..-399.53, z -117.25..-68.37. Their x, y, z are our x, z, y."""
    box = {'x': (-133.0, 115.0), 'y': (-573.0, -287.0), 'z': (-184.0, 55.0)}
    line = {'x': (-37.27, 21.88), 'y': (-511.79, -399.53), 'z': (-117.25, -68.37)}
    ours_axis = {'x': 0, 'y': 2, 'z': 1}  # their axis -> ours
    low, high = np.asarray(PAPER_CODE_EXIT_MARGINS)
    for theirs, k in ours_axis.items():
        assert 1e3 * low[k] == pytest.approx(line[theirs][0] - box[theirs][0], abs=1e-6)
        assert 1e3 * high[k] == pytest.approx(box[theirs][1] - line[theirs][1], abs=1e-6)
    wp = {'a': np.array([[0.0, 0.0, 0.0], [0.01, -0.02, 0.03]]),
          'b': np.array([[0.0, 0.05, 0.0]])}
    lo, hi = paper_code_exit_box(wp)
    np.testing.assert_allclose(lo, [-0.09573, -0.02 - 0.06675, -0.06121], atol=1e-12)
    np.testing.assert_allclose(hi, [0.01 + 0.09312, 0.05 + 0.12337, 0.03 + 0.11253],
                               atol=1e-12)


def test_the_paper_code_env_exits_at_the_box_only(paper_env) -> None:
    """paper_code: no open-end disc, the box around the centreline; ours keeps both."""
    eng = paper_env.engine
    assert eng.exit_discs.shape == (0, 7)
    lo, hi = paper_code_exit_box(eng.scenarios.waypoints)
    np.testing.assert_array_equal(eng.bbox_low, lo)
    np.testing.assert_array_equal(eng.bbox_high, hi)
    ours = CatheterNavEnv(EnvConfig()).engine
    assert ours.exit_discs.shape[0] > 0
    lo, hi = episode_bounds(ours.world.anatomy)
    np.testing.assert_array_equal(ours.bbox_low, lo)
    np.testing.assert_array_equal(ours.bbox_high, hi)
    with pytest.raises(ValueError, match="exit_rule must be one of"):
        EnvConfig(exit_rule='planes')


# ------------------------------------------------------------------ the option set
def test_option_sets_name_their_values() -> None:
    assert EnvConfig().options == 'ours'
    cfg = EnvConfig.from_options('paper_code', mode='dynamic')
    assert (cfg.options, cfg.mode, cfg.observation_kind, cfg.forward_only) == (
        'paper_code', 'dynamic', 'paper_code', True)
    assert cfg.reward == PAPER_CODE_REWARD and cfg.heartbeat.profile == 'paper_code'
    assert cfg.exit_rule == 'box' and EnvConfig().exit_rule == 'discs'
    assert cfg.catheter.forward_only and cfg.observation.kind == 'paper_code'
    assert dataclasses.replace(cfg, forward_only=False).options == 'custom'
    assert EnvConfig().with_options('paper_code') == EnvConfig.from_options('paper_code')
    assert sorted(OPTION_SETS) == ['ours', 'paper_code', 'sphere_targets']


def test_bad_option_set_names_are_one_line_errors() -> None:
    with pytest.raises(ValueError, match=r"env options: expected one of \['ours', "
                                         r"'paper_code', 'sphere_targets'\], found 'paper'"):
        EnvConfig.from_options('paper')
    with pytest.raises(ValueError, match=r"env options 'paper_code' fix \['forward_only'\]"):
        EnvConfig.from_options('paper_code', forward_only=False)
    with pytest.raises(ValueError, match="observation_kind must be one of"):
        EnvConfig(observation_kind='unity')
    with pytest.raises(ConfigError, match=r"env_options must be one of \['ours', "
                                          r"'paper_code', 'sphere_targets'\], found "
                                          r"'papercode'"):
        config_from_dict({'env_options': 'papercode'})


def test_contract_carries_the_option_set(paper_env) -> None:
    from cgail_learning.train import sim_metadata
    from cgail_sim.ftl_model import CONTRACT_KEY

    data = sim_metadata(paper_env.config)[CONTRACT_KEY]
    assert data['env_options'] == 'paper_code' and data['observation']['dim'] == 27
    assert data['catheter']['forward_only'] is True
    assert data['action_scaling']['delta_l'].startswith('|a[2]|')
    back = PolicyContract.from_dict(data)
    assert back.observation.same_as(paper_env.engine.spec) and back.catheter.forward_only
    old = {k: v for k, v in data.items() if k != 'env_options'}
    old['observation'] = {k: v for k, v in ObservationSpec(
        origin=np.zeros(3), d_max=0.3).to_dict().items() if k != 'kind'}
    legacy = PolicyContract.from_dict(old)  # written before the option sets: ours
    assert legacy.env_options == 'ours' and legacy.observation.kind == 'ours'
    bad = {**data, 'observation': {**data['observation'], 'probe_range_m': 0.001}}
    with pytest.raises(ValueError, match=r"observation probe_range_m: expected 0.0008, "
                                         r"found 0.001"):
        PolicyContract.from_dict(bad)


def test_evaluate_runs_in_the_policies_option_set() -> None:
    def pol(opt):
        return SimpleNamespace(contract=SimpleNamespace(env_options=opt))

    assert evaluation_options({'a': pol('paper_code'), 'b': pol('paper_code')}) == 'paper_code'
    assert evaluation_options({}) == 'ours'
    assert evaluation_options({}, 'paper_code') == 'paper_code'
    with pytest.raises(LearningError, match='expected one env option set'):
        evaluation_options({'a': pol('paper_code'), 'b': pol('ours')})
    with pytest.raises(LearningError, match="--env-options 'ours': expected the policies'"):
        evaluation_options({'a': pol('paper_code')}, 'ours')
    with pytest.raises(ValueError, match='env options: expected one of'):
        evaluation_options({}, 'paper')

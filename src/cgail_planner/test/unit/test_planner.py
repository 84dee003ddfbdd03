"""Planner core: policy rollout in a model world, centerline baseline, bad input, contract,
replan decisions.

The numbers come from the catheter model (:mod:`cgail_sim.ftl_model`): the step length,
the bend limit and the catheter radius are read from :class:`CatheterConfig`, not typed here.
The rollout's parity with the simulator is ``test_model_parity.py``.
"""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from cgail_planner.core.errors import ContractError, InvalidInputError, NoPathError
from cgail_planner.core.planner import (
    ModelWorld,
    Planner,
    PlannerConfig,
    reconcile_contract,
    replan_reason,
    ReplanConfig,
)
from cgail_sim.contact import Contact
from cgail_sim.exits import disc_array
from cgail_sim.ftl_model import (
    CatheterConfig,
    ObservationConfig,
    ObservationSpec,
    PolicyContract,
    RAY_DIRECTIONS,
)

FIXTURES = Path(__file__).resolve().parents[1] / 'fixtures'
MODEL = CatheterConfig()
STEP = MODEL.max_step_insertion  # insertion per step at full action


class OpenSpace:
    """A wall that is never hit (rays return their full length, the tip never touches)."""

    def raycast(self, origins, directions, max_dist):
        return np.full(len(origins), max_dist)

    def tip_contact(self, tip, radius, dt):
        return Contact(penetration=0.0, force=0.0, normal=np.zeros(3), in_contact=False,
                       clearance=math.inf)


class Plane(OpenSpace):
    """A wall plane y = y0 with the lumen below it (hit when a ray heads towards it)."""

    def __init__(self, y0: float) -> None:
        self.y0 = y0
        self.queries = 0

    def raycast(self, origins, directions, max_dist):
        dy = directions[:, 1]
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (self.y0 - origins[:, 1]) / dy
        return np.where((dy > 0) & (t >= 0), np.minimum(t, max_dist), max_dist)

    def tip_contact(self, tip, radius, dt):
        self.queries += 1
        depth = tip[1] + radius - self.y0
        return Contact(penetration=max(depth, 0.0), force=0.0, normal=np.array([0.0, 1.0, 0.0]),
                       in_contact=depth >= 0.0, clearance=max(-depth, 0.0))


def box_world(**extra) -> ModelWorld:
    """A 1 m box around the origin; the open (exit) end is a disc across the box in the plane
    y = -0.10025 (normal -y; a quarter step off the step grid)."""
    line = np.column_stack([np.zeros(50), np.linspace(0, 0.2, 50), np.zeros(50)])
    bend = np.column_stack([np.linspace(0, 0.05, 50), np.full(50, 0.2), np.zeros(50)])
    return ModelWorld(
        origin=np.zeros(3), d_max=0.3, bbox_low=np.full(3, -0.5), bbox_high=np.full(3, 0.5),
        centerlines={'left': line, 'right': np.vstack([line, bend[1:]])},
        ostia={'left': np.array([0.0, 0.2, 0.0]), 'right': np.array([0.05, 0.2, 0.0])},
        contains=lambda pts: np.linalg.norm(pts, axis=1) < 0.4,
        exit_point=np.array([0.0, -0.10025, 0.0]), exit_normal=np.array([0.0, -1.0, 0.0]),
        exit_discs=disc_array(np.array([[0.0, -0.10025, 0.0]]), np.array([[0.0, -1.0, 0.0]]),
                              np.array([0.5])), **extra)


def constant(action):
    def policy(obs):
        policy.last_obs = obs.copy()
        return np.asarray(action, dtype=np.float32)
    return policy


def test_straight_rollout_reaches_the_goal_and_ends_on_it() -> None:
    planner = Planner(PlannerConfig(), box_world(), OpenSpace(), constant([0, 0, 1]))
    goal = np.array([0.0, 0.05, 0.0])
    res = planner.plan(np.zeros(3), np.eye(3), goal)
    # full steps along y: within the goal tolerance (to rounding) 40 mm on
    steps = round((0.05 - PlannerConfig().goal_tolerance) / STEP)
    assert res.steps == steps
    assert res.raw[-1] == pytest.approx(goal)
    assert res.raw[-2] == pytest.approx([0.0, steps * STEP, 0.0])
    assert res.path[0] == pytest.approx([0, 0, 0], abs=1e-12)
    assert res.path[-1] == pytest.approx(goal, abs=1e-12)
    spacing = np.linalg.norm(np.diff(res.path, axis=0), axis=1)
    assert spacing == pytest.approx(np.full(len(spacing), PlannerConfig().path_spacing), rel=1e-6)


def test_rollout_bends_by_theta_max_dl_over_l_per_step() -> None:
    """Full alpha for n steps turns the heading by n * theta_max * dl / L about x_A."""
    cfg = PlannerConfig(max_rollout_steps=10)
    planner = Planner(cfg, box_world(), OpenSpace(), constant([1, 0, 1]))
    with pytest.raises(NoPathError, match='did not reach the goal within 10 steps'):
        planner.rollout(np.zeros(3), np.eye(3), np.array([0.0, 0.3, 0.0]))
    obs = planner.policy.last_obs  # observation before step 10: 9 steps taken
    angle = 9 * MODEL.theta_max * STEP / MODEL.segment_length
    assert obs[6:9] == pytest.approx([0.0, math.cos(angle), math.sin(angle)], abs=1e-6)


@pytest.mark.parametrize('theta_max', [math.pi / 2, math.radians(60)])
def test_the_rollout_uses_the_configured_catheter_model(theta_max) -> None:
    model = CatheterConfig(theta_max=theta_max, segment_length=0.04)
    planner = Planner(PlannerConfig(max_rollout_steps=5, catheter=model), box_world(),
                      OpenSpace(), constant([1, 0, 1]))
    with pytest.raises(NoPathError) as info:
        planner.rollout(np.zeros(3), np.eye(3), np.array([0.0, 0.3, 0.0]))
    tip = info.value.points[-1]
    k = theta_max * model.max_step_insertion / model.segment_length  # turn per step
    turns = np.arange(1, 6) * k
    expected = model.max_step_insertion * np.array([0.0, np.cos(turns).sum(),
                                                    np.sin(turns).sum()])
    assert tip == pytest.approx(expected, abs=1e-12)


def test_the_observation_is_the_models() -> None:
    from cgail_sim.ftl_model import observe_pose

    world = box_world()
    planner = Planner(PlannerConfig(), world, OpenSpace(), constant([0, 0, 1]))
    rng = np.random.default_rng(0)
    p, goal, hits = rng.normal(0, 0.05, 3), rng.normal(0, 0.05, 3), rng.uniform(0, 0.06, 25)
    r = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    r *= np.linalg.det(r)
    spec = ObservationSpec(origin=world.origin, d_max=world.d_max)
    assert np.array_equal(planner.observation(p, r, goal, hits),
                          observe_pose(spec, p, r, goal, hits))


def test_rollout_fails_when_the_tip_sphere_touches_the_wall() -> None:
    wall = Plane(0.02025)  # a quarter step off the step grid: no tie at the last bit
    planner = Planner(PlannerConfig(), box_world(), wall, constant([0, 0, 1]))
    # the tip sphere crosses the plane once the tip is past y0 - radius
    step = math.floor((wall.y0 - MODEL.radius) / STEP) + 1
    with pytest.raises(NoPathError, match=f'touched the wall at step {step} at'):
        planner.plan(np.zeros(3), np.eye(3), np.array([0.0, 0.05, 0.0]))
    # the exact clearance bounds the queries: one at the start, one when it runs out
    assert wall.queries == 2


def test_rollout_fails_when_the_tip_leaves_through_the_exit_plane() -> None:
    planner = Planner(PlannerConfig(), box_world(), OpenSpace(), constant([0, 0, -1]))
    # retraction slides back along the introducer, which starts 5 mm beyond the exit plane
    step = math.floor(0.10025 / STEP) + 1
    with pytest.raises(NoPathError, match=f'left the anatomy at step {step}$'):
        planner.plan(np.zeros(3), np.eye(3), np.array([0.0, 0.05, 0.0]))


def test_retraction_slides_back_along_the_body_and_the_introducer() -> None:
    calls = []
    scale = ObservationConfig().position_scale

    def policy(obs):
        calls.append(obs[1] * scale)
        return np.array([0, 0, 1.0 if len(calls) <= 4 else -1.0], dtype=np.float32)

    planner = Planner(PlannerConfig(max_rollout_steps=9), box_world(), OpenSpace(), policy)
    with pytest.raises(NoPathError) as info:
        planner.rollout(np.zeros(3), np.eye(3), np.array([0.0, 0.3, 0.0]))
    # 4 steps in, then back along the body past the start pose onto the introducer
    assert calls == pytest.approx(np.array([0, 1, 2, 3, 4, 3, 2, 1, 0]) * STEP, abs=1e-7)
    np.testing.assert_allclose(info.value.points, [[0.0, -STEP, 0.0]], rtol=0, atol=1e-12)


def test_centerline_path_follows_the_nearest_ostium_branch_and_is_cut_at_the_goal() -> None:
    planner = Planner(PlannerConfig(planner_type='centerline'), box_world(), OpenSpace(), None)
    goal = np.array([0.03, 0.2, 0.0])  # nearer the right ostium
    res = planner.plan(np.array([0.001, 0.05, 0.0]), np.eye(3), goal)
    assert res.planner_type == 'centerline' and res.steps == 0
    assert res.raw[0] == pytest.approx([0.001, 0.05, 0.0])
    assert res.raw[-1] == pytest.approx(goal)
    # the right branch turns along +x at y = 0.2 and is cut at the goal (x <= 0.03)
    assert res.raw[:, 0].max() == pytest.approx(0.03, abs=1e-12)
    assert res.path[-1] == pytest.approx(goal, abs=1e-12)


@pytest.mark.parametrize(('position', 'rotation', 'goal', 'match'), [
    ((np.nan, 0, 0), np.eye(3), (0, 0.05, 0), 'tip pose must be finite'),
    ((0, 0, 0), 2 * np.eye(3), (0, 0.05, 0), 'tip orientation must be a rotation'),
    ((0, 0, 0), np.eye(3), (0, np.inf, 0), 'goal must be a finite'),
    ((0, 0, 0), np.eye(3), (0.45, 0, 0), 'goal must lie inside the lumen'),
])
def test_bad_input_is_rejected_with_the_reason(position, rotation, goal, match) -> None:
    planner = Planner(PlannerConfig(planner_type='centerline'), box_world(), OpenSpace(), None)
    with pytest.raises(InvalidInputError, match=match):
        planner.plan(np.array(position, dtype=float), rotation, np.array(goal, dtype=float))


def test_cgail_needs_a_policy_of_the_right_size() -> None:
    with pytest.raises(ValueError, match="'cgail' needs a policy"):
        Planner(PlannerConfig(), box_world(), OpenSpace(), None)
    with pytest.raises(ValueError, match='observation size must be 41'):
        Planner(PlannerConfig(), box_world(), OpenSpace(), constant([0, 0, 1]), RAY_DIRECTIONS,
                obs_dim=40)


def test_non_finite_policy_output_fails_the_plan() -> None:
    planner = Planner(PlannerConfig(), box_world(), OpenSpace(), constant([0, np.nan, 1]))
    with pytest.raises(NoPathError, match='policy must return 3 finite actions'):
        planner.plan(np.zeros(3), np.eye(3), np.array([0.0, 0.05, 0.0]))


def test_onnx_straight_policy_fixture_plans_in_the_default_anatomy() -> None:
    from cgail_planner.core.onnx_policy import OnnxPolicy
    from cgail_planner.core.planner import model_world_from_sim
    from cgail_sim.wall import StaticWall
    from cgail_sim.worlds import load_world

    world = load_world('default')
    policy = OnnxPolicy(FIXTURES / 'straight_policy.onnx', expected_obs_dim=41)
    planner = Planner(PlannerConfig(), model_world_from_sim(world), StaticWall(world.anatomy),
                      policy, RAY_DIRECTIONS, obs_dim=policy.obs_dim)
    start = world.scenarios.starts[0]
    heading = start.rotation[:, 1]
    # The goal lies a quarter step off a multiple of the 0.5 mm step beyond the 10 mm
    # tolerance, so the step count does not hang on the last bit of |goal - p| (at 30 mm,
    # 40 steps end exactly 10 mm from the goal: d^2 - tol^2 = -1.9e-18 on one CPU, > 0 on
    # another). The straight policy inserts 0.5 mm a step along the start heading.
    cfg, dist = PlannerConfig(), 0.03025
    step = cfg.catheter.max_step_insertion
    expected = math.ceil((dist - cfg.goal_tolerance) / step)   # 20.25 mm / 0.5 mm -> 41
    goal = start.position + dist * heading
    res = planner.plan(start.position, start.rotation, goal)
    assert res.steps == expected == 41
    np.testing.assert_allclose(res.raw[:-1], start.position + np.outer(
        np.arange(expected + 1) * step, heading), rtol=0, atol=1e-12)
    assert res.path[-1] == pytest.approx(goal, abs=1e-12)


@pytest.mark.parametrize(('kwargs', 'expected'), [
    (dict(cross_track=0.001, goal=(0, 0, 0), since_last_plan_s=5.0), None),
    (dict(cross_track=0.009, goal=(0, 0, 0), since_last_plan_s=5.0),
     'tip left the corridor (9.0 mm from the path)'),
    (dict(cross_track=0.001, goal=(0.004, 0, 0), since_last_plan_s=5.0), 'target moved 4.0 mm'),
    (dict(cross_track=0.05, goal=(0.004, 0, 0), since_last_plan_s=0.5), None),
])
def test_replan_reason(kwargs, expected) -> None:
    got = replan_reason(ReplanConfig(), planned_goal=np.zeros(3),
                        **{**kwargs, 'goal': np.array(kwargs['goal'], dtype=float)})
    assert got == expected


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('planner_type', 'prm', "planner_type must be one of"),
    ('goal_tolerance', 0.0, r'goal_tolerance must be in \(0.0, 0.05\]'),
    ('max_rollout_steps', 0, r'max_rollout_steps must be an int in \[1, 100000\]'),
    ('path_spacing', 1.0, r'path_spacing must be in \[0.0001, 0.01\]'),
    ('catheter', 0.05, 'catheter must be a CatheterConfig'),
])
def test_config_rejects_bad_values(field, value, match) -> None:
    with pytest.raises(ValueError, match=match):
        PlannerConfig(**{field: value})


def contract(**catheter) -> PolicyContract:
    return PolicyContract(catheter=CatheterConfig(**catheter),
                          observation=ObservationSpec(origin=np.zeros(3), d_max=0.3),
                          anatomy='default', mode='static')


def test_settings_that_agree_with_the_contract_or_are_unset_keep_it() -> None:
    c = contract()
    same, notes = reconcile_contract(c, anatomy='default', mode='static', theta_max=None,
                                     segment_length=MODEL.segment_length, override=False)
    assert same is c and notes == []
    _, notes = reconcile_contract(c, anatomy='default', mode='dynamic', theta_max=None,
                                  segment_length=None, override=False)
    assert notes == ['policy trained in the static world runs in the dynamic world']


@pytest.mark.parametrize(('kwargs', 'match'), [
    (dict(theta_max=1.0), r"^theta_max: expected the policy's 1.5708, found parameter 1 "),
    (dict(segment_length=0.04), r"^segment_length: expected the policy's 0.05, found "
                                r"parameter 0.04 "),
    (dict(anatomy='elongated'), r"^anatomy: expected the policy's 'default', found parameter "
                                r"'elongated' "),
])
def test_a_setting_that_disagrees_with_the_contract_is_refused(kwargs, match) -> None:
    args = dict(anatomy='default', mode='static', theta_max=None, segment_length=None,
                override=False) | kwargs
    with pytest.raises(ContractError, match=match):
        reconcile_contract(contract(), **args)


H1, H2 = '606110321e2766a5', '0123456789abcdef'


def test_a_path_anatomy_is_identified_by_its_content_hash() -> None:
    """A path-trained policy records its anatomy's label and content hash: the planner's
    anatomy must have that hash (whatever its directory is called); built-in names compare as
    names (their meshes differ between CPUs)."""
    c = dataclasses.replace(contract(), anatomy='p07', anatomy_hash=H1)
    args = dict(mode='static', theta_max=None, segment_length=None, override=False)
    same, notes = reconcile_contract(c, anatomy='p07_copy', anatomy_hash=H1, **args)
    assert same is c and notes == []
    for anatomy, anatomy_hash, found in (
            ('p08', H2, f"'p08' \\(content hash {H2}\\)"),
            ('default', '', "built-in 'default'")):
        with pytest.raises(ContractError, match=(
                rf"^anatomy: expected the policy's 'p07' \(content hash {H1}\), found parameter "
                rf"{found} \(set override_policy_contract to run anyway\)$")):
            reconcile_contract(c, anatomy=anatomy, anatomy_hash=anatomy_hash, **args)
    with pytest.raises(ContractError, match=(
            rf"^anatomy: expected the policy's built-in 'default', found parameter 'p07' "
            rf"\(content hash {H1}\) ")):
        reconcile_contract(contract(), anatomy='p07', anatomy_hash=H1, **args)
    got, notes = reconcile_contract(c, anatomy='p08', anatomy_hash=H2,
                                    world_spec=ObservationSpec(origin=np.ones(3), d_max=0.25),
                                    **(args | dict(override=True)))
    assert (got.anatomy, got.anatomy_hash) == ('p08', H2)
    assert notes == [f"override_policy_contract: anatomy 'p08' (content hash {H2}) instead of "
                     f"the policy's 'p07' (content hash {H1}) (observed in this anatomy's "
                     "frame)"]


def test_a_contract_round_trips_its_anatomy_hash() -> None:
    c = dataclasses.replace(contract(), anatomy='p07', anatomy_hash=H1)
    back = PolicyContract.from_json(c.to_json())
    assert (back.anatomy, back.anatomy_hash) == ('p07', H1)
    assert 'anatomy_hash' not in contract().to_dict()  # (built-in: as before)
    assert PolicyContract.from_dict(contract().to_dict()).anatomy_hash == ''
    with pytest.raises(ValueError, match="anatomy_hash must be '' or 16 hex digits, found 'xyz'"):
        dataclasses.replace(contract(), anatomy_hash='xyz')


def test_a_population_policy_runs_in_any_anatomy_in_its_frame() -> None:
    """A generalist's contract (anatomies: population) is not tied to the anatomy it was
    selected in: it runs anywhere without an override, observed with that anatomy's origin and
    the d_max of the targets it was trained on (sphere targets: the sphere's bound)."""
    from cgail_planner.core.planner import world_observation_spec
    from cgail_sim.worlds import load_world

    c = dataclasses.replace(contract(), anatomy='population-128', anatomy_hash=H1,
                            anatomies='population', env_options='sphere_targets')
    assert PolicyContract.from_json(c.to_json()).anatomies == 'population'
    assert 'anatomies' not in contract().to_dict()  # (one anatomy: as before)
    args = dict(mode='static', theta_max=None, segment_length=None, override=False)
    with pytest.raises(ContractError, match="a population policy is observed in the frame of "
                                            "the anatomy it runs in"):
        reconcile_contract(c, anatomy='elongated', **args)
    sc = load_world('elongated').scenarios
    world = world_observation_spec(sc, c)
    assert world.d_max == sc.d_max_for('sphere') != sc.d_max
    np.testing.assert_array_equal(world.origin, sc.origin)
    assert world_observation_spec(sc, contract()).d_max == sc.d_max  # fixed targets
    got, notes = reconcile_contract(c, anatomy='elongated', world_spec=world, **args)
    assert (got.anatomy, got.anatomy_hash, got.anatomies) == ('elongated', '', 'population')
    assert got.observation.same_as(world)
    assert len(notes) == 1 and notes[0].startswith(
        "population policy (trained across the anatomy population) runs in built-in "
        "'elongated', observed in its frame (origin [")
    with pytest.raises(ValueError, match="anatomies must be 'one' or 'population', found 'all'"):
        dataclasses.replace(c, anatomies='all')


def test_an_override_applies_the_setting_and_warns() -> None:
    world = ObservationSpec(origin=np.ones(3), d_max=0.25)
    got, notes = reconcile_contract(contract(), anatomy='elongated', mode='static',
                                    theta_max=1.0, segment_length=None, override=True,
                                    world_spec=world)
    assert got.catheter == CatheterConfig(theta_max=1.0)
    assert got.observation.same_as(world)
    assert [n.split(':')[0] for n in notes] == ['override_policy_contract'] * 2
    assert "theta_max 1 instead of the policy's 1.5708" in notes[0]


def test_a_planner_built_from_a_contract_runs_its_model() -> None:
    from cgail_sim.worlds import load_world

    world = load_world('default')
    spec = ObservationSpec.for_world(world.scenarios)
    c = PolicyContract(catheter=CatheterConfig(theta_max=1.0), observation=spec,
                       anatomy='default', mode='static')
    planner = Planner.from_contract(c, world, OpenSpace(), constant([0, 0, 1]),
                                    PlannerConfig(goal_tolerance=0.005))
    assert planner.config.catheter == c.catheter and planner.config.goal_tolerance == 0.005
    assert planner.spec.same_as(spec)
    moved = ObservationSpec(origin=spec.origin + 0.002, d_max=spec.d_max)
    with pytest.raises(ContractError, match='observation origin: expected this anatomy'):
        Planner.from_contract(PolicyContract(catheter=c.catheter, observation=moved,
                                             anatomy='default', mode='static'),
                              world, OpenSpace(), constant([0, 0, 1]))

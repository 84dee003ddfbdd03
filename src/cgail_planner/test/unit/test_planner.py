"""Planner core: policy rollout kinematics, centerline baseline, bad input, replan decisions."""

import math
from pathlib import Path

import numpy as np
import pytest

from cgail_planner.core.planner import (
    InvalidInputError,
    ModelWorld,
    NoPathError,
    Planner,
    PlannerConfig,
    quaternion_from_rotation,
    replan_reason,
    ReplanConfig,
    rotation_from_quaternion,
)
from cgail_planner.sim.env import RAY_DIRECTIONS

FIXTURES = Path(__file__).resolve().parents[1] / 'fixtures'


class OpenSpace:
    """A wall that is never hit (rays return their full length)."""

    def raycast(self, origins, directions, max_dist):
        return np.full(len(origins), max_dist)


class Plane:
    """A wall plane y = y0 (hit when a ray heads towards it)."""

    def __init__(self, y0: float) -> None:
        self.y0 = y0

    def raycast(self, origins, directions, max_dist):
        dy = directions[:, 1]
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (self.y0 - origins[:, 1]) / dy
        return np.where((dy > 0) & (t >= 0), np.minimum(t, max_dist), max_dist)


def box_world(**extra) -> ModelWorld:
    line = np.column_stack([np.zeros(50), np.linspace(0, 0.2, 50), np.zeros(50)])
    bend = np.column_stack([np.linspace(0, 0.05, 50), np.full(50, 0.2), np.zeros(50)])
    return ModelWorld(
        origin=np.zeros(3), d_max=0.3, bbox_low=np.full(3, -0.5), bbox_high=np.full(3, 0.5),
        centerlines={'left': line, 'right': np.vstack([line, bend[1:]])},
        ostia={'left': np.array([0.0, 0.2, 0.0]), 'right': np.array([0.05, 0.2, 0.0])},
        contains=lambda pts: np.linalg.norm(pts, axis=1) < 0.4, **extra)


def constant(action):
    def policy(obs):
        policy.last_obs = obs.copy()
        return np.asarray(action, dtype=np.float32)
    return policy


def test_straight_rollout_reaches_the_goal_and_ends_on_it() -> None:
    planner = Planner(PlannerConfig(), box_world(), OpenSpace(), constant([0, 0, 1]),
                      RAY_DIRECTIONS)
    goal = np.array([0.0, 0.05, 0.0])
    res = planner.plan(np.zeros(3), np.eye(3), goal)
    # 0.5 mm per step: within 10 mm of the goal (up to rounding) after 40 mm -> step 80
    assert res.steps == 80
    assert res.raw[-1] == pytest.approx(goal)
    assert res.raw[-2] == pytest.approx([0.0, 0.040, 0.0])
    assert res.path[0] == pytest.approx([0, 0, 0], abs=1e-12)
    assert res.path[-1] == pytest.approx(goal, abs=1e-12)
    steps = np.linalg.norm(np.diff(res.path, axis=0), axis=1)
    assert steps == pytest.approx(np.full(50, 0.001), rel=1e-6)


def test_rollout_bends_by_theta_max_dl_over_l_per_step() -> None:
    """Full alpha for n steps turns the heading by n * (pi/2) * 0.5 mm / 50 mm about x_A."""
    cfg = PlannerConfig(max_rollout_steps=10)
    planner = Planner(cfg, box_world(), OpenSpace(), constant([1, 0, 1]), RAY_DIRECTIONS)
    with pytest.raises(NoPathError, match='did not reach the goal within 10 steps'):
        planner.rollout(np.zeros(3), np.eye(3), np.array([0.0, 0.3, 0.0]))
    obs = planner.policy.last_obs  # observation before step 10: 9 steps taken
    angle = 9 * (math.pi / 2) * 0.0005 / 0.05
    assert obs[6:9] == pytest.approx([0.0, math.cos(angle), math.sin(angle)], abs=1e-6)


def test_observation_layout_matches_the_environment() -> None:
    world = box_world()
    planner = Planner(PlannerConfig(), world, OpenSpace(), constant([0, 0, 1]), RAY_DIRECTIONS)
    r = rotation_from_quaternion(0.0, 0.0, math.sin(0.3), math.cos(0.3))
    hits = np.linspace(0.0, 0.05, 25)
    obs = planner.observation(np.array([0.015, 0.0, -0.03]), r, np.array([0.0, 0.03, 0.0]), hits)
    assert obs[0:3] == pytest.approx([0.1, 0.0, -0.2])
    assert obs[3:6] == pytest.approx(r[:, 0])
    assert obs[6:9] == pytest.approx(r[:, 1])
    assert obs[9:12] == pytest.approx(r[:, 2])
    v = np.array([-0.015, 0.03, 0.03]) / 0.3
    assert obs[12] == pytest.approx(np.linalg.norm(v))
    assert obs[13:16] == pytest.approx(v)
    assert obs[16:] == pytest.approx(np.clip(hits / 0.04, 0, 1))


def test_rollout_fails_on_wall_contact() -> None:
    planner = Planner(PlannerConfig(), box_world(), Plane(0.02), constant([0, 0, 1]),
                      RAY_DIRECTIONS)
    with pytest.raises(NoPathError, match='touched the wall after 33 steps'):
        planner.plan(np.zeros(3), np.eye(3), np.array([0.0, 0.05, 0.0]))


def test_retraction_slides_back_along_the_body() -> None:
    calls = []

    def policy(obs):
        calls.append(obs[1] * 0.15)
        return np.array([0, 0, 1.0 if len(calls) <= 4 else -1.0], dtype=np.float32)

    planner = Planner(PlannerConfig(max_rollout_steps=7), box_world(), OpenSpace(), policy,
                      RAY_DIRECTIONS)
    with pytest.raises(NoPathError):
        planner.rollout(np.zeros(3), np.eye(3), np.array([0.0, 0.3, 0.0]))
    assert calls == pytest.approx([0, 0.0005, 0.001, 0.0015, 0.002, 0.0015, 0.001], abs=1e-7)


def test_centerline_path_follows_the_nearest_ostium_branch_and_is_cut_at_the_goal() -> None:
    planner = Planner(PlannerConfig(planner_type='centerline'), box_world(), OpenSpace(), None,
                      RAY_DIRECTIONS)
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
    planner = Planner(PlannerConfig(planner_type='centerline'), box_world(), OpenSpace(), None,
                      RAY_DIRECTIONS)
    with pytest.raises(InvalidInputError, match=match):
        planner.plan(np.array(position, dtype=float), rotation, np.array(goal, dtype=float))


def test_cgail_needs_a_policy_of_the_right_size() -> None:
    with pytest.raises(ValueError, match="'cgail' needs a policy"):
        Planner(PlannerConfig(), box_world(), OpenSpace(), None, RAY_DIRECTIONS)
    with pytest.raises(ValueError, match='observation size must be 41'):
        Planner(PlannerConfig(), box_world(), OpenSpace(), constant([0, 0, 1]), RAY_DIRECTIONS,
                obs_dim=40)


def test_non_finite_policy_output_fails_the_plan() -> None:
    planner = Planner(PlannerConfig(), box_world(), OpenSpace(), constant([0, np.nan, 1]),
                      RAY_DIRECTIONS)
    with pytest.raises(NoPathError, match='policy must return 3 finite actions'):
        planner.plan(np.zeros(3), np.eye(3), np.array([0.0, 0.05, 0.0]))


def test_onnx_straight_policy_fixture_plans_in_the_default_anatomy() -> None:
    from cgail_planner.core.planner import model_world_from_sim
    from cgail_planner.learning.onnx_policy import OnnxPolicy
    from cgail_planner.sim.scenarios import load_world
    from cgail_planner.sim.wall import StaticWall

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
    step = cfg.max_insertion_speed * cfg.dt
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


@pytest.mark.parametrize('q', [(0, 0, 0, 1), (0.5, 0.5, 0.5, 0.5), (0.1, -0.7, 0.2, 0.67823299)])
def test_quaternion_round_trip(q) -> None:
    q = np.array(q, dtype=float) / np.linalg.norm(q)
    r = rotation_from_quaternion(*q)
    assert r.T @ r == pytest.approx(np.eye(3), abs=1e-12)
    back = np.array(quaternion_from_rotation(r))
    assert np.abs(back @ q) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('planner_type', 'rrt', "planner_type must be one of"),
    ('goal_tolerance', 0.0, r'goal_tolerance must be in \(0.0, 0.05\]'),
    ('max_rollout_steps', 0, r'max_rollout_steps must be an int in \[1, 100000\]'),
    ('path_spacing', 1.0, r'path_spacing must be in \[0.0001, 0.01\]'),
])
def test_config_rejects_bad_values(field, value, match) -> None:
    with pytest.raises(ValueError, match=match):
        PlannerConfig(**{field: value})

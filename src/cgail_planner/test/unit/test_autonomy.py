"""The autonomy's controllers: each drives the simulator from the standard start to the target
of the default anatomy; the policy reads the planner's contract and refuses a mismatch; the
rig's units; shared autonomy; bad settings fail in one line."""

from __future__ import annotations

from dataclasses import replace
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cgail_planner.core.autonomy import (
    action_from_command,
    AutonomyConfig,
    command_from_action,
    PathTracker,
    policy_planner,
    PolicyController,
    shared_command,
    SharedConfig,
)
from cgail_planner.core.errors import ContractError, InvalidInputError
from cgail_planner.core.safety import Command
from cgail_sim.ftl_model import CatheterConfig

MODELS = Path(__file__).resolve().parents[2] / 'cgail_planner' / 'models'


@pytest.fixture(scope='module')
def default_world():
    from cgail_sim.wall import StaticWall
    from cgail_sim.worlds import load_world

    world = load_world('default')
    return world, StaticWall(world.anatomy)


def drive(controller, env, max_steps: int = 1500) -> tuple[dict, int, list[Command]]:
    """Step the simulator with the controller's commands read as the rig reads them (the
    simulator's 0.1 s step), until the episode ends or the controller is done."""
    cat = env.engine.catheter
    info: dict = {}
    commands = []
    for k in range(max_steps):
        p, r = cat.tip_position[0].copy(), cat.tip_rotation[0].copy()
        command = controller.command(p, r, 0.1 * k)
        commands.append(command)
        if controller.done:
            break
        _, _, terminated, truncated, info = env.step(
            action_from_command(command.insertion_velocity, command.bend, cat.config))
        if terminated or truncated:
            break
    return info, k, commands


def start(env):
    env.reset(options={'start': 0, 'target': 0})
    cat = env.engine.catheter
    return cat.tip_position[0].copy(), cat.tip_rotation[0].copy(), env.engine.target[0].copy()


def test_path_tracking_reaches_the_target_on_the_planned_path(default_world) -> None:
    from cgail_planner.core.planner import model_world_from_sim, Planner, PlannerConfig
    from cgail_sim.env import CatheterNavEnv

    world, wall = default_world
    env = CatheterNavEnv()
    p, r, goal = start(env)
    path = Planner(PlannerConfig(planner_type='centerline'), model_world_from_sim(world), wall,
                   None).plan(p, r, goal).path
    tracker = PathTracker(AutonomyConfig(), env.engine.catheter.config)
    tracker.set_path(path)
    tracker.set_goal(goal)
    info, steps, commands = drive(tracker, env)
    assert info['success'] and not info['collision']
    assert steps < 1000
    assert all(abs(c.insertion_velocity) <= 0.005 and math.hypot(*c.bend) <= math.pi / 2
               for c in commands)
    # deterministic: the same inputs give the same commands
    again = PathTracker(AutonomyConfig(), env.engine.catheter.config)
    again.set_path(path)
    again.set_goal(goal)
    p0, r0, _ = start(env)
    assert again.command(p0, r0, 0.0) == commands[0]


def test_policy_controller_reaches_the_target(default_world) -> None:
    from cgail_planner.core.onnx_policy import OnnxPolicy
    from cgail_sim.env import CatheterNavEnv

    world, wall = default_world
    planner = policy_planner(OnnxPolicy(MODELS / 'cgail_default_static.onnx'), world, wall,
                             anatomy='default', anatomy_hash='', mode='static')
    controller = PolicyController(planner)
    env = CatheterNavEnv()
    _, _, goal = start(env)
    controller.set_goal(goal)
    info, steps, _ = drive(controller, env)
    assert info['success'] and not info['collision']
    assert steps < 1000


def test_the_policy_observes_what_the_simulator_observes(default_world) -> None:
    """The controller's observation is the one catheter model's: the simulator's own."""
    from cgail_planner.core.onnx_policy import OnnxPolicy
    from cgail_sim.env import CatheterNavEnv

    world, wall = default_world
    planner = policy_planner(OnnxPolicy(MODELS / 'cgail_default_static.onnx'), world, wall,
                             anatomy='default', anatomy_hash='', mode='static')
    env = CatheterNavEnv()
    obs, _ = env.reset(options={'start': 0, 'target': 0})
    p, r, goal = start(env)
    mine = planner.observation(p, r, goal, planner.readings(p, r))
    # The controller observes in the contract's frame (its stored origin); the simulator in
    # the frame of the anatomy it built on this host, whose mesh (and so its bounding-box
    # centre) differs in the last bits between numpy's AVX-512 and AVX2 paths: ~1 um, 7e-6 in
    # observation units. A wrong frame, scale or layout is off by far more than 1e-4 (15 um).
    np.testing.assert_allclose(mine, obs, atol=1e-4)


def test_a_policy_of_another_anatomy_or_without_a_contract_is_refused(default_world) -> None:
    from cgail_planner.core.onnx_policy import OnnxPolicy

    world, wall = default_world
    elongated = OnnxPolicy(MODELS / 'cgail_elongated_static.onnx')
    with pytest.raises(ContractError, match=r"^anatomy: expected the policy's 'elongated', "
                                            r"found parameter 'default'"):
        policy_planner(elongated, world, wall, anatomy='default', anatomy_hash='',
                       mode='static')
    with pytest.raises(ContractError, match=r'^policy: expected a catheter contract in x\.onnx, '
                                            r'found none'):
        policy_planner(SimpleNamespace(contract=None, path='x.onnx'), world, wall,
                       anatomy='default', anatomy_hash='', mode='static')


def test_actions_read_as_rig_commands_and_back() -> None:
    cat = CatheterConfig()
    velocity, bend = command_from_action([0.5, -0.25, 0.8], cat)
    assert velocity == pytest.approx(0.004)
    assert bend == pytest.approx((0.25 * math.pi, -0.125 * math.pi))
    np.testing.assert_allclose(action_from_command(velocity, bend, cat), [0.5, -0.25, 0.8])
    velocity, bend = command_from_action([3.0, -3.0, -2.0], cat)  # clipped
    assert velocity == pytest.approx(-0.005) and bend == pytest.approx((math.pi / 2,
                                                                        -math.pi / 2))
    forward = replace(cat, forward_only=True)
    assert command_from_action([0.0, 0.0, -0.5], forward)[0] == pytest.approx(0.0025)
    np.testing.assert_array_equal(action_from_command(0.05, (10.0, -10.0), cat), [1, -1, 1])


def test_path_tracking_needs_a_path_and_slows_at_the_goal() -> None:
    tracker = PathTracker()
    with pytest.raises(InvalidInputError, match=r'^path: expected a planned path, found none'):
        tracker.command(np.zeros(3), np.eye(3), 0.0)
    line = np.column_stack([np.zeros(101), np.linspace(0.0, 0.1, 101), np.zeros(101)])
    tracker.set_path(line)
    far = tracker.command(np.zeros(3), np.eye(3), 0.0)
    assert far.insertion_velocity == pytest.approx(0.005) and far.bend == (0.0, 0.0)
    tracker.reset()  # (the projection follows a moving tip: a teleported one starts afresh)
    near = tracker.command(np.array([0.0, 0.09, 0.0]), np.eye(3), 0.1)
    assert near.insertion_velocity == pytest.approx(0.005 * (0.3 + 0.7 * 0.5))
    # an aim to the side bends towards it: +x in the tip frame is -gamma
    tracker.set_path(line + np.array([0.005, 0.0, 0.0]))
    tracker.reset()
    turn = tracker.command(np.zeros(3), np.eye(3), 0.2)
    assert turn.bend[0] == pytest.approx(0.0, abs=1e-12) and turn.bend[1] < 0.0
    tracker.reset()
    at = tracker.command(np.array([0.005, 0.0995, 0.0]), np.eye(3), 0.3)
    assert at.insertion_velocity == 0.0 and tracker.done == 'at the target (0.5 mm)'
    tracker.reset()
    assert tracker.done is None


def test_shared_autonomy_adds_the_bend_and_overrides_the_insertion() -> None:
    auto = Command(0.004, (0.2, -0.1), 3.0)
    cfg = SharedConfig()
    assert shared_command(auto, (0.0, 0.0, 0.0), cfg) == auto
    out = shared_command(auto, (0.05, 0.5, -1.0), cfg)  # insertion within the deadzone
    assert out.insertion_velocity == 0.004 and out.stamp == 3.0
    assert out.bend == pytest.approx((0.2 + 0.25, -0.1 - 0.5))
    assert shared_command(auto, (-0.5, 0.0, 0.0), cfg).insertion_velocity \
        == pytest.approx(-0.0025)  # the person pulls back: retract
    wild = shared_command(auto, (math.nan, 7.0, -math.inf), cfg)
    assert wild.insertion_velocity == 0.004 and wild.bend == pytest.approx((0.7, -0.1))


@pytest.mark.parametrize(('cls', 'name', 'value', 'expected'), [
    (AutonomyConfig, 'lookahead', 0.0, r'a number in \(0, 0.1\]'),
    (AutonomyConfig, 'insertion_speed', 0.01, r'a number in \(0, 0.005\]'),
    (AutonomyConfig, 'epsilon', 0.001, r'>= stop_distance \(0.002\)'),
    (AutonomyConfig, 'max_bend', math.nan, r'a number in \(0, 1.5708\]'),
    (SharedConfig, 'insertion_deadzone', 1.0, r'a number in \[0, 1\)'),
    (SharedConfig, 'scale_insertion', -0.001, r'a number in \(0, 0.005\]'),
])
def test_bad_settings_fail_in_one_line(cls, name: str, value: float, expected: str) -> None:
    with pytest.raises(ValueError, match=f'^{name}: expected {expected}, found '):
        replace(cls(), **{name: value})

"""The numba rollout (Planner.rollout) gives the same paths and errors as the Python loop.

``Planner.rollout_reference`` is the specification; every case runs both and compares the
rolled-out points to 1e-9 m (in practice they agree to ~1e-16 m), the step counts and the
error messages, in the static wall and in the deformed (beating) wall.
"""

from pathlib import Path

import numpy as np
import pytest

from cgail_planner.core.mlp import MlpBuilder, MlpProgram
from cgail_planner.core.planner import (
    model_world_from_sim,
    NoPathError,
    Planner,
    PlannerConfig,
)
from cgail_planner.learning.onnx_policy import OnnxPolicy
from cgail_planner.sim.env import RAY_DIRECTIONS
from cgail_planner.sim.scenarios import load_world
from cgail_planner.sim.wall import DeformableWall, StaticWall

MODEL = (Path(__file__).resolve().parents[2] / 'cgail_planner' / 'learning' / 'models'
         / 'cgail_default_static.onnx')
FIXTURES = Path(__file__).resolve().parents[1] / 'fixtures'


@pytest.fixture(scope='module')
def world():
    return load_world('default')


@pytest.fixture(scope='module')
def walls(world):
    deformed = DeformableWall(world.anatomy)
    for k in range(1, 4):  # 0.3 s of heartbeat: the root has moved by several mm
        deformed.step(0.1 * k, 0.1, np.zeros((0, 3)), 0.0035)
    assert np.abs(deformed.vertices - world.anatomy.vertices).max() > 0.003
    return {'static': StaticWall(world.anatomy), 'dynamic': deformed}


@pytest.fixture(scope='module')
def policy():
    return OnnxPolicy(MODEL, expected_obs_dim=41)


def outcome(fn, *args):
    """('ok', points, steps) or ('error', message, points) of a rollout."""
    try:
        points, steps = fn(*args)
    except NoPathError as exc:
        return 'error', str(exc), exc.points, None
    return 'ok', '', points, steps


def assert_same_rollout(planner: Planner, p0, r0, goal) -> tuple:
    assert planner.uses_kernel
    fast = outcome(planner.rollout, p0, r0, goal)
    ref = outcome(planner.rollout_reference, p0, r0, goal)
    assert fast[0] == ref[0] and fast[1] == ref[1] and fast[3] == ref[3]
    assert fast[2].shape == ref[2].shape
    np.testing.assert_allclose(fast[2], ref[2], rtol=0, atol=1e-9)
    return fast


def const_policy(action) -> MlpProgram:
    b = MlpBuilder(41)
    return b.build(b.gemm(0, np.zeros((3, 41)), np.asarray(action, dtype=float)))


@pytest.mark.parametrize('mode', ['static', 'dynamic'])
@pytest.mark.parametrize(('start', 'target'), [(0, 0), (0, 4), (1, 2), (2, 1), (2, 3)])
def test_trained_policy_rollout_equals_the_reference(world, walls, policy, mode, start,
                                                     target) -> None:
    planner = Planner(PlannerConfig(), model_world_from_sim(world), walls[mode], policy,
                      RAY_DIRECTIONS, obs_dim=policy.obs_dim)
    s, t = world.scenarios.starts[start], world.scenarios.targets[target]
    kind, _, points, steps = assert_same_rollout(planner, s.position, s.rotation, t.position)
    if mode == 'static':  # the committed policy reaches every static target
        assert kind == 'ok' and steps > 100
        assert points[-1] == pytest.approx(t.position, abs=0)


@pytest.mark.parametrize('mode', ['static', 'dynamic'])
@pytest.mark.parametrize(('action', 'flip', 'match'), [
    ([1.0, 0.0, 1.0], False, 'touched the wall after 48 steps'),
    ([0.3, -0.5, 1.0], False, 'touched the wall after 62 steps'),
    ([0.0, 0.0, 1.0], True, 'left the anatomy after 61 steps'),   # down, out of the open end
])
def test_failures_equal_the_reference(world, walls, mode, action, flip, match) -> None:
    planner = Planner(PlannerConfig(), model_world_from_sim(world), walls[mode],
                      const_policy(action), RAY_DIRECTIONS)
    s = world.scenarios.starts[0]
    r0 = s.rotation @ np.diag([-1.0, -1.0, 1.0]) if flip else s.rotation
    kind, message, points, _ = assert_same_rollout(planner, s.position, r0,
                                                   world.scenarios.targets[0].position)
    assert kind == 'error' and match in message
    assert len(points) == int(match.split()[-2]) + 1


def test_step_limit_and_retraction_equal_the_reference(world, walls) -> None:
    """Insert while farther than 20 mm from the goal, retract when nearer: the tip oscillates
    around 20 mm (partial retractions along the body) until the step limit."""
    b = MlpBuilder(41)
    w = np.zeros((3, 41))
    w[2, 12] = 400.0  # obs[12] = |goal - p| / d_max
    d_max = model_world_from_sim(world).d_max
    act = b.clip(b.gemm(0, w, np.array([0.0, 0.0, -400.0 * 0.020 / d_max])), -1.0, 1.0)
    planner = Planner(PlannerConfig(max_rollout_steps=120), model_world_from_sim(world),
                      walls['static'], b.build(act), RAY_DIRECTIONS)
    s = world.scenarios.starts[0]
    goal = s.position + 0.035 * s.rotation[:, 1]
    kind, message, points, _ = assert_same_rollout(planner, s.position, s.rotation, goal)
    assert kind == 'error' and 'within 120 steps (ended 20.0 mm from it)' in message
    # it went forward 15 mm (30 steps) and then only moved by fractions of a step
    assert 28 <= len(points) <= 32
    assert np.linalg.norm(points[-1] - goal) == pytest.approx(0.020, abs=2e-4)


def test_non_finite_action_equals_the_reference(world, walls) -> None:
    b = MlpBuilder(41)
    zero = b.gemm(0, np.zeros((3, 41)), np.array([0.0, 0.0, 1.0]))
    nan = b.binary_const('div', zero, np.array([1.0, 0.0, 1.0]))  # 0 / 0 in the bend gamma
    planner = Planner(PlannerConfig(), model_world_from_sim(world), walls['static'],
                      b.build(nan), RAY_DIRECTIONS)
    s = world.scenarios.starts[0]
    kind, message, points, _ = assert_same_rollout(planner, s.position, s.rotation,
                                                   world.scenarios.targets[0].position)
    assert kind == 'error' and message == \
        'policy must return 3 finite actions, found [0.0, nan, 1.0]'
    assert len(points) == 1


def test_plan_uses_the_kernel_only_where_it_applies(world, walls, policy) -> None:
    model = model_world_from_sim(world)
    ort_policy = OnnxPolicy(MODEL, backend='onnxruntime')
    assert Planner(PlannerConfig(), model, walls['static'], policy, RAY_DIRECTIONS).uses_kernel
    assert Planner(PlannerConfig(), model, walls['dynamic'], policy,
                   RAY_DIRECTIONS).uses_kernel
    # a Python policy, an onnxruntime policy, a program of the wrong size, a non-sim wall
    assert not Planner(PlannerConfig(), model, walls['static'], lambda o: np.zeros(3),
                       RAY_DIRECTIONS).uses_kernel
    assert not Planner(PlannerConfig(), model, walls['static'], ort_policy,
                       RAY_DIRECTIONS).uses_kernel
    small = MlpBuilder(40)
    assert not Planner(PlannerConfig(), model, walls['static'],
                       small.build(small.gemm(0, np.zeros((3, 40)), None)),
                       RAY_DIRECTIONS).uses_kernel

    class Far:
        def raycast(self, origins, directions, max_dist):
            return np.full(len(origins), max_dist)

    assert not Planner(PlannerConfig(), model, Far(), policy, RAY_DIRECTIONS).uses_kernel
    # the onnxruntime policy plans the same path through the Python loop
    s, t = world.scenarios.starts[1], world.scenarios.targets[3]
    fast = Planner(PlannerConfig(), model, walls['static'], policy, RAY_DIRECTIONS)
    slow = Planner(PlannerConfig(), model, walls['static'], ort_policy, RAY_DIRECTIONS)
    a, b = fast.plan(s.position, s.rotation, t.position), \
        slow.plan(s.position, s.rotation, t.position)
    assert a.path[-1] == pytest.approx(t.position, abs=1e-12)
    assert abs(a.steps - b.steps) <= 5
    np.testing.assert_allclose(a.raw[:50], b.raw[:50], atol=1e-6)


def test_kernel_sees_the_current_shape_of_a_deformable_wall(world, policy) -> None:
    wall = DeformableWall(world.anatomy)
    planner = Planner(PlannerConfig(), model_world_from_sim(world), wall, policy,
                      RAY_DIRECTIONS)
    s, t = world.scenarios.starts[2], world.scenarios.targets[2]
    before = assert_same_rollout(planner, s.position, s.rotation, t.position)
    for k in range(1, 5):
        wall.step(0.1 * k, 0.1, np.zeros((0, 3)), 0.0035)
    after = assert_same_rollout(planner, s.position, s.rotation, t.position)
    assert before[0] != after[0] or before[2].shape != after[2].shape \
        or np.abs(before[2] - after[2]).max() > 1e-6

"""The numba rollout (Planner.rollout) gives the same paths and errors as the Python loop.

``Planner.rollout_reference`` is the specification; every case runs both and compares the
rolled-out points to 1e-9 m (in practice they agree to ~1e-16 m), the step counts and the
error messages, in the static wall and in the deformed (beating) wall.

No expected step count is a constant: the built-in mesh differs slightly between CPUs (numpy's
SIMD ufuncs, :mod:`cgail_sim.disk_cache`), which moves a wall contact or the bounding
box by a step. Counts are derived in the test from the geometry of this run (the catheter
model's kinematics of a constant action and the wall's contact query) or from a policy whose
path does not depend on the wall at all.
"""

from pathlib import Path

import numpy as np
import pytest

from cgail_planner.core.errors import NoPathError
from cgail_planner.core.mlp import MlpBuilder, MlpProgram
from cgail_planner.core.onnx_policy import OnnxPolicy
from cgail_planner.core.planner import model_world_from_sim, Planner, PlannerConfig
from cgail_sim.exits import crossed_discs
from cgail_sim.ftl_model import (
    action_to_command,
    advance_pose,
    CatheterConfig,
    RAY_DIRECTIONS,
)
from cgail_sim.wall import DeformableWall, StaticWall
from cgail_sim.worlds import load_world

MODEL = (Path(__file__).resolve().parents[2] / 'cgail_planner' / 'models'
         / 'cgail_default_static.onnx')
FIXTURES = Path(__file__).resolve().parents[1] / 'fixtures'


@pytest.fixture(scope='module')
def world():
    return load_world('default')


@pytest.fixture(scope='module')
def walls(world):
    deformed = DeformableWall(world.anatomy)
    for k in range(1, 4):  # 0.3 s of heartbeat: the root has moved by several mm
        deformed.step(0.1 * k, 0.1, np.zeros((0, 3)), CatheterConfig().radius)
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


def constant_action_outcome(planner: Planner, p0, r0, action) -> tuple[str, int]:
    """What a constant forward action must give, from the catheter model and the wall alone:
    the tip poses of the model's single-pose step (independent of the wall), each checked as
    an episode ends: a collision when the tip sphere penetrates the wall after step k
    ('touched', k), step k through an exit disc or the tip beyond the bounding box after it
    ('left', k)."""
    cfg, world, cat = planner.config, planner.world, planner.config.catheter
    alpha, gamma, dl = (float(v) for v in action_to_command(
        np.asarray(action, dtype=np.float64), cat.theta_max, cat.segment_length,
        cat.max_step_insertion))
    p, r = np.array(p0, dtype=float), np.array(r0, dtype=float)
    for k in range(1, cfg.max_rollout_steps + 1):
        p0 = p
        p, r = advance_pose(p, r, alpha, gamma, dl)
        if planner.wall.tip_contact(p, cat.radius, cat.dt).penetration > 0.0:
            return 'touched', k
        if crossed_discs(p0[None], p[None], world.exit_discs)[0] \
                or ((p < world.bbox_low) | (p > world.bbox_high)).any():
            return 'left', k
    return 'step limit', cfg.max_rollout_steps


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
@pytest.mark.parametrize(('action', 'flip', 'event', 'span'), [
    # full alpha: the tip curls into the wall of the descending aorta after ~24 mm
    ([1.0, 0.0, 1.0], False, 'touched', (40, 56)),
    ([0.3, -0.5, 1.0], False, 'touched', (54, 70)),
    # heading flipped: straight down, out of the open end through its exit plane
    ([0.0, 0.0, 1.0], True, 'left', (32, 48)),
])
def test_failures_equal_the_reference(world, walls, mode, action, flip, event, span) -> None:
    planner = Planner(PlannerConfig(), model_world_from_sim(world), walls[mode],
                      const_policy(action), RAY_DIRECTIONS)
    s = world.scenarios.starts[0]
    r0 = s.rotation @ np.diag([-1.0, -1.0, 1.0]) if flip else s.rotation
    kind, message, points, _ = assert_same_rollout(planner, s.position, r0,
                                                   world.scenarios.targets[0].position)
    expected, steps = constant_action_outcome(planner, s.position, r0, action)
    assert (expected, span[0] <= steps <= span[1]) == (event, True)
    what = 'touched the wall' if event == 'touched' else 'left the anatomy'
    assert kind == 'error' and f'{what} at step {steps}' in message
    assert len(points) == steps + 1


def test_step_limit_and_retraction_equal_the_reference(world, walls) -> None:
    """Insert while farther than 20 mm from the goal, retract when nearer, with a gain that
    overshoots: the tip goes straight ahead 15 mm in full steps, then oscillates around 20 mm
    from the goal (each retraction a partial one along the body, half the step before it)
    until the step limit.

    The path follows from the policy alone (a straight line, 1-D), so the test computes it:
    the insertion is ``clip(GAIN * (|goal - p| - 20 mm), -1, 1)`` steps of 0.5 mm. The limit
    stops it while the oscillation is still ~0.2 um, far above the float32 rounding of the
    observation (~2 nm), so no step's sign hangs on the last bits.
    """
    gain, hold, dist0, limit = 3000.0, 0.020, 0.0352, 40   # 1/m, m, m, steps
    model = model_world_from_sim(world)
    b = MlpBuilder(41)
    w = np.zeros((3, 41))
    w[2, 12] = gain * model.d_max  # obs[12] = |goal - p| / d_max
    act = b.clip(b.gemm(0, w, np.array([0.0, 0.0, -gain * hold])), -1.0, 1.0)
    cfg = PlannerConfig(max_rollout_steps=limit)
    planner = Planner(cfg, model, walls['static'], b.build(act), RAY_DIRECTIONS)
    s = world.scenarios.starts[0]
    heading = s.rotation[:, 1]
    goal = s.position + dist0 * heading
    kind, message, points, _ = assert_same_rollout(planner, s.position, s.rotation, goal)
    # the same rollout along the line: body = distances of the kept points from the start
    step = cfg.catheter.max_step_insertion
    body = [0.0]
    for _ in range(limit):
        dl = min(max(gain * (dist0 - body[-1] - hold), -1.0), 1.0) * step
        if dl > 0:
            body.append(body[-1] + dl)
        else:  # a partial retraction along the last segment (never a whole one here)
            assert -dl < body[-1] - body[-2]
            body[-1] += dl
    assert kind == 'error' and f'within {limit} steps (ended 20.0 mm from it)' in message
    assert len(points) == len(body) == 1 + 30 + 5   # 30 full steps, then 5 of the 10 forward
    # (the observation is float32: |goal - p| / d_max rounds by ~2e-9 m, times the gain)
    np.testing.assert_allclose(points, s.position + np.outer(body, heading), rtol=0, atol=1e-8)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    assert seg[:30] == pytest.approx(step, abs=1e-12) and (seg[30:] < 0.7 * step).all()
    assert np.linalg.norm(points[-1] - goal) == pytest.approx(hold, abs=1e-6)


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
        wall.step(0.1 * k, 0.1, np.zeros((0, 3)), CatheterConfig().radius)
    after = assert_same_rollout(planner, s.position, s.rotation, t.position)
    assert before[0] != after[0] or before[2].shape != after[2].shape \
        or np.abs(before[2] - after[2]).max() > 1e-6


def test_retraction_follows_a_bent_introducer_out_of_the_exit() -> None:
    """In the aorta whose descending part curves near its open end, start 2's body behind it
    is the bent introducer: retracting all the way, the tip slides along it and leaves through
    the exit disc (as the env's episode does), where a straight introducer would have taken
    it through the wall."""
    import dataclasses

    from cgail_sim.testing import curved_world

    world = curved_world()
    model = model_world_from_sim(world)
    wall = StaticWall(world.anatomy)
    s = world.scenarios.starts[2]
    assert s.bent
    planner = Planner(PlannerConfig(), model, wall, const_policy([0.0, 0.0, -1.0]),
                      RAY_DIRECTIONS)
    kind, message, points, _ = assert_same_rollout(planner, s.position, s.rotation,
                                                   world.scenarios.targets[0].position)
    nodes = np.vstack([s.introducer, s.position])
    depth = (nodes - world.anatomy.exit_point) @ world.anatomy.exit_normal
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))])
    j = int(np.flatnonzero(depth < 0.0)[0])  # the first node inside the lumen
    at_plane = arc[j - 1] + depth[j - 1] / (depth[j - 1] - depth[j]) * (arc[j] - arc[j - 1])
    steps = int((arc[-1] - at_plane) // CatheterConfig().max_step_insertion) + 1
    assert kind == 'error' and message == f'cgail rollout left the anatomy at step {steps}'
    assert len(points) == 1
    assert world.anatomy.contains(points - 0.002 * world.anatomy.exit_normal).all()
    straight = Planner(PlannerConfig(), dataclasses.replace(model, introducer=None), wall,
                       const_policy([0.0, 0.0, -1.0]), RAY_DIRECTIONS)
    kind, message, _, _ = assert_same_rollout(straight, s.position, s.rotation,
                                              world.scenarios.targets[0].position)
    assert kind == 'error' and 'touched the wall' in message

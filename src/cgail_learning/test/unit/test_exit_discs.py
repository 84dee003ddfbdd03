"""One exit rule: the tip leaves the lumen only through the disc of an open cut.

The rule (:mod:`cgail_sim.exits`) on hand-made discs; the discs every anatomy derives
from its caps (:attr:`Anatomy.exit_discs`); and a patient whose descending cut lies at the
level of the aortic root, where the former rule (the half-space beyond the descending cut's
plane) put 3 of the 5 standard targets outside the lumen: the env, the planner's reference
rollout and its numba kernel agree that a tip in the root beyond that plane is inside, and that
a tip leaving through a disc (the descending end, a branch end) is out.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cgail_learning.evaluate import CenterlineFollower
from cgail_learning.expert import run_expert_episode, ScriptedExpert
from cgail_planner.core.errors import NoPathError
from cgail_planner.core.mlp import MlpBuilder, MlpProgram
from cgail_planner.core.planner import Planner, PlannerConfig
from cgail_sim.anatomy import (
    Anatomy,
    anatomy_params,
    AnatomyError,
    build_anatomy,
    build_anatomy_from_params,
    load_anatomy_mesh,
    save_anatomy_mesh,
)
from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv
from cgail_sim.exits import (
    crossed_disc,
    crossed_discs,
    disc_array,
    EXIT_MARGIN,
    in_exit_slab,
)
from cgail_sim.ftl_model import PolicyContract

MM = 1e-3
#: one disc of radius 10 mm in the plane z = 0, normal -z (the lumen is z > 0)
DISC = disc_array(np.zeros((1, 3)), np.array([[0.0, 0.0, -1.0]]), np.array([10 * MM]))


def cross(p0, p1, discs=DISC) -> int:
    return int(crossed_disc(*(float(v) for v in (*p0, *p1)), discs))


# ------------------------------------------------------------------------------ the rule
@pytest.mark.parametrize(('p0', 'p1', 'index'), [
    ((0, 0, 1 * MM), (0, 0, -1 * MM), 0),  # straight through the centre
    ((5 * MM, 0, 1 * MM), (5 * MM, 0, -50 * MM), 0),  # a long step cannot jump over it
    ((0, 0, 0), (0, 0, -1 * MM), 0),  # from the plane outwards
    ((10.5 * MM, 0, 1 * MM), (10.5 * MM, 0, -1 * MM), 0),  # the rim, within EXIT_MARGIN
    ((12 * MM, 0, 1 * MM), (12 * MM, 0, -1 * MM), -1),  # beside the disc: the wall's business
    ((0, 0, -1 * MM), (0, 0, -3 * MM), -1),  # beyond the plane, not through the disc
    ((0, 0, -1 * MM), (0, 0, 1 * MM), -1),  # back in
    ((0, 0, 1 * MM), (0, 0, 0), -1),  # onto the plane, not past it
    ((-30 * MM, 0, 1 * MM), (30 * MM, 0, -1 * MM), 0),  # oblique, crossing at the centre
    ((-40 * MM, 0, 1 * MM), (10 * MM, 0, -1 * MM), -1),  # oblique, crossing 15 mm out
])
def test_a_step_leaves_only_through_the_disc(p0, p1, index) -> None:
    assert 0.5 * MM < EXIT_MARGIN < 2 * MM  # what the rim cases below assume
    assert cross(p0, p1) == index


def test_the_first_disc_crossed_is_named_and_the_batch_agrees() -> None:
    discs = disc_array(np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]),
                       np.array([[0.0, 0.0, -2.0], [1.0, 0.0, 0.0]]),
                       np.array([0.01, 0.005]))
    assert discs[0, 5] == -1.0  # normalised
    prev = np.array([[0.0, 0.0, 0.001], [0.099, 0.0, 0.0], [0.099, 0.02, 0.0]])
    tips = np.array([[0.0, 0.0, -0.001], [0.101, 0.0, 0.0], [0.101, 0.02, 0.0]])
    assert [cross(a, b, discs) for a, b in zip(prev, tips, strict=True)] == [0, 1, -1]
    assert crossed_discs(prev, tips, discs).tolist() == [True, True, False]


def test_the_slab_is_the_state_wise_form() -> None:
    depth = 1 * MM

    def slab(x, y, z) -> int:
        return int(in_exit_slab(x, y, z, DISC, depth))

    assert slab(0.0, 0.0, -0.5 * MM) == 0
    assert slab(10.5 * MM, 0.0, -0.5 * MM) == 0
    assert slab(12 * MM, 0.0, -0.5 * MM) == -1  # beside the disc
    assert slab(0.0, 0.0, -2 * MM) == -1  # deeper than the slab
    assert slab(0.0, 0.0, 0.5 * MM) == -1  # in the lumen


@pytest.mark.parametrize(('args', 'message'), [
    ((np.zeros((2, 3)), np.ones((1, 3)), np.ones(1)),
     'expected as many centres, normals and radii, found 2, 1 and 1'),
    ((np.zeros((1, 3)), np.zeros((1, 3)), np.ones(1)), 'expected non-zero normals and radii > 0'),
    ((np.zeros((1, 3)), np.ones((1, 3)), np.zeros(1)), 'expected non-zero normals and radii > 0'),
    ((np.full((1, 3), np.nan), np.ones((1, 3)), np.ones(1)),
     'expected finite disc centres, normals and radii'),
])
def test_bad_discs_are_refused_in_one_line(args, message) -> None:
    with pytest.raises(ValueError, match=message):
        disc_array(*args)


# ------------------------------------------------------------------- the anatomy's discs
def test_the_built_in_aorta_has_a_disc_per_open_end_and_none_at_the_valve() -> None:
    a = build_anatomy('default')
    discs = a.exit_discs
    p = anatomy_params('default')
    # the descending end, three supra-aortic branch ends and two coronary stub ends
    assert discs.shape == (6, 7) and not discs.flags.writeable
    assert np.array_equal(discs[0, :3], a.exit_point)
    assert np.array_equal(discs[0, 3:6], a.exit_normal)
    assert abs(discs[0, 6] - 0.5 * p.descending_diameter) < 1 * MM
    for side in ('left', 'right'):  # each coronary stub end is a small disc near its ostium
        near = np.linalg.norm(discs[:, :3] - a.ostia[side], axis=1)
        k = int(np.argmin(near))
        assert near[k] < 10 * MM and discs[k, 6] < 3 * MM
    # the valve plane is wall: no disc within 5 mm of the annulus
    assert np.linalg.norm(discs[:, :3] - a.annulus_center, axis=1).min() > 5 * MM
    # every disc is a cap: its centre lies on the surface, its normal out of the lumen
    assert not a.contains(discs[:, :3] + 2 * MM * discs[:, 3:6]).any()
    assert a.contains(discs[:, :3] - 2 * MM * discs[:, 3:6]).all()


def test_a_loaded_mesh_gets_the_same_discs(tmp_path) -> None:
    a = build_anatomy('default')
    loaded = load_anatomy_mesh(save_anatomy_mesh(a, tmp_path / 'aorta.stl').with_suffix('.stl'))
    got = loaded.exit_discs
    assert got.shape == a.exit_discs.shape
    np.testing.assert_allclose(got[0], a.exit_discs[0], atol=1e-5)
    # the other caps in any order
    for row in a.exit_discs[1:]:
        assert np.abs(got[1:] - row).max(axis=1).min() < 1e-5


def test_an_anatomy_without_a_cap_at_its_exit_point_has_no_discs() -> None:
    a = build_anatomy('default')
    moved = dataclasses.replace(a, exit_point=a.exit_point + np.array([0.0, 0.0, 0.1]))
    with pytest.raises(AnatomyError, match=r'expected a cap \(wall_face_mask False\) closing '
                                           r'the descending end at exit_point .* found the '
                                           r'nearest cap [0-9.]+ mm away'):
        _ = moved.exit_discs


# ------------------------------------------------- a patient cut at the level of the root
@pytest.fixture(scope='module')
def root_cut() -> Anatomy:
    """The elongated aorta with a long ascending aorta (85 mm) and the shortest descending
    one (50 mm): the descending cut lies 32 mm above the annulus, and its plane passes through
    the aortic root, as in a CTA label map cut at the level of the annulus."""
    params = dataclasses.replace(anatomy_params('elongated'), ascending_length=0.085,
                                 annulus_to_brachiocephalic=0.129, descending_length=0.050,
                                 descending_bend_length=0.040)
    return build_anatomy_from_params(params, 'root-cut')


@pytest.fixture(scope='module')
def env(root_cut: Anatomy) -> CatheterNavEnv:
    return CatheterNavEnv(EnvConfig(anatomy=root_cut, max_steps=600))


def beyond_plane(anatomy: Anatomy, points) -> np.ndarray:
    """Depth beyond the descending cut's plane (> 0: outside by the former half-space rule)."""
    return (np.asarray(points) - anatomy.exit_point) @ anatomy.exit_normal


#: the standard targets beyond the descending cut's plane
BEYOND = (1, 2, 3)


def test_targets_in_the_root_lie_beyond_the_descending_cut(root_cut, env) -> None:
    targets = np.array([t.position for t in env.scenarios.targets])
    depth = beyond_plane(root_cut, targets)
    assert (depth[list(BEYOND)] > 5 * MM).all() and (np.delete(depth, BEYOND) < 0).all()
    assert root_cut.contains(targets).all()  # in the lumen all the same
    # and far from the descending disc: no step in the root can cross it
    assert (np.linalg.norm(targets - root_cut.exit_point, axis=1)
            > root_cut.exit_discs[0, 6] + 20 * MM).all()


def test_the_follower_and_the_expert_reach_the_targets_beyond_the_plane(root_cut, env) -> None:
    """The centerline follower reaches every standard target from start 0, and the episodes
    to the targets beyond the plane end with the tip beyond it (the former rule ended them as
    exits); so does the scripted expert on one of them."""
    follower = CenterlineFollower(env)
    for target in range(5):
        env.reset(options={'start': 0, 'target': target})
        follower.reset()
        tips = []
        while True:
            _, _, terminated, truncated, info = env.step(follower.act())
            tips.append(env.catheter.tip_position[0].copy())
            if terminated or truncated:
                break
        assert info['success'], (target, info['timesteps'])
        assert (beyond_plane(root_cut, tips).max() > 0) == (target in BEYOND), target
    *_, info, _ = run_expert_episode(env, ScriptedExpert(env), options={'start': 2, 'target': 3})
    assert info['success']
    assert beyond_plane(root_cut, env.catheter.tip_position[0]) > 0


def constant(action) -> MlpProgram:
    b = MlpBuilder(41)
    return b.build(b.gemm(0, np.zeros((3, 41)), np.asarray(action, dtype=float)))


def heading_towards(p0: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """A tip rotation whose heading (column y_A) points from ``p0`` at ``goal``."""
    y = (goal - p0) / np.linalg.norm(goal - p0)
    x = np.cross(y, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, y, np.cross(x, y)])


def episode(env: CatheterNavEnv, policy, target: int, start_pose=None) -> dict:
    """One env episode from start 0 (or ``start_pose``): ending, steps and tip path."""
    options = {'start': 0, 'target': target}
    if start_pose is not None:
        options['start_pose'] = start_pose
    obs, _ = env.reset(options=options)
    tips = [env.catheter.tip_position[0].copy()]
    while True:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        tips.append(env.catheter.tip_position[0].copy())
        if terminated or truncated:
            break
    ending = ('reached' if info['success'] else 'collided' if info['collision']
              else 'left' if info['exited'] else 'limit')
    return {'ending': ending, 'steps': int(info['timesteps']), 'tips': np.array(tips)}


def assert_planner_agrees(env: CatheterNavEnv, policy, p0, r0, goal, ep: dict) -> None:
    """The reference rollout and the kernel end as the episode did, at the same step; a
    reached rollout of a forward-only policy has the episode's tip path as its body."""
    eng = env.engine
    contract = PolicyContract(catheter=env.config.catheter, observation=eng.spec,
                              anatomy=eng.world.anatomy.name, mode='static')
    planner = Planner.from_contract(contract, eng.world, eng.walls[0], policy, PlannerConfig(
        max_rollout_steps=env.config.max_steps, goal_tolerance=env.config.reward.epsilon))
    assert planner.uses_kernel
    for rollout in (planner.rollout_reference, planner.rollout):
        try:
            points, steps = rollout(p0, r0, goal)
            got = ('reached', steps)
        except NoPathError as exc:
            points, got = exc.points, (exc.reason, exc.step)
        assert got == (ep['ending'], ep['steps']), rollout.__name__
        if got[0] == 'reached':
            np.testing.assert_allclose(points[:-1], ep['tips'], rtol=0, atol=1e-9)


@pytest.mark.parametrize('target', BEYOND)
def test_a_tip_in_the_root_beyond_the_plane_is_inside_for_env_kernel_and_planner(
        root_cut, env, target) -> None:
    """Straight from the ascending aorta at a target in the root: the tip passes the
    descending cut's plane (the former rule's exit) and all three reach the target."""
    goal = env.scenarios.targets[target].position
    p0 = root_cut.annulus_center + 0.045 * root_cut.root_axis
    r0 = heading_towards(p0, goal)
    policy = constant([0.0, 0.0, 1.0])
    ep = episode(env, policy, target, (p0, r0))
    assert ep['ending'] == 'reached'
    depth = beyond_plane(root_cut, ep['tips'])
    assert depth[0] < 0 < depth.max()  # it crossed the plane, outside the disc
    assert_planner_agrees(env, policy, p0, r0, goal, ep)


@pytest.mark.parametrize('case', ['retracts out of the descending end',
                                  'inserts out of the descending end'])
def test_a_tip_leaving_through_the_descending_disc_is_out_for_all_three(root_cut, env,
                                                                        case) -> None:
    s = env.scenarios.starts[0]
    goal = env.scenarios.targets[0].position
    if case == 'retracts out of the descending end':
        policy, r0, pose = constant([0.0, 0.0, -1.0]), s.rotation, None
    else:  # heading flipped: straight down and out
        r0 = s.rotation @ np.diag([-1.0, -1.0, 1.0])
        policy, pose = constant([0.0, 0.0, 1.0]), (s.position, r0)
    ep = episode(env, policy, 0, pose)
    assert ep['ending'] == 'left'
    last = ep['tips'][-2:]
    assert cross(last[0], last[1], root_cut.exit_discs) == 0  # through the descending disc
    assert_planner_agrees(env, policy, s.position, r0, goal, ep)


def test_a_tip_leaving_through_a_branch_end_is_out_for_all_three() -> None:
    """A branch end is an open cut too: from the arch's centerline straight up the widest
    branch stub (the brachiocephalic trunk) and out of its end."""
    env = CatheterNavEnv(EnvConfig(max_steps=200))
    discs = env.anatomy.exit_discs
    k = 1 + int(np.argmax(discs[1:, 6]))
    line = env.engine.world.centerlines['left'].points
    p0 = line[int(np.argmin(np.linalg.norm(line - discs[k, :3], axis=1)))]
    r0 = heading_towards(p0, discs[k, :3])
    policy = constant([0.0, 0.0, 1.0])
    ep = episode(env, policy, 0, (p0, r0))
    assert ep['ending'] == 'left'
    last = ep['tips'][-2:]
    assert cross(last[0], last[1], discs) == k
    assert_planner_agrees(env, policy, p0, r0, env.scenarios.targets[0].position, ep)

"""Targets drawn anew per episode (``EnvConfig.targets == 'sphere'``) by the scenario set's one
sampler, and the ``d_max`` that goes with them."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cgail_sim.config import EnvConfig, OPTION_SETS
from cgail_sim.env import CatheterNavEnv, observation_spec
from cgail_sim.scenarios import (
    build_targets,
    TARGET_CLEARANCE,
    TARGET_RADIUS,
    target_sampler,
    TargetConfig,
    TargetSampler,
)
from cgail_sim.vec_env import CatheterNavVecEnv
from cgail_sim.worlds import load_world

SPHERE = EnvConfig(targets="sphere")


def _check_rules(anatomy, targets) -> None:
    """The acceptance rules of the module docstring of ``cgail_sim/scenarios.py``."""
    verts = np.asarray(anatomy.vertices)
    wall_faces = anatomy.faces[anatomy.wall_face_mask]
    wall_vids = np.unique(wall_faces)
    wall = cKDTree(np.vstack([verts[wall_vids], verts[wall_faces].mean(axis=1)]))
    centre = 0.5 * (anatomy.ostia["left"] + anatomy.ostia["right"])
    for t in targets:
        assert np.linalg.norm(t.position - centre) <= TARGET_RADIUS
        assert anatomy.contains(t.position[None])[0]
        assert wall.query(t.position)[0] >= TARGET_CLEARANCE
        d = np.linalg.norm(verts[wall_vids] - t.position, axis=1)
        assert t.vertex == int(wall_vids[np.argmin(d)])
        np.testing.assert_array_equal(t.offset, t.position - verts[t.vertex])
        near = min(("left", "right"), key=lambda b: np.linalg.norm(t.position - anatomy.ostia[b]))
        assert t.branch == near


def test_the_fixed_sets_are_the_samplers_draws_with_their_seed() -> None:
    anatomy = load_world("default").anatomy
    fixed = load_world("default", seed=3).scenarios.targets
    again = TargetSampler(anatomy).sample(np.random.default_rng(3), 5, min_separation=0.005)
    assert [t.position.tolist() for t in fixed] == [t.position.tolist() for t in again]
    assert [t.position.tolist() for t in build_targets(anatomy, seed=3)] == \
        [t.position.tolist() for t in fixed]


@pytest.mark.parametrize("anatomy", ["default", "elongated"])
def test_drawn_targets_follow_the_acceptance_rules(anatomy: str) -> None:
    a = load_world(anatomy).anatomy
    drawn = target_sampler(a).sample(np.random.default_rng(5), 40)
    _check_rules(a, drawn)
    # 40 different targets spread over the sphere (not the 5 of a fixed set)
    assert len({tuple(t.position) for t in drawn}) == 40
    assert {t.branch for t in drawn} == {"left", "right"}


def test_sphere_d_max_bounds_every_drawable_target_and_is_the_sphere_observation_scale() -> None:
    sc = load_world("default").scenarios
    a = load_world("default").anatomy
    centre = 0.5 * (a.ostia["left"] + a.ostia["right"])
    expected = float(np.linalg.norm(np.asarray(a.vertices) - centre, axis=1).max()) + 0.030
    assert sc.sphere_d_max == pytest.approx(expected, rel=1e-12)
    assert sc.sphere_d_max > sc.d_max
    drawn = target_sampler(a).sample(np.random.default_rng(0), 50)
    far = max(float(np.linalg.norm(np.asarray(a.vertices) - t.position, axis=1).max())
              for t in drawn)
    assert far <= sc.sphere_d_max
    assert observation_spec(SPHERE).d_max == sc.sphere_d_max
    assert observation_spec(EnvConfig()).d_max == sc.d_max  # (the default is unchanged)


def test_default_config_keeps_the_fixed_targets() -> None:
    assert EnvConfig().targets == "fixed" and EnvConfig().options == "ours"
    env = CatheterNavEnv()
    _, info = env.reset(seed=4)
    assert 0 <= info["target"] < 5


def test_a_sphere_reset_draws_a_new_target_per_episode_reproducibly() -> None:
    env = CatheterNavEnv(SPHERE)
    sc = env.scenarios
    fixed = {tuple(t.position) for t in sc.targets}
    seen, drawn = [], []
    eng = env.engine
    for k in range(6):
        _, info = env.reset(seed=100 + k)
        assert info["target"] == -1
        seen.append(tuple(info["target_position"]))
        drawn.append(TargetConfig(position=eng.target[0].copy(),
                                  vertex=int(eng._target_vertex[0]),
                                  offset=eng._target_offset[0].copy(), branch=eng.branch[0]))
    assert len(set(seen)) == 6 and not set(seen) & fixed
    _check_rules(env.anatomy, drawn)
    again = CatheterNavEnv(SPHERE)
    assert [tuple(again.reset(seed=100 + k)[1]["target_position"]) for k in range(6)] == seen
    # the episode's centerline is its target's branch; a named target is the fixed set's
    assert eng.branch[0] in ("left", "right")
    np.testing.assert_array_equal(eng.waypoints[0], sc.waypoints[eng.branch[0]])
    _, info = env.reset(seed=1, options={"target": 2})
    assert info["target"] == 2
    np.testing.assert_array_equal(info["target_position"], sc.targets[2].position)


def test_the_batched_env_draws_the_targets_a_single_env_draws() -> None:
    vec = CatheterNavVecEnv(SPHERE, num_envs=3)
    obs = vec.reset(seed=20)
    for i in range(3):
        single = CatheterNavEnv(SPHERE)
        o, info = single.reset(seed=20 + i)
        np.testing.assert_array_equal(vec.engine.target[i], info["target_position"])
        np.testing.assert_allclose(obs[i], o, atol=1e-6)


def test_a_drawn_target_moves_with_its_wall_vertex_in_dynamic_mode() -> None:
    env = CatheterNavEnv(EnvConfig(mode="dynamic", targets="sphere"))
    _, info = env.reset(seed=2)
    eng = env.engine
    for _ in range(5):
        env.step(np.array([0.0, 0.0, 1.0], dtype=np.float32))
    wall = eng.walls[0]
    v, o = int(eng._target_vertex[0]), eng._target_offset[0]
    np.testing.assert_array_equal(eng.target[0], wall.vertices[v] + o)
    assert np.linalg.norm(eng.target[0] - info["target_position"]) > 0.0


def test_the_sphere_targets_option_set_is_ours_with_drawn_targets() -> None:
    ours, sphere = OPTION_SETS["ours"], OPTION_SETS["sphere_targets"]
    assert {k: v for k, v in sphere.items() if k != "targets"} == \
        {k: v for k, v in ours.items() if k != "targets"}
    assert EnvConfig.from_options("sphere_targets").targets == "sphere"
    assert EnvConfig(targets="sphere").options == "sphere_targets"


def test_a_bad_targets_value_is_one_line() -> None:
    with pytest.raises(ValueError, match=r"^targets must be one of \('fixed', 'sphere'\), "
                                         r"found 'ball'$"):
        EnvConfig(targets="ball")
    with pytest.raises(ValueError, match="targets must be one of"):
        load_world("default").scenarios.d_max_for("ball")

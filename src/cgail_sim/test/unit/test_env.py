"""CatheterNavEnv: gymnasium API, determinism, bad input, reward events, dynamic mode."""

from dataclasses import replace
import itertools
import json
import math

import gymnasium as gym
from gymnasium.utils.env_checker import check_env
import numpy as np
import pytest

import cgail_sim  # noqa: F401  (registers CatheterNav-v0)
from cgail_sim.config import EnvConfig
from cgail_sim.env import (
    CatheterNavEnv,
    OBS_DIM,
    OBS_LAYOUT,
    obs_layout_dict,
    pursuit_actions,
    RAY_DIRECTIONS,
)
from cgail_sim.reward import RewardConfig

STEP = -1e-5


@pytest.fixture(scope="module")
def env() -> CatheterNavEnv:
    return CatheterNavEnv()


def pursuit_action(env: CatheterNavEnv) -> np.ndarray:
    """Scripted sanity policy (pure pursuit of the centerline) for one env."""
    return pursuit_actions(env.engine)[0]


def test_check_env(env: CatheterNavEnv) -> None:
    check_env(env, skip_render_check=True)


def test_registered() -> None:
    made = gym.make("CatheterNav-v0")
    obs, _ = made.reset(seed=0)
    assert obs.shape == (OBS_DIM,)
    assert made.unwrapped.config.mode == "static"
    made.close()


def test_obs_layout(env: CatheterNavEnv) -> None:
    assert OBS_LAYOUT[0].start == 0 and OBS_LAYOUT[-1].stop == OBS_DIM == 41
    for a, b in itertools.pairwise(OBS_LAYOUT):
        assert a.stop == b.start
    np.testing.assert_allclose(np.linalg.norm(RAY_DIRECTIONS, axis=1), 1.0)
    assert RAY_DIRECTIONS.shape == (25, 3)
    obs, info = env.reset(seed=1)
    e = env.engine
    rot = obs[3:12].reshape(3, 3).T
    np.testing.assert_allclose(rot, e.catheter.tip_rotation[0], atol=1e-6)
    np.testing.assert_allclose(obs[0:3], (e.catheter.tip_position[0] - env.scenarios.origin)
                               / 0.15, atol=1e-6)
    assert obs[12] == pytest.approx(np.linalg.norm(obs[13:16]), rel=1e-6)
    np.testing.assert_allclose(obs[13:16] * env.scenarios.d_max,
                               info["target_position"] - e.catheter.tip_position[0], atol=1e-7)
    assert np.all((obs[16:] >= 0.0) & (obs[16:] <= 1.0))
    assert env.observation_space.contains(obs)


def test_determinism(env: CatheterNavEnv) -> None:
    other = CatheterNavEnv()

    def rollout(e: CatheterNavEnv) -> list:
        out = []
        obs, _ = e.reset(seed=42)
        rng = np.random.default_rng(7)
        out.append(obs)
        for _ in range(150):
            obs, r, te, tr, info = e.step(rng.uniform(-1, 1, 3).astype(np.float32))
            out += [obs, r, te, tr, info["collision_force"]]
            if te or tr:
                obs, _ = e.reset()
                out.append(obs)
        return out

    a, b = rollout(env), rollout(other)
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize(
    ("action", "match"),
    [([0.0, float("nan"), 1.0], "finite"), ([0.0, 0.0, float("inf")], "finite"),
     ([0.0, 1.0], r"shape \(3,\)"), ([[0.0, 0.0, 1.0]], r"shape \(3,\)"), ("abc", "numeric")],
)
def test_invalid_actions_raise(env: CatheterNavEnv, action: object, match: str) -> None:
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(action)


def test_out_of_range_actions_are_clipped(env: CatheterNavEnv) -> None:
    env.reset(seed=0, options={"start": 0, "target": 0})
    o1, r1, *_ = env.step(np.array([5.0, -7.0, 3.0]))
    env.reset(seed=0, options={"start": 0, "target": 0})
    o2, r2, _, _, info = env.step(np.array([1.0, -1.0, 1.0]))
    np.testing.assert_array_equal(o1, o2)
    lim = math.pi / 2 * 0.0005 / 0.05
    np.testing.assert_allclose(info["bend"], [lim, -lim])
    assert info["insertion"] == pytest.approx(0.0005)
    assert r1 == r2 == pytest.approx(STEP + 1e-5)  # r_bending paid at full bend


def test_step_before_reset_raises() -> None:
    fresh = CatheterNavEnv()
    with pytest.raises(RuntimeError, match="reset"):
        fresh.step(np.zeros(3))


@pytest.mark.parametrize(
    ("kw", "match"),
    [({"mode": "wobbly"}, "mode must be one of"), ({"dt": 0.0}, "dt must be in"),
     ({"max_steps": 0}, "max_steps must be"), ({"theta_max": 4.0}, "theta_max must be in"),
     ({"ray_length": 1.0}, "ray_length must be in"), ({"outer_diameter": 0.1}, "outer_diameter"),
     ({"reward": "x"}, "reward must be a RewardConfig")],
)
def test_config_rejects(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        EnvConfig(**kw)


def test_bad_reset_options(env: CatheterNavEnv) -> None:
    with pytest.raises(ValueError, match="start must be in"):
        env.reset(options={"start": 3})
    with pytest.raises(ValueError, match="options keys"):
        env.reset(options={"goal": 1})
    start = env.scenarios.starts[0]
    for pose, match in (((start.position[:2], start.rotation), "finite \\(3,\\) position"),
                        ((start.position, 2.0 * start.rotation), "orthogonality error 3"),
                        ((start.position, -start.rotation), "determinant -1"),
                        (5, "start_pose must be \\(position, rotation\\)")):
        with pytest.raises(ValueError, match=match):
            env.reset(options={"start": 0, "target": 0, "start_pose": pose})


def test_start_pose_option_replays_from_a_given_pose(env: CatheterNavEnv) -> None:
    """The tip starts at ``start_pose`` with the introducer behind it; the scenario's own pose
    gives the scenario's episode bit for bit."""
    from cgail_sim.scenarios import introducer_tail

    start = env.scenarios.starts[1]
    a = np.array([0.4, -0.3, 1.0], dtype=np.float32)
    obs0, _ = env.reset(options={"start": 1, "target": 2})
    nxt0 = env.step(a)[0]
    obs1, _ = env.reset(options={"start": 1, "target": 2,
                                 "start_pose": (start.position, start.rotation)})
    np.testing.assert_array_equal(obs1, obs0)
    np.testing.assert_array_equal(env.step(a)[0], nxt0)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(0.02), -math.sin(0.02)],
                     [0.0, math.sin(0.02), math.cos(0.02)]])
    p, r = start.position + np.array([0.0, 0.0, 1e-4]), start.rotation @ turn
    obs2, _ = env.reset(options={"start": 1, "target": 2, "start_pose": (p, r)})
    cat = env.catheter
    assert cat.tip_position[0] == pytest.approx(p, abs=0)
    assert cat.tip_rotation[0] == pytest.approx(r, abs=0)
    assert cat.positions[0, 0] == pytest.approx(introducer_tail(env.anatomy, p, r), abs=0)
    assert obs2[2] == pytest.approx(obs0[2] + 1e-4 / 0.15, abs=1e-6)
    assert obs2[6:9] == pytest.approx(r[:, 1], abs=1e-7)


def test_collision_ends_episode_with_r_obst(env: CatheterNavEnv) -> None:
    """Straight insertion from the highest start runs into the arch wall."""
    env.reset(seed=0, options={"start": 2, "target": 0})
    for _ in range(2000):
        _, r, te, tr, info = env.step(np.array([0.0, 0.0, 1.0]))
        if te or tr:
            break
    assert te and not tr
    assert info["collision"] and not info["success"]
    assert info["penetration"] > 0.0
    assert r == pytest.approx(-1.0 + STEP + info["reward_centerline"], abs=1e-12)


def test_retraction_out_of_the_lumen_gives_r_exit(env: CatheterNavEnv) -> None:
    env.reset(seed=0, options={"start": 0, "target": 0})
    for _ in range(200):
        _, r, te, tr, info = env.step(np.array([1.0, 1.0, -1.0]))
        if te or tr:
            break
    assert te and info["exited"] and not info["collision"]
    assert r == pytest.approx(-1.0 + STEP, abs=1e-12)
    assert info["bend"].tolist() == [0.0, 0.0]


def test_truncation_at_max_steps() -> None:
    e = CatheterNavEnv(EnvConfig(max_steps=5))
    e.reset(seed=0)
    for k in range(5):
        _, r, te, tr, info = e.step(np.zeros(3))  # no insertion: nothing happens
        assert r == pytest.approx(STEP, abs=1e-15)
        assert te is False and tr is (k == 4)
    assert info["timesteps"] == 5


def test_theta_max_curriculum(env: CatheterNavEnv) -> None:
    env.reset(seed=0, options={"start": 0, "target": 0})
    env.set_theta_max(math.radians(45))
    _, _, _, _, info = env.step(np.array([1.0, 0.0, 1.0]))
    assert info["bend"][0] == pytest.approx(math.radians(45) * 0.0005 / 0.05)
    env.set_theta_max(math.pi / 2)


def test_scripted_pursuit_reaches_the_target(env: CatheterNavEnv) -> None:
    """Sanity policy: follow the centerline under the FTL constraints, then aim at the target."""
    env.reset(seed=0, options={"start": 0, "target": 1})
    total = 0.0
    for _ in range(2000):
        _, r, te, tr, info = env.step(pursuit_action(env))
        total += r
        if te or tr:
            break
    assert info["success"] and te
    assert info["distance"] < 0.010
    assert info["waypoints_reached"] >= 50
    assert r == pytest.approx(1.0 + STEP + info["reward_centerline"] + info["reward_bending"])
    assert total > 1.0 + 0.05 * 40


def test_reward_config_is_used() -> None:
    e = CatheterNavEnv(EnvConfig(reward=RewardConfig(r_step=-0.5)))
    e.reset(seed=0)
    _, r, *_ = e.step(np.zeros(3))
    assert r == -0.5


@pytest.fixture(scope="module")
def dyn_env() -> CatheterNavEnv:
    return CatheterNavEnv(EnvConfig(mode="dynamic"))


def test_dynamic_target_moves_with_the_wall(dyn_env: CatheterNavEnv) -> None:
    _, info0 = dyn_env.reset(seed=0, options={"start": 0, "target": 0})
    rest = info0["target_position"]
    np.testing.assert_allclose(rest, dyn_env.scenarios.targets[0].position)
    moved = []
    for _ in range(5):  # 0.5 s: half a heartbeat at 70 bpm, no insertion
        _, _, te, _, info = dyn_env.step(np.zeros(3))
        assert not te
        moved.append(np.linalg.norm(info["target_position"] - rest))
        wall = dyn_env.engine.walls[0]
        t = dyn_env.scenarios.targets[0]
        np.testing.assert_allclose(info["target_position"],
                                   wall.vertex_position(t.vertex) + t.offset)
    assert max(moved) > 1e-4  # the heartbeat moves the root (and its ostia) by mm


def test_dynamic_check_env_and_determinism(dyn_env: CatheterNavEnv) -> None:
    check_env(dyn_env, skip_render_check=True)
    other = CatheterNavEnv(replace(EnvConfig(), mode="dynamic"))
    for e in (dyn_env, other):
        e.reset(seed=5)
    rng = np.random.default_rng(3)
    for _ in range(20):
        a = rng.uniform(-1, 1, 3)
        a[2] = abs(a[2])
        o1, r1, *_ = dyn_env.step(a)
        o2, r2, *_ = other.step(a)
        np.testing.assert_array_equal(o1, o2)
        assert r1 == r2


def test_obs_layout_dict_with_normalisers(env: CatheterNavEnv) -> None:
    plain = obs_layout_dict()
    assert plain["dim"] == OBS_DIM and "d_max" not in plain
    assert [f["name"] for f in plain["fields"]][-1] == "rays"
    full = obs_layout_dict(EnvConfig())
    assert full["d_max"] == env.scenarios.d_max
    assert full["origin"] == env.scenarios.origin.tolist()
    assert (full["position_scale"], full["ray_length"]) == (0.15, 0.04)
    json.dumps(full)


def test_render_rgb_array() -> None:
    e = CatheterNavEnv(render_mode="rgb_array")
    e.reset(seed=0)
    e.step(np.array([0.0, 0.0, 1.0]))
    img = e.render()
    assert img is not None and img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[0] > 100 and img.shape[1] > 100
    assert img.std() > 10  # not a blank frame
    assert CatheterNavEnv().render() is None
    with pytest.raises(ValueError, match="render_mode must be"):
        CatheterNavEnv(render_mode="human")


def test_dynamic_registration() -> None:
    made = gym.make("CatheterNavDynamic-v0", config=EnvConfig(max_steps=3))
    assert made.unwrapped.config.mode == "dynamic"
    assert made.unwrapped.config.max_steps == 3
    made.close()


def test_static_contact_broad_phase_is_exact() -> None:
    """Skipping tip queries under the Lipschitz clearance bound changes no contact result."""
    fast, full = CatheterNavEnv(), CatheterNavEnv()
    skipped = 0
    for e in (fast, full):
        e.reset(seed=0, options={"start": 2, "target": 4})
    rng = np.random.default_rng(5)
    for _ in range(400):
        a = rng.uniform(-1, 1, 3)
        a[2] = 0.2 + 0.8 * abs(a[2])
        full.engine._clearance_lb[:] = -np.inf  # force the exact query every step
        _, r1, te1, tr1, i1 = fast.step(a)
        _, r2, te2, tr2, i2 = full.step(a)
        skipped += int(fast.engine._clearance_lb[0] != full.engine._clearance_lb[0])
        assert (r1, te1, tr1) == (r2, te2, tr2)
        for key in ("penetration", "in_contact", "collision", "collision_force"):
            assert i1[key] == i2[key], key
        if te1 or tr1:
            break
    assert te1 and i1["collision"]  # the random walk ends on the wall: contacts were compared
    assert skipped > 10  # and many steps did skip the query

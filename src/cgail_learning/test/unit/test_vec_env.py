"""The batched env equals N single envs step by step (static and dynamic), with auto-reset.

Observations are compared to 1e-6: numpy's vectorised sin/cos may differ from the scalar path in
the last bit (~1e-16), which is all that batching changes.
"""

import numpy as np
import pytest

from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv, OBS_DIM
from cgail_sim.vec_env import CatheterNavVecEnv


def compare(config: EnvConfig, n: int, steps: int, seed: int = 11) -> int:
    """Step a vec env and n single envs with the same actions; return the number of resets."""
    vec = CatheterNavVecEnv(config, num_envs=n)
    singles = [CatheterNavEnv(config) for _ in range(n)]
    obs = vec.reset(seed=seed)
    assert obs.shape == (n, OBS_DIM) and obs.dtype == np.float32
    for i, e in enumerate(singles):
        o, _ = e.reset(seed=seed + i)
        np.testing.assert_allclose(obs[i], o, atol=1e-6)
    rng = np.random.default_rng(0)
    resets = 0
    for _ in range(steps):
        act = rng.uniform(-1.0, 1.0, size=(n, 3))
        act[:, 2] = np.abs(act[:, 2])  # mostly forwards, so episodes end by collision
        obs, rew, term, trunc, infos = vec.step(act.astype(np.float32))
        assert rew.dtype == np.float32
        for i, e in enumerate(singles):
            o, r, te, tr, info = e.step(act[i])
            assert (bool(term[i]), bool(trunc[i])) == (te, tr)
            assert rew[i] == pytest.approx(np.float32(r), abs=1e-9)
            for key in ("success", "collision", "exited", "timesteps", "waypoints_reached"):
                assert infos[i][key] == info[key], key
            assert infos[i]["collision_force"] == pytest.approx(info["collision_force"])
            assert infos[i]["targeting_error"] == pytest.approx(info["targeting_error"])
            if te or tr:
                resets += 1
                np.testing.assert_allclose(infos[i]["final_obs"], o, atol=1e-6)
                o, _ = e.reset()
            else:
                assert "final_obs" not in infos[i]
            np.testing.assert_allclose(obs[i], o, atol=1e-6)
    return resets


def test_static_vec_equals_single() -> None:
    resets = compare(EnvConfig(max_steps=60), n=4, steps=150)
    assert resets >= 4  # truncations and collisions both exercised auto-reset


def test_dynamic_vec_equals_single() -> None:
    compare(EnvConfig(mode="dynamic", max_steps=8), n=2, steps=12)


def test_theta_max_and_bad_input() -> None:
    vec = CatheterNavVecEnv(EnvConfig(), num_envs=2)
    with pytest.raises(RuntimeError, match="reset"):
        vec.step(np.zeros((2, 3)))
    vec.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        vec.step(np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        vec.step(np.array([[0.0, 0.0, np.nan], [0.0, 0.0, 0.0]]))
    vec.set_theta_max(0.5)
    _, _, _, _, infos = vec.step(np.array([[1.0, 0.0, 1.0], [0.0, -1.0, 1.0]]))
    assert infos[0]["bend"][0] == pytest.approx(0.5 * 0.0005 / 0.05)
    assert infos[1]["bend"][1] == pytest.approx(-0.5 * 0.0005 / 0.05)
    with pytest.raises(ValueError, match="num_envs must be"):
        CatheterNavVecEnv(EnvConfig(), num_envs=0)


def test_concatenated_envs_step_as_their_parts() -> None:
    """ConcatVecEnv over two target sets: env i of the whole is env i - offset of its part,
    seeded seed + i, and the parts keep their own target sets."""
    from cgail_learning.envs import ConcatVecEnv

    cfgs = [EnvConfig(scenario_seed=0), EnvConfig(scenario_seed=3)]
    whole = ConcatVecEnv([CatheterNavVecEnv(c, 2) for c in cfgs])
    parts = [CatheterNavVecEnv(c, 2) for c in cfgs]
    assert whole.num_envs == 4
    obs = whole.reset(seed=5)
    np.testing.assert_array_equal(obs, np.concatenate([parts[0].reset(seed=5),
                                                       parts[1].reset(seed=7)]))
    rng = np.random.default_rng(1)
    ended = 0
    for _ in range(300):
        act = rng.uniform(-1, 1, (4, 3)).astype(np.float32)
        act[:, 2] = np.abs(act[:, 2])  # mostly forwards, so episodes end by collision
        o, r, te, tr, infos = whole.step(act)
        ref = [parts[0].step(act[:2]), parts[1].step(act[2:])]
        np.testing.assert_array_equal(o, np.concatenate([ref[0][0], ref[1][0]]))
        np.testing.assert_array_equal(r, np.concatenate([ref[0][1], ref[1][1]]))
        np.testing.assert_array_equal(te | tr, np.concatenate([ref[0][2] | ref[0][3],
                                                               ref[1][2] | ref[1][3]]))
        assert [i['target'] for i in infos] == [i['target'] for p in ref for i in p[4]]
        ended += int((te | tr).sum())
    assert ended > 0
    targets = [p.engine.scenarios.targets[0].position for p in whole.parts]
    assert not np.allclose(targets[0], targets[1])
    whole.set_theta_max(1.0)
    assert all(np.allclose(p.engine.catheter.theta_max, 1.0) for p in whole.parts)
    with pytest.raises(ValueError, match='at least one batched env'):
        ConcatVecEnv([])

"""DAgger labels: the expert's fresh plan for states the learner reached, and the warm start
that clones them with the demonstrations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cgail_learning.dagger import expert_labels
from cgail_learning.errors import DemoError
from cgail_learning.expert import ScriptedExpert
from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv


def _env() -> CatheterNavEnv:
    return CatheterNavEnv(EnvConfig(anatomy='default', max_steps=60))


def test_label_ignores_the_plan_of_an_earlier_state() -> None:
    """After the expert planned at one state and the learner moved elsewhere, ``label`` is the
    plan made afresh at the new state, not the rest of the old plan."""
    env = _env()
    env.reset(seed=0, options={'start': 0, 'target': 0})
    expert = ScriptedExpert(env)
    expert.reset(None)
    expert.act()  # plans replan_every steps and executes the first
    for _ in range(2):
        env.step(np.array([1.0, 1.0, 1.0], np.float32))  # not what the expert planned
    assert len(expert._plan) == expert.cfg.replan_every - 1  # a stale plan is pending
    fresh = ScriptedExpert(env)
    fresh.reset(None)
    fresh._progress = expert._progress
    want = fresh.act()
    np.testing.assert_allclose(expert.label(), want, atol=1e-6)
    assert len(expert._plan) == len(fresh._plan) == expert.cfg.replan_every - 1


def test_labels_cover_every_nth_state_the_learner_reached() -> None:
    env = _env()
    seen: list[np.ndarray] = []

    def learner(obs: np.ndarray) -> np.ndarray:
        seen.append(np.asarray(obs, np.float32).copy())
        return np.array([0.8, -0.3, 1.0], np.float32)  # a learner that drifts into the wall

    obs, act, stats = expert_labels(env, learner, episodes=2, seed=5, every=3)
    assert stats['episodes'] == 2 and stats['labels'] == len(obs) == len(act)
    assert 0.0 <= stats['policy_success'] <= 1.0
    assert obs.dtype == np.float32 and act.dtype == np.float32
    assert obs.shape[1] == env.observation_space.shape[0] and act.shape[1] == 3
    assert np.isfinite(obs).all() and (np.abs(act) <= 1.0).all()
    # the labelled states are the learner's own, every 3rd one of each episode
    lengths, k = [], 0
    for o in obs:
        idx = next(i for i in range(k, len(seen)) if np.array_equal(seen[i], o))
        lengths.append(idx)
        k = idx + 1
    assert lengths[0] == 0 and len(obs) >= 2
    # the expert does not agree with the drifting learner everywhere
    assert not np.allclose(act, [0.8, -0.3, 1.0], atol=0.05)


def test_labels_stop_when_asked_and_reject_a_bad_stride() -> None:
    env = _env()
    calls = []

    def stop() -> bool:
        calls.append(1)
        return len(calls) > 1

    obs, _, stats = expert_labels(env, lambda o: np.zeros(3, np.float32), 5, every=2, stop=stop)
    assert stats['episodes'] == 1 and len(obs) > 0
    _, _, none = expert_labels(env, lambda o: np.zeros(3, np.float32), 0)
    assert none['episodes'] == 0 and np.isnan(none['policy_success'])
    with pytest.raises(ValueError, match='every must be an int >= 1, found 0'):
        expert_labels(env, lambda o: np.zeros(3, np.float32), 1, every=0)


def test_the_warm_start_clones_the_labels_with_the_demonstrations() -> None:
    """``pretrain_bc(extra=...)`` fits the normaliser on demonstrations and labels together,
    moves the policy towards the labels, and names a mis-shaped label set in one line."""
    from cgail_learning.config import config_from_dict, config_to_dict, load_config
    from cgail_learning.envs import ConcatVecEnv
    from cgail_learning.trainer import Trainer
    from cgail_sim.vec_env import CatheterNavVecEnv

    d = config_to_dict(load_config('smoke'))
    d['num_envs'] = 1
    env = ConcatVecEnv([CatheterNavVecEnv(EnvConfig(anatomy='default'), 1)])
    dim = env.single_observation_space.shape[0]
    rng = np.random.default_rng(0)
    demo_obs = rng.normal(0.0, 1.0, (256, dim)).astype(np.float32)
    demo_act = np.tile([0.5, 0.0, 1.0], (256, 1)).astype(np.float32)
    extra_obs = rng.normal(3.0, 1.0, (256, dim)).astype(np.float32)
    extra_act = np.tile([-0.5, 0.0, 1.0], (256, 1)).astype(np.float32)
    trainer = Trainer(config_from_dict(d), env, demo_obs=demo_obs, demo_act=demo_act,
                      demo_episodes=4, seed=0)
    assert trainer.normalizer is not None  # (the smoke preset normalises, as cgail does)
    trainer.pretrain_bc(40, extra=(extra_obs, extra_act))
    assert trainer.normalizer.count.item() == 512
    assert abs(trainer.normalizer.mean.mean().item() - 1.5) < 0.2
    a_demo = trainer.act_deterministic(demo_obs[:64])[:, 0].mean()
    a_label = trainer.act_deterministic(extra_obs[:64])[:, 0].mean()
    assert a_demo > 0.3 and a_label < -0.3, (a_demo, a_label)
    # the demonstrations the GAIL and in-loop BC use are untouched
    assert len(trainer.demo_obs) == 256 and torch.equal(trainer.demo_obs,
                                                       torch.as_tensor(demo_obs))
    with pytest.raises(DemoError, match=r'expected extra finite \(obs, act\) pairs shaped'):
        trainer.pretrain_bc(1, extra=(extra_obs[:, :5], extra_act))

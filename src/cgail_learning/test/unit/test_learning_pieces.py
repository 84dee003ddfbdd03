"""Exact-value tests of the trainer pieces: GAE, PPO clip, GAIL, ICM, BC, curriculum, config."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from cgail_learning.bc import bc_loss, BehavioralCloning
from cgail_learning.buffer import compute_gae, RolloutBuffer
from cgail_learning.config import (
    BCConfig,
    config_from_dict,
    CuriosityConfig,
    CurriculumConfig,
    GailConfig,
    load_config,
    NetworkConfig,
    PRESET_DIR,
)
from cgail_learning.curiosity import capped_reward, Curiosity
from cgail_learning.curriculum import Curriculum
from cgail_learning.errors import ConfigError
from cgail_learning.gail import Gail, gail_reward, gradient_penalty
from cgail_learning.logger import read_event_scalars, ScalarLogger
from cgail_learning.networks import Actor, Critic, RunningNormalizer
from cgail_learning.ppo import (
    clipped_surrogate,
    clipped_value_loss,
    linear_schedule,
    ppo_loss,
)

torch.set_num_threads(1)   # tiny networks: threads only add overhead on the shared CPU


def test_gae_by_hand_with_termination_and_truncation():
    # one env, 3 steps; step 1 truncated (bootstrap from final obs value 5), step 2 terminated
    r = np.array([[1.0], [2.0], [3.0]])
    v = np.array([[0.5], [1.0], [2.0]])
    nv = np.array([[1.0], [5.0], [9.0]])
    term = np.array([[False], [False], [True]])
    ended = np.array([[False], [True], [True]])
    g, lam = 0.9, 0.8
    adv, ret = compute_gae(r, v, nv, term, ended, g, lam)
    d2 = 3.0 - 2.0                      # terminal: no bootstrap
    d1 = 2.0 + 0.9 * 5.0 - 1.0          # truncated: bootstrap, recursion cut
    d0 = 1.0 + 0.9 * 1.0 - 0.5
    a0 = d0 + g * lam * d1
    np.testing.assert_allclose(adv[:, 0], [a0, d1, d2], rtol=1e-6)
    np.testing.assert_allclose(ret[:, 0], [a0 + 0.5, d1 + 1.0, d2 + 2.0], rtol=1e-6)


def test_buffer_advantage_is_mean_of_signals_normalised():
    buf = RolloutBuffer(2, 1, 1, 1, ['extrinsic', 'gail'])
    for t in range(2):
        buf.add(np.zeros((1, 1)), np.zeros((1, 1)), np.zeros(1), np.zeros(1), np.zeros((1, 1)),
                np.array([t == 1]), np.array([t == 1]), {'extrinsic': np.zeros(1),
                                                         'gail': np.zeros(1)})
    buf.rewards['extrinsic'][:, 0] = [1.0, 0.0]
    buf.rewards['gail'][:, 0] = [0.0, 3.0]
    buf.next_values['extrinsic'][:] = 0
    buf.next_values['gail'][:] = 0
    buf.finish({'extrinsic': 0.5, 'gail': 0.0}, lam=1.0)
    # extrinsic gamma .5: adv [1 + .5*0, 0] = [1, 0]; gail gamma 0: [0, 3]; mean [0.5, 1.5]
    mean = np.array([0.5, 1.5])
    np.testing.assert_allclose(buf.advantages[:, 0], (mean - mean.mean()) / mean.std(),
                               rtol=1e-5)
    np.testing.assert_allclose(buf.returns['gail'][:, 0], [0.0, 3.0])


@pytest.mark.parametrize(('ratio', 'adv', 'expected'), [
    (1.5, 1.0, -1.2),    # clipped at 1 + eps
    (0.5, 1.0, -0.5),    # below the clip range a positive advantage is not clipped (min)
    (0.5, -1.0, 0.8),    # clipped at 1 - eps for a negative advantage
    (1.5, -1.0, 1.5),
])
def test_ppo_clipped_surrogate(ratio, adv, expected):
    logp = torch.tensor([math.log(ratio)])
    loss = clipped_surrogate(logp, torch.zeros(1), torch.tensor([adv]), 0.2)
    assert loss.item() == pytest.approx(expected, rel=1e-6)


def test_clipped_value_loss_and_schedule():
    # V moved from 0 to 1, clipped to 0.2; return 1: max((1-1)^2, (1-0.2)^2) = 0.64
    loss = clipped_value_loss(torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([1.0]), 0.2)
    assert loss.item() == pytest.approx(0.64)
    assert linear_schedule(0.2, 0.1, 50, 100) == pytest.approx(0.15)
    assert linear_schedule(0.2, 0.1, 500, 100) == pytest.approx(0.1)
    assert linear_schedule(0.2, 0.1, 50, 100, 'constant') == 0.2


def test_unclipped_value_loss_is_the_plain_squared_error():
    # stable-baselines3's default: V moved from 0 to 1, return 3 -> (3 - 1)^2, no clip to 0.2
    loss = clipped_value_loss(torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([3.0]), None)
    assert loss.item() == pytest.approx(4.0)


@pytest.mark.parametrize(('normalize', 'invariant'), [(True, True), (False, False)])
def test_minibatch_advantage_normalisation_removes_scale_and_shift(normalize, invariant):
    """``ppo.advantage_normalization: minibatch`` (stable-baselines3): the policy loss of
    advantages A and 3 A + 5 is the same; without it, it is not."""
    torch.manual_seed(0)
    net = NetworkConfig(hidden_units=8)
    actor, critic = Actor(3, 2, net, None), Critic(3, ['extrinsic'], net, None)
    obs, act = torch.randn(16, 3), torch.randn(16, 2)
    with torch.no_grad():
        old_logp = actor.distribution(obs).log_prob(act).sum(-1) + 0.3 * torch.randn(16)
    adv = torch.randn(16)
    ret, old_v = {'extrinsic': torch.randn(16)}, {'extrinsic': torch.zeros(16)}

    def policy_loss(a: torch.Tensor) -> float:
        _, st = ppo_loss(actor, critic, obs, act, old_logp, a, ret, old_v, 0.2, 0.0, 0.5,
                         clip_value=False, normalize_advantages=normalize)
        return st.policy_loss

    same = policy_loss(adv) == pytest.approx(policy_loss(3 * adv + 5), rel=1e-4, abs=1e-6)
    assert same == invariant


def test_orthogonal_init_gives_orthogonal_hidden_layers():
    """``network.orthogonal_init`` (stable-baselines3's ``ortho_init``): hidden weights W with
    W W^T = 2 I (gain sqrt 2) and zero biases; value heads gain 1; the default init is not."""
    torch.manual_seed(0)
    for ortho in (True, False):
        net = NetworkConfig(hidden_units=16, orthogonal_init=ortho)
        actor, critic = Actor(32, 2, net, None), Critic(32, ['extrinsic'], net, None)
        w = actor.body[0].weight.detach()
        is_ortho = torch.allclose(w @ w.T, 2.0 * torch.eye(16), atol=1e-4)
        assert is_ortho == ortho
        if ortho:
            assert not actor.body[0].bias.any() and not critic.body[2].bias.any()
            head = critic.heads['extrinsic'].weight.detach()
            assert head.norm().item() == pytest.approx(1.0, rel=1e-4)


def test_the_discriminator_can_normalise_its_own_input():
    """``gail.own_normalizer`` (``imitation``'s RunningNorm): every training batch, expert and
    policy, joins the statistics; inputs are standardised, unclipped; rewards do not update
    them; the statistics travel in the state dict (checkpoints)."""
    torch.manual_seed(0)
    gail = Gail(2, 1, GailConfig(strength=1.0, hidden_units=8, use_actions=True,
                                 own_normalizer=True))
    expert, policy = torch.randn(64, 2) * 10 + 100, torch.randn(64, 2) * 10 - 100
    e_act, p_act = torch.ones(64, 1), -torch.ones(64, 1)
    gail.update(expert, e_act, policy, p_act)
    norm = gail.disc.normalizer
    assert norm is not None and norm.count.item() == pytest.approx(128, abs=1e-3)
    x = gail.disc.inputs(torch.cat([expert, policy]), torch.cat([e_act, p_act]))
    assert x.shape == (128, 4) and not x[:, -1].any()               # the absorbing flag column
    assert x[:, :3].mean(0).abs().max().item() < 1e-3
    assert x[:, :3].std(0, unbiased=False).sub(1).abs().max().item() < 1e-3
    gail.reward(expert, e_act)
    assert norm.count.item() == pytest.approx(128, abs=1e-3)
    assert {'normalizer.mean', 'normalizer.var', 'normalizer.count'} <= set(
        gail.disc.state_dict())
    plain = Gail(2, 1, GailConfig(strength=1.0, hidden_units=8))
    assert plain.disc.normalizer is None and 'normalizer.mean' not in plain.disc.state_dict()


def test_gail_reward_is_ml_agents_form_and_never_negative():
    r = gail_reward(np.array([0.5, 0.9, 0.1, 0.0]))
    np.testing.assert_allclose(r, [math.log(2), -math.log(0.1), -math.log(0.9), 0.0],
                               rtol=1e-5, atol=1e-7)
    assert (r >= 0).all()


def test_gradient_penalty_exact_for_linear_discriminator():
    torch.manual_seed(0)
    gail = Gail(2, 1, GailConfig(strength=1.0, hidden_units=4))
    lin = torch.nn.Linear(2, 1)
    with torch.no_grad():
        lin.weight[:] = torch.tensor([[3.0, 4.0]])   # ||grad logit|| = 5 everywhere
        lin.bias[:] = 0
    gail.disc.net = torch.nn.Sequential(lin)
    gp = gradient_penalty(gail.disc, torch.randn(8, 2), torch.randn(8, 2))
    assert gp.item() == pytest.approx(16.0)


def test_discriminator_learns_expert_vs_policy():
    torch.manual_seed(0)
    gail = Gail(2, 1, GailConfig(strength=1.0, hidden_units=32, learning_rate=3e-3))
    expert, policy = torch.randn(64, 2) + 2.0, torch.randn(64, 2) - 2.0
    for _ in range(200):
        gail.update(expert, None, policy, None)
    assert gail.reward(expert, None).mean() > math.log(2) > gail.reward(policy, None).mean()


@pytest.mark.parametrize(('expert_ends', 'policy_ends', 'keep_going'), [
    (2, 16, True),    # the policy ends its episodes 8x as often (collisions): ending early
                      # must not pay, so each further step is paid
    (16, 2, False),   # the policy ends 8x less often (dawdling): finishing must pay
])
def test_ending_is_paid_by_how_often_the_expert_ends(expert_ends, policy_ends, keep_going):
    """DAC's absorbing state, on states the discriminator cannot tell apart (D(s) = 1/2): the
    sign of the per-step reward says whether ending or going on pays. The shifted form
    ``-log(1 - D) - log 2`` pays 0 either way, ML-Agents' ``-log(1 - D)`` log 2 either way."""
    torch.manual_seed(0)
    gail = Gail(2, 1, GailConfig(strength=1.0, hidden_units=32, learning_rate=3e-3))
    states = torch.randn(64, 2)  # the same states on both sides: only the endings differ
    for _ in range(800):  # (converged by ~500: step 0.47-0.49 / -1.17 to -1.41)
        gail.update(states, None, states, None, expert_absorbing=expert_ends,
                    policy_absorbing=policy_ends)
    assert abs(gail.reward(states, None).mean() - math.log(2)) < 0.15  # D(s) ~ 1/2
    step = float(gail.step_reward(states, None).mean())
    # D(absorbing) ~ the ending frequencies' ratio (2/66 vs 16/80): -log(1 - D) 0.14 or 2.0
    # (measured 0.28 and 2.0)
    assert (step > 0.3) if keep_going else (step < -0.8), step


def test_icm_reward_is_capped_and_zero_before_update():
    np.testing.assert_allclose(capped_reward(np.array([0.1, 10.0, 100.0]), 0.02),
                               [0.1, 10.0, 50.0])
    cur = Curiosity(3, 2, CuriosityConfig(strength=0.5, encoding_size=8))
    obs = torch.randn(4, 3) * 100
    act = torch.zeros(4, 2)
    np.testing.assert_array_equal(cur.reward(obs, act, -obs), np.zeros(4))
    cur.update(obs, act, -obs)
    r = cur.reward(obs, act, -obs)
    assert np.all(r <= 1.0 / 0.5 + 1e-6) and np.all(r >= 0)


def test_curriculum_changes_lesson_after_min_episodes_and_threshold():
    cur = Curriculum(CurriculumConfig(theta_max_deg=(90.0, 60.0, 45.0), measure='success',
                                      thresholds=(0.5, 0.9), min_lesson_length=4))
    assert cur.theta_max == pytest.approx(math.pi / 2)
    assert not any(cur.record(0.0, True) for _ in range(3))    # too few episodes
    assert cur.record(0.0, False)                              # 3/4 = 0.75 >= 0.5
    assert cur.lesson == 1 and cur.theta_max == pytest.approx(math.pi / 3)
    assert not any(cur.record(0.0, s) for s in (True, True, True, False))  # 0.75 < 0.9
    assert cur.lesson == 1


def test_bc_step_lowers_bc_loss():
    torch.manual_seed(0)
    actor = Actor(4, 2, NetworkConfig(hidden_units=32), None)
    obs = np.random.default_rng(0).normal(size=(256, 4)).astype(np.float32)
    act = np.tanh(obs[:, :2] - obs[:, 2:]).astype(np.float32)
    bc = BehavioralCloning(actor, obs, act, BCConfig(strength=1.0, batch_size=64), 3e-3)
    before = bc_loss(actor, torch.as_tensor(obs), torch.as_tensor(act)).item()
    bc.update(0, 3e-3, 256, np.random.default_rng(0))
    after = bc_loss(actor, torch.as_tensor(obs), torch.as_tensor(act)).item()
    assert after < 0.9 * before


def test_bc_strength_scales_learning_rate():
    actor = Actor(2, 1, NetworkConfig(hidden_units=8), None)
    bc = BehavioralCloning(actor, np.zeros((4, 2), np.float32), np.zeros((4, 1), np.float32),
                           BCConfig(strength=0.14, batch_size=4, steps=100), 3e-4)
    stats = bc.update(50, 3e-4, 4, np.random.default_rng(0))
    assert stats['policy/bc_learning_rate'] == pytest.approx(3e-4 * 0.07)


def test_bc_ml_agents_schedule_decays_once_over_the_whole_buffer():
    """``schedule: ml-agents``, as ML-Agents' ``BCModule`` (``trainers/torch/components/bc/
    module.py``: ``current_lr = policy_learning_rate * strength``, ``DecayedValue(LINEAR,
    current_lr, 1e-10, steps)``, ``samples_per_update`` 0 = every demo batch): the authors'
    softAorta12 BC (strength 0.5, steps 8M, policy lr 5e-4). The policy's own decayed rate
    plays no part; ``ours`` multiplies it in and caps a pass at ``max_samples``."""
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(2560, 2)).astype(np.float32)
    act = np.zeros((2560, 1), np.float32)
    cfg = BCConfig(strength=0.5, batch_size=256, num_epoch=1, steps=8_000_000,
                   schedule='ml-agents')
    bc = BehavioralCloning(Actor(2, 1, NetworkConfig(hidden_units=8), None), obs, act, cfg,
                           5e-4)
    assert bc.learning_rate(0, 1e-9) == pytest.approx(2.5e-4, rel=1e-9)
    assert bc.learning_rate(4_000_000, 1e-9) == pytest.approx(1.25e-4, rel=1e-6)
    assert bc.learning_rate(8_000_000, 1e-9) == pytest.approx(1e-10, rel=1e-6)
    assert bc.learning_rate(9_000_000, 5e-4) == pytest.approx(1e-10, rel=1e-6)
    stats = bc.update(2_000_000, 1e-9, 1024, np.random.default_rng(0))
    assert stats['policy/bc_learning_rate'] == pytest.approx(1.875e-4, rel=1e-6)
    steps = {int(st['step']) for st in bc.opt.state.values()}
    assert steps == {2560 // 256}  # the whole buffer, not the 1024 of max_samples

    ours = BehavioralCloning(Actor(2, 1, NetworkConfig(hidden_units=8), None), obs, act,
                             dataclasses.replace(cfg, schedule='ours'), 5e-4)
    stats = ours.update(2_000_000, 3.75e-4, 1024, np.random.default_rng(0))
    assert stats['policy/bc_learning_rate'] == pytest.approx(3.75e-4 * 0.5 * 0.75, rel=1e-9)
    assert {int(st['step']) for st in ours.opt.state.values()} == {1024 // 256}


def test_bc_schedule_is_written_only_when_not_ours():
    """A config dict written before ``bc.schedule`` existed still equals today's (``--resume``
    compares them), and the authors' presets select ``ml-agents``."""
    from cgail_learning.config import config_to_dict

    for name in ('cgail', 'smoke', 'gail', 'generalist'):
        cfg = load_config(name)
        assert cfg.bc.schedule == 'ours' and 'schedule' not in config_to_dict(cfg)['bc']
    for name in ('paper_code_cgail', 'paper_code_lambda0'):
        d = config_to_dict(load_config(name))
        assert d['bc']['schedule'] == 'ml-agents'
        assert config_from_dict(d).bc.schedule == 'ml-agents'
    with pytest.raises(ConfigError, match=r"bc.schedule must be one of \['ours', 'ml-agents'\]"):
        config_from_dict({'bc': {'schedule': 'mlagents'}})


def test_normalizer_matches_numpy():
    rng = np.random.default_rng(1)
    a, b = rng.normal(3, 2, (100, 3)), rng.normal(-1, 0.5, (50, 3))
    norm = RunningNormalizer(3)
    norm.update(a)
    norm.update(b)
    both = np.concatenate([a, b])
    np.testing.assert_allclose(norm.mean.numpy(), both.mean(0), rtol=1e-4)
    np.testing.assert_allclose(norm.var.numpy(), both.var(0), rtol=1e-3)


@pytest.mark.parametrize('name', ['cgail', 'gail', 'mu0', 'lambda0', 'nu0', 'smoke'])
def test_presets_load(name):
    cfg = load_config(name)
    assert cfg.name == name


def test_cgail_preset_is_the_papers_table():
    cfg = load_config('cgail')
    assert cfg.extrinsic.strength == pytest.approx(0.2 * (1 - 0.7))
    assert cfg.gail.strength == 0.8 and cfg.bc.strength == pytest.approx(0.2 * 0.7)
    assert cfg.curiosity.strength == 0.02 and cfg.ppo.beta == 5e-4
    assert (cfg.ppo.batch_size, cfg.ppo.buffer_size, cfg.max_steps) == (1024, 10240, 500_000)
    assert cfg.extrinsic.gamma == cfg.gail.gamma == 0.99
    gail = load_config('gail')   # pure GAIL (the authors' chi_soft_gail), SB3/imitation settings
    assert gail.network.hidden_units == 64 and gail.network.activation == 'tanh'
    assert gail.bc.strength == gail.curiosity.strength == gail.extrinsic.strength == 0
    assert (gail.gail.strength, gail.gail.reward_form, gail.max_steps) == (1.0, 'standard',
                                                                           2_000_000)
    assert load_config('mu0').bc.strength == 0 and load_config('lambda0').gail.strength == 0
    assert load_config('nu0').curiosity.strength == 0


@pytest.mark.parametrize(('data', 'match'), [
    ({'ppo': {'batchsize': 3}}, r"unknown key 'ppo.batchsize'"),
    ({'ppo': {'beta': 2.0}}, r'ppo.beta must be in \[0, 1\], found 2.0'),
    ({'gail': {'strength': -1}}, r'gail.strength must be in \[0, 10\]'),
    ({'ppo': {'batch_size': 1000, 'buffer_size': 1500}}, 'ppo.buffer_size must be a multiple'),
    ({'max_steps': 'many'}, 'max_steps must be of type int'),
    ({'ppo': {'advantage_normalization': 'episode'}},
     r"ppo.advantage_normalization must be 'buffer' or 'minibatch', found 'episode'"),
    ({'curriculum': {'theta_max_deg': [60, 90], 'thresholds': [1]}}, 'non-increasing'),
])
def test_bad_config_names_key_and_range(data, match):
    with pytest.raises(ConfigError, match=match):
        config_from_dict(data)


def test_unknown_preset_lists_the_presets(tmp_path: Path):
    with pytest.raises(ConfigError, match='cgail'):
        load_config('nope')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('network: {hidden_units: 0}\n')
    with pytest.raises(ConfigError, match=r'network.hidden_units must be in \[1, 4096\]'):
        load_config(bad)
    assert (PRESET_DIR / 'cgail.yaml').is_file()


def test_scalar_logger_writes_readable_event_file(tmp_path: Path):
    log = ScalarLogger(tmp_path)
    log.log(10, {'losses/value_loss': 0.5, 'eval/success_rate': 0.25})
    log.close()
    events = list(tmp_path.glob('events.out.tfevents.*'))
    assert len(events) == 1
    assert read_event_scalars(events[0]) == [('losses/value_loss', 0.5, 10),
                                             ('eval/success_rate', 0.25, 10)]
    data = events[0].read_bytes()
    flipped = tmp_path / 'flipped'
    flipped.write_bytes(data[:-6] + bytes([data[-6] ^ 0xFF]) + data[-5:])
    with pytest.raises(ValueError, match='CRC mismatch'):
        read_event_scalars(flipped)
    flipped.write_bytes(data[:-3])
    with pytest.raises(ValueError, match='corrupt record'):
        read_event_scalars(flipped)
    assert (tmp_path / 'scalars.csv').read_text().splitlines()[1] == '10,losses/value_loss,0.5'


def test_sync_vec_env_steps_as_gymnasiums_same_step_vector_env() -> None:
    """Why SyncVecEnv is ours (its docstring): gymnasium's SyncVectorEnv in same-step
    auto-reset mode gives the same observations, rewards, ends and final observations, but the
    ended env's top-level info is the reset's; ours is the ended step's, as the trainer reads
    it."""
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode

    from cgail_learning.envs import SyncVecEnv
    from cgail_learning.testing import PointReach

    ours = SyncVecEnv([PointReach] * 4)
    lib = gym.vector.SyncVectorEnv([PointReach] * 4, autoreset_mode=AutoresetMode.SAME_STEP)
    assert np.array_equal(ours.reset(seed=3), lib.reset(seed=3)[0])
    rng = np.random.default_rng(0)
    ended = successes = 0
    for _ in range(400):
        act = rng.uniform(-1.0, 1.0, size=(4, *ours.single_action_space.shape))
        obs, rew, term, trunc, infos = ours.step(act.astype(np.float32))
        obs2, rew2, term2, trunc2, info2 = lib.step(act.astype(np.float32))
        assert np.array_equal(obs, obs2) and np.array_equal(rew, rew2.astype(np.float32))
        assert np.array_equal(term, term2) and np.array_equal(trunc, trunc2)
        for i in np.flatnonzero(term | trunc):
            ended += 1
            assert np.array_equal(infos[i]['final_obs'], info2['final_obs'][i])
            assert infos[i]['is_success'] == info2['final_info']['is_success'][i]
            if infos[i]['is_success']:
                successes += 1
                assert not info2['is_success'][i]  # gymnasium's top level: the reset's info
    assert ended >= 20 and successes >= 1

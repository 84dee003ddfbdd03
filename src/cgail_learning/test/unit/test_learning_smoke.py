"""Smoke training on the toy point-reaching env: the full C-GAIL machinery must learn."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cgail_learning.config import config_from_dict
from cgail_learning.envs import SyncVecEnv
from cgail_learning.errors import DemoError, PolicyLoadError
from cgail_learning.testing import expert_demos, PointReach
from cgail_learning.train import run_training
from cgail_learning.trainer import evaluate_policy, Trainer

SMOKE = {
    'name': 'toy', 'max_steps': 12288, 'num_envs': 8,
    'network': {'hidden_units': 64},
    'ppo': {'learning_rate': 1e-3, 'batch_size': 256, 'buffer_size': 1024,
            'schedule': 'constant'},
    'extrinsic': {'strength': 0.06}, 'gail': {'strength': 0.8, 'hidden_units': 64},
    'bc': {'strength': 1.0, 'batch_size': 64, 'num_epoch': 8}, 'curiosity': {'strength': 0.02,
                                                            'encoding_size': 16},
    'curriculum': {'theta_max_deg': [90, 60], 'measure': 'success', 'thresholds': [0.3],
                   'min_lesson_length': 20},
    'eval_every': 6144, 'eval_episodes': 20, 'checkpoint_every': 6144,
}


def _trainer(seed: int, **over) -> Trainer:
    torch.set_num_threads(1)
    cfg = config_from_dict({**SMOKE, **over})
    demo_obs, demo_act = expert_demos(40)
    return Trainer(cfg, SyncVecEnv([PointReach] * cfg.num_envs), demo_obs=demo_obs,
                   demo_act=demo_act, seed=seed, demo_episodes=40)


def test_cgail_learns_on_toy_env(tmp_path: Path):
    trainer = _trainer(0)
    before = evaluate_policy(trainer.act_deterministic, PointReach(), 20, seed=500)
    result = run_training(trainer, PointReach(), tmp_path, progress=False)
    after = evaluate_policy(trainer.act_deterministic, PointReach(), 20, seed=500)
    assert before['eval/success_rate'] == 0.0
    assert after['eval/success_rate'] >= 0.6, result
    assert trainer.curriculum.lesson == 1          # success passed 0.3 over 20 episodes
    assert trainer.env.envs[0].theta_max == pytest.approx(np.radians(60))
    assert (tmp_path / 'final.pt').is_file() and (tmp_path / 'best.pt').is_file()
    assert (tmp_path / 'checkpoints' / 'step_6144.pt').is_file()
    tags = {line.split(',')[1] for line in (tmp_path / 'scalars.csv').read_text().splitlines()}
    assert {'losses/value_loss', 'losses/gail_loss', 'losses/bc_loss', 'eval/success_rate',
            'losses/curiosity_forward_loss', 'policy/beta'} <= tags


def test_same_seed_reproduces_the_run():
    a = _trainer(3, max_steps=1024)
    sa = a.train_iteration()
    b = _trainer(3, max_steps=1024)
    sb = b.train_iteration()
    assert sa == sb
    obs = np.zeros((2, 4), np.float32)
    np.testing.assert_array_equal(a.act_deterministic(obs), b.act_deterministic(obs))


def test_init_from_checkpoint_copies_the_policy(tmp_path: Path):
    a = _trainer(1, max_steps=1024)
    a.train_iteration()
    a.save(tmp_path / 'a.pt')
    b = _trainer(2, max_steps=1024)
    b.load_weights(tmp_path / 'a.pt')
    obs = np.random.default_rng(0).normal(size=(5, 4)).astype(np.float32)
    np.testing.assert_allclose(a.act_deterministic(obs), b.act_deterministic(obs))
    with pytest.raises(PolicyLoadError, match='checkpoint not found'):
        b.load_weights(tmp_path / 'missing.pt')
    (tmp_path / 'bad.pt').write_bytes(b'not a checkpoint')
    with pytest.raises(PolicyLoadError, match='not a readable checkpoint'):
        b.load_weights(tmp_path / 'bad.pt')


def test_missing_or_mismatched_demos_are_errors():
    cfg = config_from_dict(SMOKE)
    with pytest.raises(DemoError, match='expected demonstrations'):
        Trainer(cfg, SyncVecEnv([PointReach]))
    with pytest.raises(DemoError, match=r'expected obs \(M, 4\)'):
        Trainer(cfg, SyncVecEnv([PointReach]), demo_obs=np.zeros((3, 5), np.float32),
                demo_act=np.zeros((3, 2), np.float32))
    for episodes in (None, 0, 4):  # GAIL's absorbing state needs the episode count
        with pytest.raises(DemoError, match=r'expected the number of demonstration episodes, '
                                            r'in \[1, 3\]'):
            Trainer(cfg, SyncVecEnv([PointReach]), demo_obs=np.zeros((3, 4), np.float32),
                    demo_act=np.zeros((3, 2), np.float32), demo_episodes=episodes)


def test_bc_warm_start_solves_the_toy_env_before_any_env_step():
    trainer = _trainer(4)
    before = evaluate_policy(trainer.act_deterministic, PointReach(), 20, seed=500)
    demo = trainer.demo_obs.numpy().astype(np.float64)
    stats = trainer.pretrain_bc(30, batch_size=32)  # (211 demo pairs: 7 steps per epoch)
    after = evaluate_policy(trainer.act_deterministic, PointReach(), 20, seed=500)
    assert before['eval/success_rate'] == 0.0
    assert after['eval/success_rate'] >= 0.6  # (0.70-0.80 over seeds 4-6 and 30-100 epochs)
    assert trainer.step == 0 and stats['bc_pretrain/epochs'] == 30
    # the normaliser now holds the demonstrations' statistics
    np.testing.assert_allclose(trainer.normalizer.mean.numpy(), demo.mean(0), rtol=1e-6,
                               atol=1e-9)
    np.testing.assert_allclose(trainer.normalizer.var.numpy(), demo.var(0), rtol=1e-6,
                               atol=1e-9)
    # the expert's actions are reproduced (the loss sums the squared error over 2 action dims;
    # 0.04-0.06 measured)
    assert stats['losses/bc_pretrain_loss'] < 0.15
    with pytest.raises(ValueError, match='expected epochs >= 1'):
        trainer.pretrain_bc(0)
    ppo_only = config_from_dict({**SMOKE, 'gail': {'strength': 0.0}, 'bc': {'strength': 0.0}})
    with pytest.raises(DemoError, match='pretrain_bc: expected demonstrations'):
        Trainer(ppo_only, SyncVecEnv([PointReach])).pretrain_bc(5)


@pytest.mark.parametrize('form', ['absorbing', 'standard'])
def test_the_gail_reward_form_decides_what_the_policy_is_paid(form: str):
    """``standard`` pays ML-Agents' ``-log(1 - D)`` (never negative) and trains the
    discriminator without absorbing rows; ``absorbing`` pays it relative to the absorbing
    state's reward and logs that reward."""
    trainer = _trainer(0, max_steps=2048, gail={'strength': 0.8, 'hidden_units': 64,
                                                'reward_form': form})
    seen: dict[str, int] = {}
    update = trainer.gail.update

    def spy(*args, **kwargs):
        seen['absorbing'] = seen.get('absorbing', 0) + kwargs['expert_absorbing'] + \
            kwargs['policy_absorbing']
        return update(*args, **kwargs)

    trainer.gail.update = spy
    scalars = {}
    while trainer.step < 2048:
        scalars = trainer.train_iteration()
    assert ('rewards/gail_absorbing' in scalars) == (form == 'absorbing')
    if form == 'standard':
        assert seen['absorbing'] == 0 and scalars['rewards/gail_mean'] >= 0.0
    else:
        assert seen['absorbing'] > 0  # the toy's episodes end within the buffer


@pytest.mark.parametrize('per_buffer', [0, 3])
def test_the_discriminator_steps_per_buffer(per_buffer: int):
    """``gail.updates_per_buffer`` 0: one discriminator step per PPO minibatch (ML-Agents: 3
    epochs x 1024 / 256 = 12 per buffer, each on 256 policy samples); N: N steps per buffer on
    ``gail.batch_size`` policy samples each (imitation's rounds)."""
    trainer = _trainer(0, max_steps=1024,
                       gail={'strength': 0.8, 'hidden_units': 64, 'updates_per_buffer': per_buffer,
                             'batch_size': 100})
    sizes: list[int] = []
    update = trainer.gail.update

    def spy(expert_obs, expert_act, policy_obs, policy_act, **kwargs):
        sizes.append(len(policy_obs))
        assert len(expert_obs) + kwargs['expert_absorbing'] == len(policy_obs)
        return update(expert_obs, expert_act, policy_obs, policy_act, **kwargs)

    trainer.gail.update = spy
    before = [p.detach().clone() for p in trainer.gail.disc.parameters()]
    trainer.train_iteration()
    assert sizes == ([256] * 12 if per_buffer == 0 else [100] * per_buffer)
    assert any((p != q).any() for p, q in zip(trainer.gail.disc.parameters(), before, strict=True))


IMITATION_LIKE = dict(
    max_steps=1024, normalize=False, extrinsic={'strength': 0.0}, bc={'strength': 0.0},
    curiosity={'strength': 0.0}, curriculum={},
    network={'hidden_units': 64, 'orthogonal_init': True},
    ppo={'learning_rate': 1e-3, 'batch_size': 256, 'buffer_size': 1024, 'schedule': 'constant',
         'advantage_normalization': 'minibatch', 'clip_value_loss': False},
    gail={'strength': 1.0, 'hidden_units': 64, 'use_actions': True, 'reward_form': 'standard',
          'gradient_penalty': 0.0, 'own_normalizer': True, 'updates_per_buffer': 2,
          'batch_size': 100})


def test_a_trainer_at_the_imitation_librarys_settings_runs_and_checkpoints(tmp_path: Path):
    """stable-baselines3's PPO options (orthogonal init, minibatch advantage normalisation, no
    value clipping, no observation normaliser) and ``imitation``'s discriminator (its own input
    normaliser on (s, a), 2 steps of 100 a buffer): one iteration trains every part, and the
    discriminator's statistics survive a checkpoint."""
    from cgail_learning.checkpoint import load_checkpoint
    trainer = _trainer(0, **IMITATION_LIKE)
    assert trainer.normalizer is None and list(trainer.signals) == ['gail']
    scalars = trainer.train_iteration()
    norm = trainer.gail.disc.normalizer
    assert norm is not None and norm.count.item() == pytest.approx(2 * 200, abs=1e-3)
    assert np.isfinite(scalars['losses/value_loss']) and scalars['rewards/gail_mean'] >= 0.0
    trainer.save(tmp_path / 'a.pt')
    again = _trainer(1, **IMITATION_LIKE)
    assert not torch.equal(again.gail.disc.normalizer.mean, norm.mean)
    again.resume(load_checkpoint(tmp_path / 'a.pt'), tmp_path / 'a.pt')
    assert torch.equal(again.gail.disc.normalizer.mean, norm.mean)


def test_gail_update_settings_out_of_range_are_one_line():
    with pytest.raises(Exception, match=r'gail\.updates_per_buffer must be in \[0, 10000\]'):
        config_from_dict({**SMOKE, 'gail': {'strength': 0.8, 'updates_per_buffer': -1}})
    with pytest.raises(Exception, match=r'gail\.batch_size must be in \[1, 1e6\]'):
        config_from_dict({**SMOKE, 'gail': {'strength': 0.8, 'batch_size': 0}})


def test_an_unknown_gail_reward_form_is_one_line():
    with pytest.raises(Exception, match=r"gail\.reward_form must be 'absorbing' or "
                                        r"'standard', found 'shifted'"):
        config_from_dict({**SMOKE, 'gail': {'strength': 0.8, 'reward_form': 'shifted'}})


def test_a_resumed_trainer_continues_where_its_checkpoint_stood(tmp_path: Path):
    """``Trainer.resume``: step, update count, networks, optimisers, random streams, curriculum
    and episode statistics are those of the checkpoint; a checkpoint of another configuration
    or without the resume state is refused in one line."""
    from cgail_learning.checkpoint import load_checkpoint
    from cgail_learning.errors import PolicyLoadError

    a = _trainer(3, max_steps=8192)
    while a.step < 2048:
        a.train_iteration()
    a.save(tmp_path / 'a.pt', run={'best': 0.5})
    ckpt = load_checkpoint(tmp_path / 'a.pt')
    assert ckpt['run'] == {'best': 0.5} and not (tmp_path / 'a.pt.tmp').exists()
    b = _trainer(3, max_steps=16384)  # (a larger budget may extend a run)
    b.resume(ckpt, tmp_path / 'a.pt')
    assert torch.equal(torch.get_rng_state(), ckpt['resume']['torch_rng'])
    assert (b.step, b.n_updates, b.curriculum.lesson) == (a.step, a.n_updates,
                                                          a.curriculum.lesson)
    assert list(b.stats.successes) == list(a.stats.successes) and len(b.stats.successes) > 0
    for pa, pb in zip(a.actor.parameters(), b.actor.parameters(), strict=True):
        assert torch.equal(pa, pb)
    for name, opt in a._optimizers().items():
        sa, sb = opt.state_dict()['state'], b._optimizers()[name].state_dict()['state']
        assert sa.keys() == sb.keys() and all(
            torch.equal(sa[k]['exp_avg'], sb[k]['exp_avg']) for k in sa), name
    assert a.rng.integers(0, 2**31, 4).tolist() == b.rng.integers(0, 2**31, 4).tolist()
    b.train_iteration()  # and it trains on
    assert b.step > a.step

    other = _trainer(3, max_steps=8192, ppo={**SMOKE['ppo'], 'learning_rate': 5e-4})
    with pytest.raises(PolicyLoadError, match='expected a checkpoint of this configuration'):
        other.resume(ckpt, tmp_path / 'a.pt')
    del ckpt['resume']
    with pytest.raises(PolicyLoadError, match='expected a checkpoint with its resume state'):
        b.resume(ckpt, tmp_path / 'a.pt')

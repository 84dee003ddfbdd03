"""ONNX export: torch/onnxruntime parity, metadata, loader errors, identical rollouts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cgail_learning.config import NetworkConfig
from cgail_learning.errors import PolicyLoadError
from cgail_learning.export import default_contract, export_actor, write_contract
from cgail_learning.networks import Actor, RunningNormalizer
from cgail_learning.testing import PointReach
from cgail_planner.core.onnx_policy import OnnxPolicy
from cgail_sim.ftl_model import CONTRACT_KEY


def _actor(obs_dim: int, act_dim: int, seed: int = 0) -> Actor:
    torch.manual_seed(seed)
    norm = RunningNormalizer(obs_dim)
    norm.update(np.random.default_rng(seed).normal(2.0, 3.0, (500, obs_dim)))
    actor = Actor(obs_dim, act_dim, NetworkConfig(hidden_units=32), norm)
    with torch.no_grad():
        actor.mu.weight.mul_(1000)   # non-trivial, partly saturated actions
    return actor.eval()


def test_parity_and_metadata(tmp_path: Path):
    actor = _actor(41, 3)
    contract = default_contract('default', 'static', {'preset': 'cgail'})
    path = export_actor(actor, tmp_path / 'p.onnx', {'preset': 'cgail', 'anatomy': 'default',
                                                      CONTRACT_KEY: contract.to_dict()})
    policy = OnnxPolicy(path, expected_obs_dim=41)
    obs = np.random.default_rng(1).normal(2.0, 4.0, (256, 41)).astype(np.float32)
    with torch.no_grad():
        ref = actor.deterministic(torch.as_tensor(obs)).numpy()
    np.testing.assert_allclose(policy(obs), ref, atol=1e-5)
    np.testing.assert_allclose(policy(obs[0]), ref[0], atol=1e-5)
    assert np.any(np.abs(ref) == 1.0) and np.all(np.abs(ref) <= 1.0)
    assert policy.metadata['preset'] == 'cgail' and policy.metadata['obs_dim'] == 41
    assert policy.contract is not None
    assert policy.contract.to_dict() == contract.to_dict()
    assert policy.contract.observation.same_as(contract.observation)


def test_a_contract_is_written_into_an_exported_file_and_the_graph_is_kept(tmp_path: Path):
    import onnx

    path = export_actor(_actor(41, 3), tmp_path / 'p.onnx', {'theta_max_rad': 1.5707963})
    assert OnnxPolicy(path).contract is None
    contract = default_contract('default', 'dynamic', {'note': 'x'})
    write_contract(path, contract, tmp_path / 'q.onnx')
    before, after = onnx.load(str(path)), onnx.load(str(tmp_path / 'q.onnx'))
    assert before.graph == after.graph
    policy = OnnxPolicy(tmp_path / 'q.onnx')
    assert policy.contract is not None and policy.contract.mode == 'dynamic'
    assert policy.contract.training == {'note': 'x'}
    assert 'theta_max_rad' not in policy.metadata  # the legacy key is gone


@pytest.mark.parametrize(('edit', 'match'), [
    (lambda d: d.update(retraction_rule='stop at the start pose'), 'retraction_rule: expected'),
    (lambda d: d.update(version=99), 'version: expected 1, found 99'),
    (lambda d: d['catheter'].update(theta_max=7.0), 'theta_max must be in'),
    (lambda d: d['observation'].pop('d_max'), "expected the keys of ObservationSpec"),
    (lambda d: d['observation'].update(dim=40), 'observation layout: expected'),
])
def test_a_contract_that_cannot_be_read_refuses_the_policy(tmp_path: Path, edit, match):
    data = default_contract('default', 'static').to_dict()
    edit(data)
    path = export_actor(_actor(41, 3), tmp_path / 'p.onnx', {CONTRACT_KEY: data})
    with pytest.raises(PolicyLoadError, match=match):
        OnnxPolicy(path)


def test_a_contract_of_another_observation_size_refuses_the_policy(tmp_path: Path):
    data = default_contract('default', 'static').to_dict()
    path = export_actor(_actor(40, 3), tmp_path / 'p.onnx', {CONTRACT_KEY: data})
    with pytest.raises(PolicyLoadError, match="expected the model's 40, found 41"):
        OnnxPolicy(path)


def test_loader_errors(tmp_path: Path):
    with pytest.raises(PolicyLoadError, match='not found'):
        OnnxPolicy(tmp_path / 'missing.onnx')
    bad = tmp_path / 'bad.onnx'
    bad.write_bytes(b'\x00garbage')
    with pytest.raises(PolicyLoadError, match='not a loadable ONNX model'):
        OnnxPolicy(bad)
    path = export_actor(_actor(4, 2), tmp_path / 'p.onnx', {})
    with pytest.raises(PolicyLoadError, match='expected 41, found 4'):
        OnnxPolicy(path, expected_obs_dim=41)
    with pytest.raises(PolicyLoadError, match=r'expected \(B, 4\), found \(5,\)'):
        OnnxPolicy(path)(np.zeros(5))


def test_onnx_module_does_not_import_torch():
    src = (Path(__file__).parents[3] / 'cgail_planner' / 'cgail_planner' / 'core'
           / 'onnx_policy.py')
    text = src.read_text()
    assert 'import torch' not in text and 'from torch' not in text


def _rollout(policy, env, seed: int) -> list[np.ndarray]:
    obs, _ = env.reset(seed=seed)
    traj = [obs]
    for _ in range(60):
        obs, _, te, tr, _ = env.step(policy(obs))
        traj.append(obs)
        if te or tr:
            break
    return traj


def test_onnx_rollout_equals_torch_rollout_on_toy_env(tmp_path: Path):
    actor = _actor(4, 2, seed=3)
    policy = OnnxPolicy(export_actor(actor, tmp_path / 'p.onnx', {}))

    def torch_policy(o: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return actor.deterministic(torch.as_tensor(o[None])).numpy()[0]

    a, b = _rollout(torch_policy, PointReach(), 7), _rollout(policy, PointReach(), 7)
    assert len(a) == len(b)
    np.testing.assert_allclose(np.stack(a), np.stack(b), atol=1e-5)


@pytest.mark.slow
def test_onnx_rollout_equals_torch_rollout_in_simulator(tmp_path: Path):
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    env = CatheterNavEnv(EnvConfig(mode='static'))
    actor = _actor(env.observation_space.shape[0], 3, seed=5)
    policy = OnnxPolicy(export_actor(actor, tmp_path / 'p.onnx', {}))

    def torch_policy(o: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return actor.deterministic(torch.as_tensor(o[None])).numpy()[0]

    def run(pol) -> tuple[np.ndarray, dict]:
        obs, _ = env.reset(seed=0, options={'start': 1, 'target': 2})
        tips = []
        for _ in range(150):
            obs, _, te, tr, info = env.step(pol(obs))
            tips.append(env.catheter.tip_position[0].copy())
            if te or tr:
                break
        return np.stack(tips), info

    (ta, ia), (tb, ib) = run(torch_policy), run(policy)
    assert ta.shape == tb.shape
    np.testing.assert_allclose(ta, tb, atol=1e-6)
    assert ia['success'] == ib['success'] and ia['collision'] == ib['collision']


def test_training_notes_record_the_curriculum_lesson_of_the_checkpoint():
    import math

    from cgail_learning.export import training_notes

    ckpt = {'config': {'name': 'cgail', 'curriculum': {'theta_max_deg': [90.0, 75.0, 60.0]}},
            'step': 491520, 'curriculum_lesson': 1}
    assert training_notes(ckpt) == {
        'preset': 'cgail', 'train_steps': 491520, 'curriculum_theta_max_deg': [90.0, 75.0, 60.0],
        'curriculum_lesson': 1, 'final_theta_max_rad': math.radians(75.0)}
    no_curriculum = {'config': {'name': 'gail'}, 'step': 5, 'curriculum_lesson': 0}
    assert training_notes(no_curriculum)['final_theta_max_rad'] is None


# ----------------------------------------------------------------------------------------------
# Fine-tuning from an export: the actor and its normaliser read back
# ----------------------------------------------------------------------------------------------
def _trainer(hidden: int = 32, normalize: bool = True):
    from cgail_learning.config import config_from_dict
    from cgail_learning.trainer import Trainer

    cfg = config_from_dict({'name': 't', 'max_steps': 1024, 'num_envs': 2, 'normalize': normalize,
                            'network': {'hidden_units': hidden, 'init_log_std': -1.5},
                            'ppo': {'batch_size': 64, 'buffer_size': 128}})
    from cgail_sim.config import EnvConfig
    from cgail_sim.vec_env import CatheterNavVecEnv

    return Trainer(cfg, CatheterNavVecEnv(EnvConfig(), 2), seed=3)


def test_an_exported_policy_is_read_back_as_the_actor_it_was(tmp_path: Path):
    from cgail_learning.export import actor_state_from_onnx

    actor = _actor(41, 3)
    path = export_actor(actor, tmp_path / 'p.onnx', {'train_steps': 12345})
    state = actor_state_from_onnx(path)
    assert float(state['normalizer.count']) == 12345.0
    np.testing.assert_allclose(state['normalizer.mean'].numpy(), actor.normalizer.mean.numpy(),
                               rtol=1e-6)
    np.testing.assert_allclose(state['normalizer.var'].numpy(), actor.normalizer.var.numpy(),
                               rtol=1e-5)
    trainer = _trainer()
    trainer.load_weights(path)
    obs = np.random.default_rng(2).normal(2.0, 4.0, (64, 41)).astype(np.float32)
    np.testing.assert_allclose(trainer.act_deterministic(obs), OnnxPolicy(path)(obs), atol=1e-5)
    # log_std is not exported: the preset's initial value stays
    assert torch.allclose(trainer.actor.log_std, torch.full((3,), -1.5))


@pytest.mark.parametrize('case', ['shape', 'normaliser', 'not onnx', 'not an actor'])
def test_an_export_that_does_not_fit_the_preset_is_a_one_line_error(tmp_path: Path, case):
    path = export_actor(_actor(41, 3), tmp_path / 'p.onnx', {})
    trainer, match = _trainer(), ''
    if case == 'shape':
        trainer, match = _trainer(hidden=16), r'network shapes differ .*expected 2 x 16 units'
    elif case == 'normaliser':
        trainer, match = _trainer(normalize=False), 'expected a policy without an observation'
    elif case == 'not onnx':
        path.write_bytes(b'not a model')
        match = 'not a readable ONNX model'
    else:
        import onnx

        model = onnx.load(str(path))
        for t in model.graph.initializer:
            t.name = t.name.replace('actor.', 'net.')
        for n in model.graph.node:
            n.input[:] = [i.replace('actor.', 'net.') for i in n.input]
        onnx.save(model, str(path))
        match = 'expected the actor initializers of cgail export-onnx'
    with pytest.raises(PolicyLoadError, match=match) as info:
        trainer.load_weights(path)
    assert '\n' not in str(info.value)


def test_the_committed_policy_fine_tunes_from_where_it_stands():
    """The committed default policy, read back into a cgail trainer, acts as the ONNX does."""
    from cgail_learning.config import load_config
    from cgail_learning.trainer import Trainer
    from cgail_patient.plan import committed_policy
    from cgail_sim.config import EnvConfig
    from cgail_sim.vec_env import CatheterNavVecEnv

    env = CatheterNavVecEnv(EnvConfig(), 2)
    demo = np.zeros((4, 41), np.float32), np.zeros((4, 3), np.float32)
    trainer = Trainer(load_config('cgail'), env, demo_obs=demo[0], demo_act=demo[1],
                      demo_episodes=1)
    trainer.load_weights(committed_policy())
    obs = env.reset(seed=1)
    for _ in range(30):
        obs, *_ = env.step(np.tile(np.float32([0.2, -0.1, 1.0]), (2, 1)))
    np.testing.assert_allclose(trainer.act_deterministic(obs),
                               OnnxPolicy(committed_policy())(obs), atol=1e-5)

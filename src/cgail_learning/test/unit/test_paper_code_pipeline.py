"""``paper_code`` end to end at smoke scale: make_demos, train, export, evaluate, the planner.

One module fixture records 2 expert demonstrations in the paper_code option set and trains a
tiny paper_code C-GAIL run on them (512 steps, seconds); the tests export it and run it through
``evaluate`` and the planner. The authors' presets are checked against ``docs/fidelity.md``
and built into a trainer (no training: their buffers are 10,240 steps).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
import sys

import numpy as np
import onnx
import pytest
import torch
import yaml

from cgail_learning import evaluate, export, train
from cgail_learning.config import load_config
from cgail_planner.core.onnx_policy import OnnxPolicy
from cgail_sim.ftl_model import CONTRACT_KEY

sys.path.insert(0, str(Path(__file__).parent))
from tiny_pipeline import demos_and_training

TINY = {
    'name': 'paper_code_tiny', 'env_options': 'paper_code', 'max_steps': 512, 'num_envs': 2,
    'network': {'hidden_units': 16, 'num_layers': 5},
    'ppo': {'batch_size': 128, 'buffer_size': 256, 'learning_rate': 5.0e-4, 'epsilon': 0.25},
    'extrinsic': {'strength': 0.3}, 'gail': {'strength': 0.7, 'hidden_units': 16},
    'bc': {'strength': 0.5, 'batch_size': 128, 'num_epoch': 1, 'steps': 512},
    'normalize': False, 'eval_every': 256, 'eval_episodes': 1, 'checkpoint_every': 0,
}


@pytest.fixture(scope='module')
def run(tmp_path_factory) -> Path:
    """make_demos (2 episodes) and train (512 steps), both in paper_code; the run directory."""
    return demos_and_training(tmp_path_factory.mktemp('paper_code'),
                              ['--episodes', '2', '--env-options', 'paper_code'], TINY)


def test_make_demos_records_the_option_set(run) -> None:
    from cgail_learning.demo_bags import read_demo_bag, replay_demo_bag

    meta, episodes = read_demo_bag(run / 'demos')
    assert meta['env_options'] == 'paper_code' and len(episodes) == 2
    assert all((e.delta_l > 0).all() for e in episodes)  # forward only
    for options, dim in (('paper_code', 27), ('ours', 41)):  # replays in either
        replay = replay_demo_bag(run / 'demos', env_options=options)
        assert replay.obs.shape[1] == dim and replay.report.max_drift_m < 1e-6


def test_train_writes_the_paper_code_contract(run) -> None:
    cfg = yaml.safe_load((run / 'run' / 'config.yaml').read_text())
    assert cfg['env_options'] == 'paper_code'
    ckpt = torch.load(run / 'run' / 'final.pt', weights_only=False)
    contract = ckpt['metadata'][CONTRACT_KEY]
    assert contract['env_options'] == 'paper_code'
    assert contract['observation']['kind'] == 'paper_code'
    assert contract['observation']['dim'] == 27 and contract['catheter']['forward_only']


@pytest.fixture(scope='module')
def policy_path(run) -> Path:
    out = run / 'policy.onnx'
    assert export.main([str(run / 'run' / 'final.pt'), '--out', str(out)]) == 0
    return out


def test_export_carries_the_contract_to_the_policy(policy_path) -> None:
    meta = {p.key: json.loads(p.value) for p in onnx.load(str(policy_path)).metadata_props}
    assert meta['obs_dim'] == 27
    policy = OnnxPolicy(policy_path)
    assert policy.obs_dim == 27 and policy.contract.env_options == 'paper_code'
    assert policy.contract.observation.kind == 'paper_code'
    assert policy.contract.catheter.forward_only


def test_evaluate_runs_the_policy_in_its_option_set(policy_path, tmp_path) -> None:
    assert evaluate.main(['--policy', f'PC={policy_path}', '--baselines', 'centerline',
                          '--trials', '2', '--out', str(tmp_path)]) == 0
    report = (tmp_path / 'report.md').read_text()
    assert 'env options `paper_code`' in report and 'PC' in report


def test_evaluate_refuses_policies_of_two_option_sets(policy_path, tmp_path, capsys) -> None:
    ours = (Path(__file__).resolve().parents[3] / 'cgail_planner' / 'cgail_planner' / 'models'
            / 'cgail_default_static.onnx')
    assert evaluate.main(['--policy', f'PC={policy_path}', '--policy', f'C={ours}',
                          '--baselines', '--trials', '1', '--out', str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and 'expected one env option set' in err


def test_the_planner_runs_the_policy_with_its_observation(policy_path) -> None:
    from cgail_planner.core.errors import NoPathError
    from cgail_planner.core.planner import Planner, PlannerConfig
    from cgail_sim.wall import StaticWall
    from cgail_sim.worlds import load_world

    policy = OnnxPolicy(policy_path)
    world = load_world(policy.contract.anatomy)
    planner = Planner.from_contract(policy.contract, world, StaticWall(world.anatomy), policy,
                                    PlannerConfig(max_rollout_steps=150))
    assert planner.uses_kernel and planner.obs_dim == 27
    start, goal = world.scenarios.starts[0], world.scenarios.targets[0].position
    ends = []
    for roll in (planner.rollout, planner.rollout_reference):
        try:
            points, steps = roll(start.position, start.rotation, goal)
            ends.append(('reached', steps, points[:-1]))
        except NoPathError as exc:
            ends.append((exc.reason, exc.step, exc.points))
    (ka, sa, pa), (kb, sb, pb) = ends
    assert (ka, sa) == (kb, sb) and sa > 0
    np.testing.assert_allclose(pa, pb, rtol=0, atol=1e-9)


def test_the_planner_rolls_out_with_the_training_envs_exit_rule(policy_path) -> None:
    """A paper_code policy's rollouts end where its training episodes did: only out of the
    authors' exit box, through no open-end disc (AUTHORS_SCENE.md, "Exit"); a policy of our
    option set keeps the discs and the grown bounding box. The RRT baseline that evaluate runs
    in an env plans with that env's rule."""
    from cgail_planner.core.planner import exit_rule_of, Planner, PlannerConfig
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv
    from cgail_sim.scenarios import episode_bounds, paper_code_exit_box
    from cgail_sim.wall import StaticWall
    from cgail_sim.worlds import load_world

    policy = OnnxPolicy(policy_path)
    assert exit_rule_of(policy.contract) == 'box'
    world = load_world(policy.contract.anatomy)
    planner = Planner.from_contract(policy.contract, world, StaticWall(world.anatomy), policy,
                                    PlannerConfig(max_rollout_steps=150))
    low, high = paper_code_exit_box(world.scenarios.waypoints)
    assert planner.world.exit_discs.shape == (0, 7)
    np.testing.assert_array_equal(planner.world.bbox_low, low)
    np.testing.assert_array_equal(planner.world.bbox_high, high)
    ours = dataclasses.replace(policy.contract, env_options='ours')
    assert exit_rule_of(ours) == 'discs'
    model = Planner.from_contract(ours, world, StaticWall(world.anatomy), policy).world
    np.testing.assert_array_equal(model.exit_discs, world.anatomy.exit_discs)
    np.testing.assert_array_equal(model.bbox_low, episode_bounds(world.anatomy)[0])
    for options, discs in (('paper_code', 0), ('ours', world.anatomy.exit_discs.shape[0])):
        env = CatheterNavEnv(EnvConfig.from_options(options))
        rrt = evaluate.RrtFollower(env)
        assert rrt._model.exit_discs.shape[0] == discs
        np.testing.assert_array_equal(rrt._model.bbox_high, env.engine.bbox_high)


@pytest.mark.parametrize(('name', 'layers', 'units', 'steps', 'signals', 'bc'), [
    ('paper_code_cgail', 5, 128, 8_000_000, {'extrinsic': 0.3, 'gail': 0.7}, 0.5),
    ('paper_code_gail', 4, 64, 5_000_000, {'gail': 1.0}, 0.0),
    ('paper_code_ppo', 5, 128, 8_000_000, {'extrinsic': 1.0}, 0.0),
    ('paper_code_lambda0', 5, 128, 8_000_000, {'extrinsic': 0.3}, 0.5),
    ('paper_code_mu0', 5, 128, 8_000_000, {'extrinsic': 0.3, 'gail': 0.7}, 0.0),
])
def test_the_authors_presets(name, layers, units, steps, signals, bc) -> None:
    """The presets hold the authors' runs' numbers (docs/fidelity.md) and build a trainer in
    the paper_code env (27 observations)."""
    from cgail_learning.trainer import Trainer

    cfg = load_config(name)
    assert cfg.env_options == 'paper_code' and cfg.normalize is False
    assert (cfg.network.num_layers, cfg.network.hidden_units, cfg.max_steps) == (
        layers, units, steps)
    assert (cfg.ppo.learning_rate, cfg.ppo.epsilon) == (5e-4, 0.25)
    assert {k: s.strength for k, s in cfg.signals().items()} == signals
    assert cfg.bc.strength == bc and (bc == 0.0 or cfg.bc.steps == 8_000_000)
    assert bc == 0.0 or cfg.bc.schedule == 'ml-agents'  # decayed once, whole demo buffer
    env, _, meta = train.make_envs('static', 'default', 2, cfg.env_options)
    demo = (np.zeros((4, 27), np.float32), np.zeros((4, 3), np.float32)) \
        if cfg.needs_demos else (None, None)
    trainer = Trainer(cfg, env, demo_obs=demo[0], demo_act=demo[1], seed=0, metadata=meta,
                      demo_episodes=1 if cfg.needs_demos else None)
    assert trainer.obs_dim == 27
    assert trainer.act_deterministic(env.reset(seed=0)).shape == (2, 3)

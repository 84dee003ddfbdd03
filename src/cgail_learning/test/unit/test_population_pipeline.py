"""Training across the population end to end at smoke scale: make_demos --population, train on
population training anatomies with drawn targets (and resume), export, evaluate on held-out
anatomies.

Tiny (512 steps, 2 training anatomies): it checks the plumbing, not that the policy learns.
"""

from __future__ import annotations

import json
from pathlib import Path
import sys

import pytest
import torch

from cgail_learning import evaluate, export, train
from cgail_learning.demo_bags import read_demo_bag
from cgail_sim.ftl_model import CONTRACT_KEY

sys.path.insert(0, str(Path(__file__).parent))
from tiny_pipeline import demos_and_training

pytestmark = pytest.mark.slow

TINY = {
    'name': 'generalist_tiny', 'env_options': 'sphere_targets', 'max_steps': 512,
    'num_envs': 2, 'network': {'hidden_units': 16},
    'ppo': {'batch_size': 128, 'buffer_size': 256},
    'extrinsic': {'strength': 0.06}, 'gail': {'strength': 0.8, 'hidden_units': 16},
    'bc': {'strength': 0.14, 'batch_size': 128, 'num_epoch': 1},
    'eval_every': 256, 'eval_episodes': 2, 'checkpoint_every': 256,
    'population': {'anatomies': 2, 'redraw_every': 1, 'eval_anatomies': 1,
                   'include': ['elongated']},
}


@pytest.fixture(scope='module')
def run(tmp_path_factory) -> Path:
    """make_demos --population 2 --include elongated (3 episodes) and a 512-step population
    training run."""
    return demos_and_training(tmp_path_factory.mktemp('population'),
                              ['--population', '2', '--include', 'elongated', '--episodes', '3'],
                              TINY,
                              ['--threads', '1'])


def test_the_demos_run_in_the_population_training_anatomies(run) -> None:
    meta, episodes = read_demo_bag(run / 'demos')
    assert meta['population'] and [e.anatomy for e in episodes] == [
        'population-0', 'population-1', 'elongated']


def test_train_records_the_population_and_resumes(run) -> None:
    ckpt = torch.load(run / 'run' / 'final.pt', weights_only=False)
    meta = ckpt['metadata']
    assert meta['population'] == {'train_seeds': [0, 2], 'eval_seeds': [2, 3],
                                  'redraw_every': 1, 'include': ['elongated']}
    contract = meta[CONTRACT_KEY]
    assert contract['env_options'] == 'sphere_targets' and contract['anatomy'] == 'population-2'
    assert contract['anatomies'] == 'population'
    assert ckpt['step'] >= 512
    assert train.main(['--resume', str(run / 'run'), '--demos', str(run / 'demos'),
                       '--max-steps', '768', '--no-progress']) == 0
    assert torch.load(run / 'run' / 'final.pt', weights_only=False)['step'] >= 768


def test_evaluate_runs_on_held_out_anatomies(run) -> None:
    policy = run / 'policy.onnx'
    assert export.main([str(run / 'run' / 'final.pt'), '--out', str(policy)]) == 0
    out = run / 'eval'
    assert evaluate.main(['--policy', f'G={policy}', '--baselines', 'centerline',
                          '--population', '2', '--trials', '2', '--out', str(out)]) == 0
    data = json.loads((out / 'results.json').read_text())
    assert data['population_seeds'] == ['population-10000', 'population-10001']
    assert data['env_options'] == 'sphere_targets'
    static = data['modes']['static']
    assert [len(static[m]['trials']) for m in ('G', 'centerline')] == [4, 4]
    assert set(data['per_anatomy_success']['static']['G']) == {'population-10000',
                                                                'population-10001'}
    report = (out / 'report.md').read_text()
    assert '2 held-out population anatomies' in report and '| population-10001 |' in report
    assert '| **all** [95% CI over anatomies] |' in report
    assert '![success per anatomy, static](per_anatomy_static.png)' in report
    assert (out / 'per_anatomy_static.png').stat().st_size > 5000
    assert set(data['success_ci_over_anatomies']['static']) == {'G', 'centerline'}


def test_the_planner_runs_the_generalist_in_another_anatomy(run) -> None:
    """The exported contract says population: the planner takes it in `default` (not its
    selection anatomy) without an override, in default's frame, and plans."""
    from cgail_planner.core.errors import NoPathError
    from cgail_planner.core.onnx_policy import OnnxPolicy
    from cgail_planner.core.planner import Planner, reconcile_contract, world_observation_spec
    from cgail_sim.wall import StaticWall
    from cgail_sim.worlds import load_world

    policy_path = run / 'policy_for_planner.onnx'
    assert export.main([str(run / 'run' / 'final.pt'), '--out', str(policy_path)]) == 0
    policy = OnnxPolicy(policy_path)
    assert policy.contract is not None and policy.contract.anatomies == 'population'
    world = load_world('default')
    spec = world_observation_spec(world.scenarios, policy.contract)
    contract, notes = reconcile_contract(policy.contract, anatomy='default', mode='static',
                                         theta_max=None, segment_length=None, override=False,
                                         world_spec=spec)
    assert notes[0].startswith('population policy') and contract.observation.same_as(spec)
    planner = Planner.from_contract(contract, world, StaticWall(world.anatomy), policy)
    assert planner.spec.same_as(spec)
    start = world.scenarios.starts[0]
    # a 512-step policy rarely reaches the goal: the rollout runs it to the end either way
    try:
        result = planner.plan(start.position, start.rotation,
                              world.scenarios.targets[0].position)
        assert len(result.path) >= 2
    except NoPathError as exc:
        assert 'cgail rollout did not reach the goal within' in str(exc)


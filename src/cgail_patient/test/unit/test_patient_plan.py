"""plan_patient: bad input is one line and exit 2; a run writes a planner, its evaluation on
unseen targets, a report and the rig commands (slow: a one-minute budget end to end)."""

from __future__ import annotations

import pytest

from cgail_patient.plan import main, PlanOptions, rig_commands


def test_a_bad_anatomy_is_one_line_and_exit_status_2(bad_anatomy, tmp_path, capsys) -> None:
    spec, text = bad_anatomy
    assert main([str(spec), '--out', str(tmp_path / 'run'), '--no-progress']) == 2
    err = capsys.readouterr().err
    assert err.startswith('cgail plan-patient: error: ') and err.count('\n') == 1, err
    assert text in err, err
    assert not (tmp_path / 'run').exists()


@pytest.mark.parametrize('args, text', [
    (['--budget-min', '0.5'], 'budget_min must be in [1, 1440] minutes, found 0.5'),
    (['--goal-static', '1.5'], 'goal_static must be in (0, 1], found 1.5'),
    (['--test-seeds', '3'], 'test_seeds must be target sets apart from the training ones'),
    (['--validation-seeds', '1'], 'test_seeds must be target sets apart from validation_seeds'),
    (['--train-seeds', '-1'], 'train_seeds must be one or more ints >= 0'),
    (['--trials', '0'], 'trials must be in [1, 1000], found 0'),
    (['--bc-epochs', '-1'], 'bc_epochs must be an int in [0, 1000], found -1'),
    (['--jobs', '-1'], 'jobs must be an int in [0, 256] (0: one per CPU core), found -1'),
    (['--base', 'nowhere.onnx'], 'expected an exported .onnx policy or a train checkpoint, or '
                                 '"scratch", found no file at nowhere.onnx'),
    (['--preset', 'nopreset'], "expected a preset name in"),
])
def test_bad_options_are_one_line_and_exit_status_2(prepared, tmp_path, capsys, args,
                                                     text) -> None:
    out = tmp_path / 'run'
    assert main([str(prepared), '--out', str(out), '--no-progress', *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith('cgail plan-patient: error: ') and err.count('\n') == 1, err
    assert text in err, err
    assert not (out / 'plan.yaml').exists()


def test_an_earlier_run_is_never_overwritten(prepared, tmp_path, capsys) -> None:
    out = tmp_path / 'run'
    out.mkdir()
    (out / 'plan.yaml').write_text('goals_met: true\n')
    assert main([str(prepared), '--out', str(out), '--no-progress']) == 2
    assert 'expected a new run directory, found an earlier run' in capsys.readouterr().err
    assert (out / 'plan.yaml').read_text() == 'goals_met: true\n'


def test_the_rig_commands_name_the_anatomy_and_the_policies(tmp_path) -> None:
    pol = {'static': tmp_path / 's.onnx', 'dynamic': tmp_path / 'd.onnx'}
    lines = rig_commands('/p/anat', pol)
    assert any(line.startswith('scripts/ws cgail session --anatomy '
                               f'/p/anat --policy {pol["static"]} --mode static')
               and '--gui' in line
               for line in lines)
    assert any(f'--policy {pol["dynamic"]} --mode dynamic' in line for line in lines)
    assert any(line.startswith('scripts/ws cgail launch ') and 'anatomy:=/p/anat' in line
               and f'policy_path:={pol["static"]}' in line for line in lines)
    assert any('planner_node' in line and '-p anatomy:=/p/anat' in line for line in lines)


def test_options_default_to_disjoint_target_sets() -> None:
    o = PlanOptions()
    assert not set(o.test_seeds) & (set(o.train_seeds) | set(o.demo_seeds)
                                    | set(o.validation_seeds))
    assert 0 in o.demo_seeds  # the rig's own targets are demonstrated


@pytest.mark.slow
def test_a_one_minute_run_end_to_end(prepared, tmp_path, capsys) -> None:
    """The whole pipeline on a prepared anatomy with a one-minute budget and small target sets:
    demo bags, a policy per mode whose contract names the anatomy by its content hash, the
    evaluation on the unseen set with the centerline follower and the base policy beside it,
    the report with its plot and rig commands. The exit status says whether the goals were met
    (a minute is not meant to meet them; the status must agree with the record)."""
    import yaml

    from cgail_learning.demo_bags import read_demo_bag
    from cgail_planner.core.onnx_policy import OnnxPolicy
    from cgail_sim.anatomy_spec import resolve_anatomy

    out = tmp_path / 'run'
    status = main([str(prepared), '--out', str(out), '--budget-min', '1', '--trials', '2',
                   '--demo-seeds', '0', '--train-seeds', '3', '4', '--validation-seeds', '20',
                   '--test-seeds', '1', '--no-progress'])
    err = capsys.readouterr().err
    assert status in (0, 1), err
    rec = yaml.safe_load((out / 'plan.yaml').read_text())
    assert (status == 0) == rec['goals_met']
    assert 'goals met' in err if status == 0 else 'goals NOT met' in err
    content_hash = resolve_anatomy(str(prepared)).content_hash
    assert rec['anatomy_hash'] == content_hash
    meta, episodes = read_demo_bag(out / 'demos' / 'seed_0')
    assert len(episodes) == 15 and meta['anatomy_hash'] == content_hash
    for mode in ('static', 'dynamic'):
        policy = OnnxPolicy(out / f'policy_{mode}.onnx')
        assert policy.contract is not None and policy.contract.anatomy_hash == content_hash
        rates = rec['success_unseen_targets'][mode]
        assert set(rates) >= {'C-GAIL (this run)', 'centerline'}
        assert all(0.0 <= r <= 1.0 for r in rates.values())
    assert 'C-GAIL (base, not tuned)' in rec['success_unseen_targets']['static']
    # fine-tuning runs at the contract's theta_max: no curriculum (preset cgail has one)
    config = yaml.safe_load((out / 'train' / 'static' / 'config.yaml').read_text())
    assert config['curriculum']['theta_max_deg'] == [] and config['name'] == 'cgail'
    assert rec['validation_history'] and rec['timings_s']['total'] > 0
    # the warm start is validated first, before any C-GAIL step
    first = rec['validation_history'][0]
    assert first['warm_start'] and first['steps'] == 0 and first['phase'] == 'static'
    assert '| static (BC warm start) | ' in (out / 'report.md').read_text()
    report = (out / 'report.md').read_text()
    assert f'scripts/ws cgail session --anatomy {prepared.resolve()}' in report
    assert '| static |' in report and '![validation during training](training.png)' in report
    for png in ('training.png', 'evaluation/static_T_a.png', 'evaluation/dynamic_T_s.png'):
        assert (out / png).stat().st_size > 5000, png
    assert (out / 'evaluation' / 'report.md').is_file()


def test_demonstrations_do_not_depend_on_the_number_of_processes(prepared, tmp_path) -> None:
    """Two target sets in one process and in two (spawned workers): the same bags, the same
    (obs, act) pairs in the order of the sets."""
    import numpy as np

    from cgail_learning.demo_bags import read_demo_bag
    from cgail_patient.plan import _record_demos

    runs = {}
    for jobs in (1, 2):
        lines: list[str] = []
        out = tmp_path / f'jobs{jobs}'
        runs[jobs] = _record_demos(str(prepared), PlanOptions(jobs=jobs), out, lines.append,
                                   seeds=(0, 3))
        assert sorted(line.split(':')[0] for line in lines) == [
            'expert, static, target set 0', 'expert, static, target set 3']
        for s in (0, 3):
            meta, episodes = read_demo_bag(out / 'demos' / f'seed_{s}')
            assert meta['scenario_seed'] == s and len(episodes) == 15
    (o1, a1, n1), s1 = runs[1]
    (o2, a2, n2), s2 = runs[2]
    assert n1 == n2 and s1 == s2 and n1 >= 20
    assert np.array_equal(o1, o2) and np.array_equal(a1, a2)


@pytest.mark.slow
def test_dynamic_demonstrations_are_recorded_in_the_beating_aorta(prepared, tmp_path) -> None:
    """The dynamic phase's own demonstrations: one bag per set, in the beating aorta."""
    from cgail_learning.demo_bags import read_demo_bag
    from cgail_patient.plan import _record_demos

    lines: list[str] = []
    (obs, act, n_episodes), stats = _record_demos(str(prepared), PlanOptions(), tmp_path,
                                                  lines.append, mode='dynamic', seeds=(3,))
    meta, episodes = read_demo_bag(tmp_path / 'demos' / 'dynamic_seed_3')
    assert meta['mode'] == 'dynamic' and meta['scenario_seed'] == 3 and len(episodes) == 15
    assert stats['episodes'] == 15 and stats['expert_success'] >= 0.8
    assert n_episodes == round(15 * stats['expert_success'])  # the successful ones
    assert len(obs) == len(act) > 1000 and obs.shape[1] == 41
    assert lines == [f'expert, dynamic, target set 3: 15 episodes, success '
                     f'{100 * stats["expert_success"]:.0f}%']


def test_the_dynamic_phase_never_exports_worse_than_the_static_policy(prepared, tmp_path):
    """With no time left to train, the dynamic phase returns the static incumbent as it was
    validated, rather than an unvalidated or worse checkpoint."""
    import numpy as np

    from cgail_learning.demos import Demos
    from cgail_patient.plan import _Clock, _train_phase, PlanResult

    incumbent = tmp_path / 'static_best.pt'
    demos = Demos(np.zeros((4, 41), np.float32), np.zeros((4, 3), np.float32), 1)
    lines: list[str] = []
    best, s_rate, d_rate = _train_phase(
        'dynamic', str(prepared), PlanOptions(train_seeds=(3,)), tmp_path, _Clock(0.0), demos,
        '', PlanResult(out=tmp_path), lines.append, False, warm_start=False,
        incumbent=(incumbent, 0.97, 0.77))
    assert (best, s_rate, d_rate) == (incumbent, 0.97, 0.77)
    assert lines == ['training (dynamic): 0 steps, best validation (static, dynamic) 97% / 77%']


@pytest.mark.slow
def test_a_dagger_round_follows_a_warm_start_under_the_goal(prepared, tmp_path) -> None:
    """A warm start validated under the static goal plus 5 points is followed by a DAgger
    round: validated like any checkpoint, logged, named in the report's table."""
    from cgail_patient.plan import (
        _Clock,
        _record_demos,
        _row_label,
        _train_phase,
        PlanResult,
    )

    options = PlanOptions(train_seeds=(3,), demo_seeds=(3,), validation_seeds=(20,),
                          test_seeds=(1,), goal_static=1.0, bc_epochs=3)
    lines: list[str] = []
    demos, _ = _record_demos(str(prepared), options, tmp_path, lines.append)
    result = PlanResult(out=tmp_path)
    _train_phase('static', str(prepared), options, tmp_path, _Clock(50.0), demos, '', result,
                 lines.append, False)
    first, second = result.history[:2]
    assert first['warm_start'] and not first.get('dagger')
    assert second['dagger'] == 1 and second['steps'] == 0 and second['phase'] == 'static'
    assert _row_label(second) == 'static (DAgger round 1)'
    assert any(line.startswith('DAgger round 1: the policy reached ') and
               '% of 15 training episodes; ' in line for line in lines), lines
    assert result.timings_s['dagger'] > 0

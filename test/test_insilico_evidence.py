"""bench/insilico_evidence.py on a fake fresh-budget study: the training and failure tables, the
static policies evaluated in the beating aorta (a stand-in evaluator), skipping what is done,
and its one-line errors."""

from __future__ import annotations

import json
from pathlib import Path
import subprocess

from bench_modules import bench_module
import pytest

study = bench_module('insilico_study')
evidence = bench_module('insilico_evidence')


def write_results(folder: Path, name: str, mode: str, outcomes: str) -> None:
    """``outcomes``: one letter a trial, s success, c collision, t the step limit."""
    folder.mkdir(parents=True, exist_ok=True)
    trials = [{'success': o == 's', 'collision': o == 'c', 'timesteps': 400,
               'targeting_error_mm': 6.0} for o in outcomes]
    (folder / 'results.json').write_text(json.dumps(
        {'trials': len(trials), 'modes': {mode: {name: {'summary': {}, 'trials': trials}}}}))


@pytest.fixture
def fake(tmp_path):
    """C-GAIL (two seeds) that succeeds, GAIL (one seed) that never reached a target."""
    layout = study.Layout(tmp_path / 'study', fresh=True)
    results = {('cgail', 0): ('sscsss', 'ssssss'), ('cgail', 1): ('ccssss', 'sssssc'),
               ('gail', 0): ('cccccc', 'cctccc')}
    for (m, s), (static, dynamic) in results.items():
        n = 2048
        folder = layout.budget(m, s, n)
        (folder / 'static').mkdir(parents=True)
        rows = [(1024, 'eval/success_rate', 0.5), (2048, 'eval/success_rate', 0.25),
                (1024, 'environment/success_rate', 0.3 if m == 'cgail' else 0.0),
                (2048, 'environment/success_rate', 0.1 if m == 'cgail' else 0.0),
                (2048, 'environment/episode_length', 312.4),
                (2048, 'environment/episode_reward', -0.8)]
        (folder / 'static' / 'scalars.csv').write_text(
            'step,tag,value\n' + ''.join(f'{a},{b},{c}\n' for a, b, c in rows))
        layout.snapshot(m, s, n).write_text(json.dumps({'step': n}))
        (folder / 'static.onnx').write_bytes(f'{m}{s}'.encode())
        write_results(layout.evaluation(m, s, n, 'static', 0), m, 'static', static)
        write_results(layout.evaluation(m, s, n, 'dynamic', 0), m, 'dynamic', dynamic)
    return layout


def test_the_tables_from_the_runs(fake):
    runs = evidence.find_runs(fake.root)
    assert [r.name for r in runs] == ['cgail seed 0 2,048', 'cgail seed 1 2,048',
                                      'gail seed 0 2,048']
    assert evidence.training_row(runs[0]) == ['cgail', '0', '2,048', '50% at 1,024',
                                              '25% at 2,048', '30%', '312', '-0.80']
    assert evidence.training_row(runs[2])[5] == '0%'  # not one training episode at a target
    # failures per start: trial k starts at k % 3
    assert evidence.failure_row(runs[1], 'static') == ['cgail', '1', '2,048', 'static', '4/6',
                                                       '2', '0', '1 / 1 / 0']
    assert evidence.failure_row(runs[2], 'dynamic') == ['gail', '0', '2,048', 'dynamic', '0/6',
                                                        '5', '1', '2 / 2 / 2']
    text = evidence.build_evidence(fake.root, runs, 6)
    assert '| cgail | 0 | 2,048 | 83% | - | 100% |' in text  # the zero-shot not run yet
    assert 'evidence_static_in_dynamic.png' not in text


def test_static_policies_run_in_the_beating_aorta_once(fake, monkeypatch, capsys):
    calls = []

    def fake_evaluate(cmd, stdout, stderr, env, stdin):
        calls.append(cmd)
        out = Path(cmd[cmd.index('--out') + 1])
        assert cmd[cmd.index('--modes') + 1] == 'dynamic' and '--baselines' in cmd
        assert cmd[cmd.index('--scenario-seed') + 1] == '0'
        name = cmd[cmd.index('--policy') + 1].split('=')[0]
        write_results(out, name, 'dynamic', 'sssssc')
        return subprocess.CompletedProcess(cmd, 0)

    monkeypatch.setattr(evidence.subprocess, 'run', fake_evaluate)
    monkeypatch.setattr(evidence, 'heartbeat_motion', lambda options: evidence.Motion(
        options, 0.74, (0.5, 6.0), 5.5, 120, 2455))
    assert evidence.main(['--study', str(fake.root), '--trials', '6']) == 0
    # GAIL never succeeded in a static evaluation: not run
    assert [c[c.index('--policy') + 1].split('=')[0] for c in calls] == ['cgail', 'cgail']
    text = (fake.root / 'evidence.md').read_text()
    assert '| cgail | 1 | 2,048 | 67% | 83% | 83% |' in text
    assert '| gail | 0 | 2,048 | 0% | - | 0% |' in text
    assert (fake.root / 'evidence_static_in_dynamic.png').stat().st_size > 0
    assert '| `paper_code` | 0.74 s | 0.5, 6.0 | 5.5 | 120 of 2,455 |' in text
    calls.clear()
    assert evidence.main(['--study', str(fake.root), '--trials', '6']) == 0
    assert calls == []  # done for the current policies
    (fake.budget('cgail', 0, 2048) / 'static.onnx').write_bytes(b'another policy')
    assert evidence.main(['--study', str(fake.root), '--trials', '6']) == 0
    assert len(calls) == 1  # a new policy is evaluated again


def test_a_failed_evaluation_is_one_line(fake, monkeypatch, capsys):
    monkeypatch.setattr(evidence.subprocess, 'run',
                        lambda cmd, **kw: subprocess.CompletedProcess(cmd, 3))
    assert evidence.main(['--study', str(fake.root)]) == 2
    err = capsys.readouterr().err
    assert err.startswith('insilico_evidence: error: cgail seed 0 2,048: evaluate exited 3; '
                          'see ') and err.count('\n') == 1


@pytest.mark.parametrize('argv, message', [
    (['--trials', '0'], '--trials: expected >= 1, found 0'),
    (['--study', 'NOWHERE'], '--study: expected a study folder, found no folder'),
    (['--study', 'EMPTY'], '--study: expected runs of a study made with --fresh-budgets'),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, tmp_path, capsys):
    (tmp_path / 'EMPTY').mkdir()
    argv = [str(tmp_path / a) if a in ('NOWHERE', 'EMPTY') else a for a in argv]
    assert evidence.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'insilico_evidence: error: {message}') and err.count('\n') == 1


def test_the_heartbeat_motion_of_both_option_sets():
    """The measured motion (coarse bounds: the physics, not its last bits): the authors'
    one-sided axial push moves the wall near the root, ours moves the root and its targets."""
    theirs, ours = (evidence.heartbeat_motion(o, cycles=1.0) for o in ('paper_code', 'ours'))
    assert theirs.period == pytest.approx(0.74) and len(theirs.targets_mm) == 5
    assert 4.0 < theirs.wall_mm < 9.0 and max(theirs.targets_mm) < 2.0
    assert min(ours.targets_mm) > 3.0 and ours.moving > 2 * theirs.moving

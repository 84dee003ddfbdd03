"""The simulated in-vitro session (cgail_planner.system.session).

Fast: argument checks and the report stage on the committed trial bags. Slow (-m slow): the
whole rig in-process (phantom + simulated devices, aurora_node over the pty, pam_node,
driver_node, teleop_node, planner_node, operator_node) for one short trial per condition.
"""

from pathlib import Path
import shutil

import pytest

from cgail_planner.system.session import main, report

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / 'bags' / 'fixtures'


def test_cgail_condition_needs_a_policy(tmp_path, capsys) -> None:
    missing = tmp_path / 'missing.onnx'
    assert main(['--out', str(tmp_path), '--trials', '1', '--policy', str(missing)]) == 2
    assert f'needs --policy <model.onnx> (export_onnx), found no file at {missing}' \
        in capsys.readouterr().err


def test_default_policy_is_the_committed_cgail_model_of_the_anatomy_and_mode() -> None:
    from cgail_planner.system.session import build_parser, default_policy

    assert build_parser().parse_args([]).policy is None  # resolved from --anatomy and --mode
    for anatomy, mode, name in (('default', 'static', 'cgail_default_static.onnx'),
                                ('default', 'dynamic', 'cgail_default_dynamic.onnx'),
                                ('elongated', 'static', 'cgail_elongated_static.onnx'),
                                ('elongated', 'dynamic', 'cgail_elongated_static.onnx')):
        policy = default_policy(anatomy, mode)
        assert policy.name == name and policy.is_file()
    assert not default_policy('nonexistent', 'static').is_file()


def test_refuses_to_mix_with_existing_bags(tmp_path, capsys) -> None:
    (tmp_path / 'bags' / 'cgail').mkdir(parents=True)
    (tmp_path / 'bags' / 'cgail' / 'old').mkdir()
    assert main(['--out', str(tmp_path), '--conditions', 'centerline']) == 2
    assert 'already holds bags' in capsys.readouterr().err


def test_report_on_recorded_trials(tmp_path) -> None:
    bags = tmp_path / 'bags'
    for condition in ('cgail', 'centerline'):
        (bags / condition).mkdir(parents=True)
        shutil.copytree(FIXTURES / f'{condition}_trial', bags / condition / f'{condition}_01')
    lines: list[str] = []
    outcomes = [('cgail', 1, 'at the target (1.0 mm)'), ('centerline', 1, 'time limit')]
    assert report(tmp_path, bags, outcomes, lines.append, wall_s=1.0) == 0
    text = (tmp_path / 'metrics.md').read_text()
    assert '| 1 | cgail | at the target (1.0 mm) |' in text
    assert 'Side by side with the paper' in text and 'Kruskal-Wallis' in text
    assert (tmp_path / 'metrics.csv').is_file() and (tmp_path / 'metrics_boxplot.png').is_file()


def _assert_both_trials_reached(out: Path) -> None:
    """The session's report: no callback error, trial 1 of each condition reached its target
    within epsilon in time, with a tracking error under 10 mm."""
    text = (out / 'metrics.md').read_text()
    assert 'callback errors: 0.' in text
    rows = [line for line in text.splitlines()
            if line.startswith(('| cgail_01', '| centerline_01'))]
    assert len(rows) == 2, text
    for row in rows:
        cells = [c.strip() for c in row.strip('|').split('|')]
        assert cells[8] == 'yes', row                  # reached within epsilon in time
        assert float(cells[6]) < 10.0, row             # T_a (mm)


@pytest.mark.slow
def test_one_trial_per_condition_end_to_end(tmp_path) -> None:
    out = tmp_path / 'session'
    code = main(['--trials', '1', '--out', str(out), '--time-limit', '150'])
    assert code == 0
    _assert_both_trials_reached(out)
    assert (out / 'metrics_boxplot.png').is_file()
    assert sorted(p.name for p in (out / 'bags').iterdir()) == ['centerline', 'cgail']


@pytest.mark.slow
def test_one_trial_per_condition_in_a_prepared_anatomy(prepared_anatomy, tmp_path) -> None:
    """The session in a prepared directory with a policy contracted for it: every node
    resolves the same anatomy, the planner accepts the contract, both trials reach the
    target."""
    from cgail_planner.learning.export import default_contract, write_contract

    policy = write_contract(
        ROOT / 'src' / 'cgail_planner' / 'cgail_planner' / 'learning' / 'models'
        / 'cgail_default_static.onnx', default_contract(prepared_anatomy, 'static'),
        tmp_path / 'cgail_p07_static.onnx')
    out = tmp_path / 'session'
    assert main(['--trials', '1', '--out', str(out), '--time-limit', '150', '--anatomy',
                 str(prepared_anatomy), '--policy', str(policy), '--jobs', '1']) == 0
    _assert_both_trials_reached(out)

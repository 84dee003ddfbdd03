"""CI: play the committed fixture bags into live topics, record them back, check the metrics.

Each fixture's known values (``bags/fixtures/*/expected.json``) come from its analytic
construction in ``bags/fixtures/make_fixtures.py``, not from the metrics code. The player runs
as a subprocess (same ROS_DOMAIN_ID, localhost-only discovery from scripts/env.sh); this process
records the live topics with :class:`BagRecorder` and evaluates the recorded bag.
"""

import json
import os
from pathlib import Path
import shutil
import subprocess
import sys
import time

import pytest

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / 'bags' / 'fixtures'
TOPICS = ('em_tracker/tip_pose', 'planner/path', 'planner/goal')
RATE = 8.0


def run_module(module: str, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', module, *args], env=os.environ.copy(),
                          capture_output=True, text=True, timeout=timeout, check=False)


@pytest.mark.parametrize('fixture', ['cgail_trial', 'centerline_trial'])
def test_replayed_fixture_gives_the_known_metrics(rclpy_context, tmp_path: Path,
                                                  fixture: str) -> None:
    from rclpy.executors import SingleThreadedExecutor

    from cgail_bags.metrics_cli import evaluate_bags
    from cgail_bags.record import BagRecorder, RecorderConfig

    expected = json.loads((FIXTURES / fixture / 'expected.json').read_text())
    node = rclpy_context.create_node('playback_recorder')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    recorder = BagRecorder(node, RecorderConfig(output=tmp_path / fixture, topics=TOPICS,
                                                condition=expected['condition'],
                                                discovery_period=0.1))
    player = subprocess.Popen(
        [sys.executable, '-m', 'cgail_bags.play', str(FIXTURES / fixture),
         '--rate', str(RATE), '--wait-for-subscribers', '20', '--linger', '0.5'],
        env=os.environ.copy(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60.0
        while player.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
    finally:
        if player.poll() is None:
            player.kill()
    output = player.communicate()[0]
    assert player.returncode == 0, output
    assert f'published {expected["samples"] + 2} messages' in output
    recorder.stop()
    executor.shutdown()
    node.destroy_node()

    (m,) = evaluate_bags([tmp_path / fixture])
    assert m.condition == expected['condition']
    # Sensor QoS is best effort: allow a few lost tip poses, and tolerances that cover them.
    assert expected['samples'] * 0.95 <= m.samples <= expected['samples']
    mm = 1e-3
    assert m.tracking_mean == pytest.approx(expected['tracking_mean_m'], abs=0.05 * mm)
    assert m.tracking_std == pytest.approx(expected['tracking_std_m'], abs=0.05 * mm)
    assert m.tracking_max == pytest.approx(expected['tracking_max_m'], abs=0.02 * mm)
    assert m.targeting_error == pytest.approx(expected['targeting_error_m'], abs=0.3 * mm)
    assert m.duration == pytest.approx(expected['duration_s'], abs=0.1)
    assert m.success is expected['success']
    assert m.time_to_target == pytest.approx(expected['time_to_target_s'], abs=0.1)
    assert m.curvature_mean * 1e-3 == pytest.approx(expected['curvature_mean_per_mm'], rel=0.01)
    assert m.curvature_std * 1e-3 < 0.02 * expected['curvature_mean_per_mm']


def test_committed_fixtures_give_the_known_metrics_exactly(tmp_path: Path, capsys) -> None:
    from cgail_bags.metrics_cli import evaluate_bags, main

    assert main([str(FIXTURES), '-o', str(tmp_path)]) == 0
    assert '| cgail_trial | cgail | 401 | 2.62 |' in capsys.readouterr().out

    for m in evaluate_bags([FIXTURES]):
        expected = json.loads((FIXTURES / m.name / 'expected.json').read_text())
        assert m.condition == expected['condition']
        assert m.samples == expected['samples']
        assert m.tracking_mean == pytest.approx(expected['tracking_mean_m'], abs=1e-6)
        assert m.tracking_std == pytest.approx(expected['tracking_std_m'], abs=1e-6)
        assert m.tracking_max == pytest.approx(expected['tracking_max_m'], abs=1e-6)
        assert m.targeting_error == pytest.approx(expected['targeting_error_m'], abs=1e-9)
        assert m.duration == pytest.approx(expected['duration_s'], abs=1e-6)
        assert m.time_to_target == pytest.approx(expected['time_to_target_s'], abs=1e-6)
        assert m.curvature_mean * 1e-3 == pytest.approx(expected['curvature_mean_per_mm'],
                                                        rel=1e-3)
    # Two single-trial conditions with distinct values: H = 1, p = erfc(1/sqrt(2)) = 0.3173.
    report = (tmp_path / 'metrics.md').read_text()
    assert '| tracking error T_r | 1.000 | 0.3173 | no |' in report
    assert '| cgail | 1 | 100% | 2.62 | 1.50 | 10.0 |' in report
    # ours: T_r (5.2335 - 2.6169) / 5.2335 = 50 %, T_a (3 - 1.5) / 3 = 50 % better
    assert '| targeting error T_a | 1.26 ± 0.55 | 41% | 1.50 | 3.00 | 50% |' in report
    assert (tmp_path / 'metrics.csv').read_text().count('\n') == 3
    assert (tmp_path / 'metrics_boxplot.png').read_bytes()[:4] == b'\x89PNG'


def truncated_fixture(tmp_path: Path) -> Path:
    bag = tmp_path / 'truncated_trial'
    shutil.copytree(FIXTURES / 'cgail_trial', bag)
    mcap = bag / 'cgail_trial.mcap'
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size * 2 // 3])
    return bag


def test_truncated_fixture_gives_a_clear_player_error(tmp_path: Path) -> None:
    bag = truncated_fixture(tmp_path)
    result = run_module('cgail_bags.play', str(bag))
    assert result.returncode == 2
    assert 'Traceback' not in result.stderr
    assert f'cgail bag play: error: {bag}: truncated or corrupt bag' in result.stderr


def test_truncated_fixture_gives_a_clear_metrics_error(tmp_path: Path, capsys) -> None:
    from cgail_bags.metrics_cli import main

    bag = truncated_fixture(tmp_path)
    assert main([str(bag), '-o', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert f'cgail bag metrics: error: {bag}: truncated or corrupt bag' in err
    assert 'File end magic is invalid' in err


def test_fixtures_are_what_the_script_makes(tmp_path: Path) -> None:
    """The committed bags match make_fixtures.py (catches an edited script not rerun)."""
    sys.path.insert(0, str(FIXTURES))
    try:
        import make_fixtures
    finally:
        sys.path.remove(str(FIXTURES))
    from cgail_bags.bagio import iter_raw, open_bag

    assert make_fixtures.main(['--out', str(tmp_path)]) == 0
    for name in make_fixtures.TRIALS:
        made, committed = tmp_path / name, FIXTURES / name
        assert json.loads((made / 'expected.json').read_text()) == json.loads(
            (committed / 'expected.json').read_text())
        assert (made / 'README.md').read_text() == (committed / 'README.md').read_text()
        with open_bag(made) as a, open_bag(committed) as b:
            assert [(c.topic, t, bytes(r)) for c, t, r in iter_raw(a)] == [
                (c.topic, t, bytes(r)) for c, t, r in iter_raw(b)]

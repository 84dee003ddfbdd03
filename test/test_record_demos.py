"""``record_demos`` end to end, without a person: the scripted demonstrator at the gamepad.

The scripted driver publishes ``sensor_msgs/Joy`` on ``joy`` as ``joy_node`` would; teleop turns
it into the catheter commands the recorder maps onto the simulator. The bag must be a valid
demonstration bag (``load_demo_bag`` replays it) that ``train --preset smoke`` takes. Bad input
gives one line; a NaN Joy axis from another process is reported once and loses nothing.
"""

from __future__ import annotations

from collections.abc import Iterator
import json
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import time

import pytest

REPO = Path(__file__).resolve().parents[1]


def record_demos(*args: str) -> list[str]:
    """The command line of ``record_demos`` in this environment."""
    return [sys.executable, '-m', 'cgail_rig.record_demos', *args]


def start(args: list[str]) -> subprocess.Popen[str]:
    return subprocess.Popen(record_demos(*args), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=dict(os.environ))


def read_until(proc: subprocess.Popen[str], pattern: str, timeout: float) -> tuple[str, str]:
    """Lines of ``proc`` up to the first that matches ``pattern``: (all text, the match)."""
    assert proc.stdout is not None
    text = ''
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        text += line
        m = re.search(pattern, line)
        if m:
            return text, m.group(0)
    raise AssertionError(f'expected a line matching {pattern!r} within {timeout} s, found:\n'
                         f'{text}')


@pytest.fixture(scope='module')
def scripted_bag(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, str]]:
    out = tmp_path_factory.mktemp('record') / 'demos'
    run = subprocess.run(record_demos('--anatomy', 'default', '--out', str(out), '--driver',
                                      'scripted', '--episodes', '2', '--time-scale', '50',
                                      '--port', '0', '--pause', '0.5'),
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    yield out, run.stdout


def test_scripted_demonstrations_are_a_demo_bag_that_replays(scripted_bag) -> None:
    from cgail_learning.demo_bags import read_demo_bag, replay_demo_bag
    from cgail_learning.recorder import read_recording

    out, stdout = scripted_bag
    assert stdout.count('cgail record-demos: episode ') == 2
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary['saved'] == 2 and summary['rejected_inputs'] == {}
    meta, episodes = read_demo_bag(out)
    assert (meta['anatomy'], meta['mode']) == ('default', 'static')
    assert [(e.start, e.target) for e in episodes] == [(0, 0), (1, 0)]
    assert all(e.success for e in episodes) == (summary['successes'] == 2)
    recording = read_recording(out)
    assert recording is not None and recording['who'] == 'scripted expert'
    assert [e['device'] for e in recording['episodes']] == ['scripted', 'scripted']
    assert [e['steps'] for e in recording['episodes']] == [len(e.alpha) for e in episodes]
    replay = replay_demo_bag(out, only_successful=False)
    assert replay.report.max_drift_m < 1e-9 and replay.report.episodes == 2
    assert len(replay.obs) == sum(len(e.alpha) for e in episodes)
    # every recorded step moved the catheter, within the action space
    assert (abs(replay.act) <= 1.0).all() and (replay.act[:, 2] != 0.0).all()


@pytest.mark.slow
def test_train_smoke_accepts_the_recorded_bag(scripted_bag, tmp_path: Path) -> None:
    out, _ = scripted_bag
    run = subprocess.run([sys.executable, '-m', 'cgail_learning.train', '--preset',
                          'smoke', '--mode', 'static', '--demos', str(out), '--max-steps', '1024',
                          '--num-envs', '2', '--out', str(tmp_path / 'run'), '--no-progress'],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    assert 'cgail train: demonstrations:' in run.stdout + run.stderr
    assert (tmp_path / 'run' / 'final.pt').is_file()


@pytest.mark.parametrize(('args', 'message'), [
    (['--anatomy', 'nowhere'], 'nowhere'),
    (['--episodes', '0'], '--episodes: episodes must be an int in [1, 10000], found 0'),
    (['--time-scale', 'nan'], '--time-scale: expected a number in (0, 1000], found nan'),
    (['--time-limit', '-1'], '--time-limit: time_limit_s must be in (0, 3600] s, found -1.0'),
])
def test_bad_input_is_one_line(args: list[str], message: str, tmp_path: Path) -> None:
    run = subprocess.run(record_demos('--out', str(tmp_path / 'd'), *args),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('cgail record-demos: error: '), run.stderr
    assert message in lines[0]
    assert not (tmp_path / 'd').exists()


def test_an_existing_out_is_refused(tmp_path: Path) -> None:
    (tmp_path / 'd').mkdir()
    run = subprocess.run(record_demos('--out', str(tmp_path / 'd')), capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 2
    assert run.stderr.strip() == (f'cgail record-demos: error: --out {tmp_path / "d"}: expected '
                                  'a new bag directory, found it exists (choose another name '
                                  'or remove it)')


def test_a_nan_joy_axis_is_one_line_and_loses_nothing(rclpy_context, tmp_path: Path) -> None:
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Joy

    from cgail_learning.demo_bags import read_demo_bag

    out = tmp_path / 'demos'
    proc = start(['--out', str(out), '--driver', 'scripted', '--episodes', '3', '--time-scale',
                  '20', '--port', '0', '--pause', '0.5'])
    node = rclpy_context.create_node('nan_joy')
    try:
        pub = node.create_publisher(Joy, 'joy', qos_profile_sensor_data)
        text, _ = read_until(proc, r'episode 1/3: \w+', 240)
        bad = Joy(axes=[0.0, float('nan'), 0.0, 0.0, 0.0], buttons=[0, 0, 0, 0, 1])
        deadline = time.monotonic() + 30
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.05)  # discovery
        for _ in range(5):
            pub.publish(bad)
            time.sleep(0.05)
        more, _ = read_until(proc, r'episode 2/3: \w+', 240)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        node.destroy_node()
        if proc.poll() is None:
            proc.kill()
    lines = (text + more + rest).splitlines()
    nan_lines = [line for line in lines if 'found nan' in line]
    assert nan_lines == ['cgail record-demos: joy (gamepad): expected Joy axis 1 finite in '
                         '[-1, 1], found nan: teleop stopped the catheter (deadman released); '
                         'fix the device or its axes'], lines
    assert proc.returncode == 0, lines  # (the output says which node failed)
    summary = json.loads(lines[-1])
    assert summary['interrupted'] is True and summary['saved'] >= 2
    assert sum(summary['rejected_inputs'].values()) >= 1
    _, episodes = read_demo_bag(out)
    assert len(episodes) == summary['saved']

"""The launcher: spec validation, signal forwarding, escalation, required nodes, CLI guard."""

import io
import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest
import yaml

from cgail_planner.system.launch_spec import (
    LaunchSpecError,
    load_launch_file,
    parse_launch,
)
from cgail_planner.system.launcher import main, node_command, ProcessLauncher

# A child that records the signal it got, then exits 0 on SIGINT (like an rclpy node).
GOOD_CHILD = textwrap.dedent('''
    import signal, sys, time
    out = sys.argv[1]
    def on(sig, _):
        open(out, 'a').write(f'{signal.Signals(sig).name}\\n')
        sys.exit(0)
    signal.signal(signal.SIGINT, on)
    signal.signal(signal.SIGTERM, on)
    print('ready', flush=True)
    while True:
        time.sleep(0.05)
''')
# A child that ignores SIGINT: the launcher must escalate to SIGTERM.
STUBBORN_CHILD = GOOD_CHILD.replace('signal.signal(signal.SIGINT, on)',
                                    'signal.signal(signal.SIGINT, signal.SIG_IGN)')


def _spec(tmp_path, nodes):
    return parse_launch({'name': 't', 'nodes': nodes}, tmp_path)


def _wait_ready(out: io.StringIO, names, timeout=15.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        text = out.getvalue()
        if all(f'[{n}] ready' in text for n in names):
            return
        time.sleep(0.05)
    raise AssertionError(f'children not ready: {out.getvalue()!r}')


@pytest.mark.parametrize('nodes, match', [
    ([], 'at least one node'),
    ([{'name': 'a', 'package': 'p'}], 'expected package and executable'),
    ([{'name': 'a', 'command': ['x'], 'ros': False}, {'name': 'a', 'command': ['y'],
                                                      'ros': False}], 'duplicates'),
    ([{'name': 'a', 'command': ['x'], 'colour': 1}], 'unknown key'),
    ([{'name': 'bad name', 'command': ['x']}], 'identifier'),
    ([{'name': 'a', 'package': 'p', 'executable': 'e', 'plugin': 'nocolon'}], 'module:Class'),
    ([{'name': 'a', 'package': 'p', 'executable': 'e', 'parameters_file': 'nope.yaml'}],
     'not found'),
])
def test_bad_specs_name_the_problem(tmp_path, nodes, match):
    with pytest.raises(LaunchSpecError, match=match):
        _spec(tmp_path, nodes)


def test_ros_node_command_has_name_params_and_remaps(tmp_path, monkeypatch):
    exe = tmp_path / 'prefix' / 'lib' / 'pkg' / 'exe'
    exe.parent.mkdir(parents=True)
    exe.write_text('#!/bin/sh\n')
    exe.chmod(0o755)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'prefix'))
    spec = _spec(tmp_path, [{'name': 'n1', 'package': 'pkg', 'executable': 'exe',
                             'parameters': {'rate_hz': 40.0},
                             'remappings': {'joy': 'gamepad'}}])
    cmd = node_command(spec.nodes[0], tmp_path)
    assert cmd[0] == str(exe)
    assert cmd[1:5] == ['--ros-args', '-r', '__node:=n1', '--params-file']
    assert yaml.safe_load(Path(cmd[5]).read_text()) == {'n1': {'ros__parameters':
                                                               {'rate_hz': 40.0}}}
    assert cmd[-2:] == ['-r', 'joy:=gamepad']


def test_missing_executable_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    spec = _spec(tmp_path, [{'name': 'n1', 'package': 'pkg', 'executable': 'nope'}])
    with pytest.raises(LaunchSpecError, match="executable 'nope' of package 'pkg' not found"):
        ProcessLauncher(spec)


def test_sigint_is_forwarded_and_stubborn_children_get_sigterm(tmp_path):
    good, stubborn = tmp_path / 'good.txt', tmp_path / 'stubborn.txt'
    spec = _spec(tmp_path, [
        {'name': 'good', 'command': [sys.executable, '-c', GOOD_CHILD, str(good)],
         'ros': False},
        {'name': 'stubborn', 'command': [sys.executable, '-c', STUBBORN_CHILD, str(stubborn)],
         'ros': False},
    ])
    out = io.StringIO()
    launcher = ProcessLauncher(spec, out=out, shutdown_timeout=1.0)
    launcher.start()
    _wait_ready(out, ['good', 'stubborn'])
    pids = launcher.pids()
    t0 = time.monotonic()
    launcher.request_stop()
    assert launcher.supervise() == 0
    assert good.read_text() == 'SIGINT\n'
    assert stubborn.read_text() == 'SIGTERM\n'
    assert time.monotonic() - t0 < 5.0
    for pid in pids.values():
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_required_node_exit_shuts_down_the_rest(tmp_path):
    survivor = tmp_path / 'survivor.txt'
    spec = _spec(tmp_path, [
        {'name': 'crash', 'command': [sys.executable, '-c',
                                      'import time, sys; time.sleep(0.5); sys.exit(3)'],
         'ros': False, 'required': True},
        {'name': 'other', 'command': [sys.executable, '-c', GOOD_CHILD, str(survivor)],
         'ros': False},
    ])
    out = io.StringIO()
    launcher = ProcessLauncher(spec, out=out, shutdown_timeout=2.0)
    launcher.start()
    assert launcher.supervise() == 3
    assert 'required node crash exited with code 3' in out.getvalue()
    assert survivor.read_text() == 'SIGINT\n'


def test_respawn_restarts_a_crashed_node(tmp_path):
    counter = tmp_path / 'count.txt'
    script = (f'open({str(counter)!r}, "a").write("x"); import time; time.sleep(0.2); '
              'raise SystemExit(1)')
    spec = _spec(tmp_path, [{'name': 'flaky', 'command': [sys.executable, '-c', script],
                             'ros': False, 'respawn': True}])
    out = io.StringIO()
    launcher = ProcessLauncher(spec, out=out, shutdown_timeout=1.0)
    launcher.start()
    # supervise in a thread until the third start (respawn delays 0.5 s, then 1 s; each start
    # is a Python interpreter, slow on a loaded machine), then stop it
    supervisor = threading.Thread(target=launcher.supervise, kwargs={'max_duration': 60.0})
    supervisor.start()
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline and not (
            counter.exists() and len(counter.read_text()) >= 3):
        time.sleep(0.05)
    launcher.request_stop()
    supervisor.join(timeout=30.0)
    assert not supervisor.is_alive()
    assert len(counter.read_text()) >= 3, out.getvalue()
    assert 'respawn #2' in out.getvalue()


def test_cli_refuses_without_localhost_discovery(tmp_path, monkeypatch, capsys):
    f = tmp_path / 'l.yaml'
    f.write_text(yaml.safe_dump({'nodes': [{'name': 'a', 'command': ['true'], 'ros': False}]}))
    monkeypatch.delenv('ROS_AUTOMATIC_DISCOVERY_RANGE')
    assert main([str(f)]) == 2
    assert 'ROS_AUTOMATIC_DISCOVERY_RANGE is unset' in capsys.readouterr().err


def test_cli_sigint_shuts_children_down_cleanly(tmp_path):
    marks = [tmp_path / f'{n}.txt' for n in ('a', 'b')]
    f = tmp_path / 'l.yaml'
    f.write_text(yaml.safe_dump({'name': 'cli', 'nodes': [
        {'name': m.stem, 'command': [sys.executable, '-c', GOOD_CHILD, str(m)], 'ros': False}
        for m in marks]}))
    proc = subprocess.Popen([sys.executable, '-m', 'cgail_planner.system.launcher', str(f)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    assert proc.stdout is not None
    while sum(ln.strip() in ('[a] ready', '[b] ready') for ln in lines) < 2:
        line = proc.stdout.readline()
        assert line, f'launcher ended early: {lines}'
        lines.append(line)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=15)
    assert proc.returncode == 0, out
    assert [m.read_text() if m.exists() else None for m in marks] == ["SIGINT\n"] * 2, out


def test_load_launch_file_reports_yaml_errors(tmp_path):
    f = tmp_path / 'bad.yaml'
    f.write_text('nodes: [unclosed')
    with pytest.raises(LaunchSpecError, match='not valid YAML'):
        load_launch_file(f)
    with pytest.raises(LaunchSpecError, match='does not exist'):
        load_launch_file(tmp_path / 'missing.yaml')


def test_lean_in_process_nodes_offer_no_parameter_or_lifecycle_services(rclpy_context):
    from cgail_planner.system.launch_spec import NodeSpec
    from cgail_planner.system.launcher import build_node

    built = []
    try:
        for lean in (False, True):
            for exe, cls, name in (('teleop_node', 'TeleopNode', 'teleop'),
                                   ('driver_node', 'DriverNode', 'sleeve_driver')):
                spec = NodeSpec(name=name, package='catheter_driver', executable=exe,
                                plugin=f'catheter_driver.nodes.{exe}:{cls}')
                node = build_node(spec, {'can_channel': f'lean_{lean}'}
                                  if name == 'sleeve_driver' else None, lean=lean)
                built.append(node)
                services = {s.srv_name for s in node.services}
                has_params = any(s.endswith('/get_parameters') for s in services)
                has_lifecycle = any(s.endswith('/change_state') for s in services)
                assert has_params == (not lean), (name, services)
                if name == 'sleeve_driver':
                    assert has_lifecycle == (not lean), services
                    assert node._state_machine.current_state[1] == 'active'
    finally:
        for node in built:
            node.destroy_node()

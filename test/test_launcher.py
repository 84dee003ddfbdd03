"""The launcher: spec validation, signal forwarding, escalation, required nodes, CLI guard."""

import io
import os
from pathlib import Path
import shlex
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest
import yaml

from cgail_node_utils.lifecycle import lifecycle_state
from cgail_rig.launch_spec import (
    default_launch_file,
    LaunchSpecError,
    load_launch_file,
    load_params_file,
    NodeSpec,
    parse_launch,
)
from cgail_rig.launcher import build_node, main, node_command, ProcessLauncher

PACKAGE = Path(__file__).resolve().parents[1] / 'src' / 'cgail_rig'
SIM_RIG = PACKAGE / 'launch' / 'sim_rig.launch.yaml'

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


def _spec(tmp_path, actions, arguments=None):
    return parse_launch({'launch': actions}, tmp_path, arguments, name='t')


def _exe(name, argv, **attrs):
    """A plain process (``executable`` action) running ``argv``."""
    return {'executable': {'name': name, 'cmd': shlex.join(argv), **attrs}}


def _wait_ready(out: io.StringIO, names, timeout=15.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        text = out.getvalue()
        if all(f'[{n}] ready' in text for n in names):
            return
        time.sleep(0.05)
    raise AssertionError(f'children not ready: {out.getvalue()!r}')


@pytest.mark.parametrize('actions, match', [
    ([], 'at least one node'),
    ([{'node': {'name': 'a', 'pkg': 'p'}}], r"node 'a': expected a 'exec' attribute"),
    ([_exe('a', ['x']), _exe('a', ['y'])], 'duplicates'),
    ([{'executable': {'name': 'a', 'cmd': 'x', 'colour': 1}}],
     r"executable 'a' has unknown key\(s\) \['colour'\]"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e', 'plugin': 'p.e:E'}}],
     r"unknown key\(s\) \['plugin'\]"),
    ([_exe('bad name', ['x'])], 'identifier'),
    ([{'executable': {'cmd': 'x'}}], 'expected a name'),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e', 'param': [{'from': 'nope.yaml'}]}}],
     r"parameters file 'nope.yaml' not found"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e', 'param': [{'name': 'x'}]}}],
     "parameter 'x' needs a value"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e',
                'param': [{'name': 'x', 'value': '{k: 1}'}]}}],
     "must read as a bool, number, string or list, found dict '{k: 1}'"),
    ([{'group': {'scoped': True}}], r"unsupported action 'group'"),
    ([_exe('a', ['x'], on_exit='restart')], "on_exit must be shutdown, found 'restart'"),
    ([_exe('a', ['x'], respawn='yes')], "respawn must be true or false, found 'yes'"),
    ([_exe('a', ['$(eval 1 + 1)'])], r"unsupported substitution '\$\(eval 1 \+ 1\)'"),
    ([{'executable': {'name': 'a', 'cmd': "python3 'unclosed"}}],
     "cannot split 'cmd' into words"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e', 'remap': [{'from': 'x'}]}}],
     r"remap\[0\]: expected exactly from and to, found \['from'\]"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e',
                'remap': [{'from': '~/tip pose', 'to': 'x'}]}}],
     r"^launch 't': node 'a'\.remap\[0\]: remap from '~/tip pose' is not a topic name; "
     r"expected a relative, absolute \(/\.\.\.\) or private \(~/\.\.\.\) name"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e',
                'remap': [{'from': '~/x', 'to': 'rig/2x'}]}}],
     r"remap\[0\]: remap to 'rig/2x' is not a topic name"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e',
                'remap': [{'from': '~/x', 'to': 'rig/x/'}]}}],
     r"remap to 'rig/x/' is not a topic name"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e', 'remap': [{'from': '__node', 'to': 'b'}]}}],
     r"remap from '__node': the node name and namespace are set with name and namespace"),
    ([{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e',
                'remap': [{'from': '~/x', 'to': 'y'}, {'from': '~/x', 'to': 'z'}]}}],
     r"remap\[1\]: '~/x' is remapped twice \(to 'y' and 'z'\); expected once"),
])
def test_bad_specs_name_the_problem(tmp_path, actions, match):
    with pytest.raises(LaunchSpecError, match=match):
        _spec(tmp_path, actions)


@pytest.mark.parametrize('data', [
    {'name': 'old', 'nodes': [{'name': 'a', 'command': ['x'], 'ros': False}]},
    [{'node': {'name': 'a', 'pkg': 'p', 'exec': 'e'}}],
    {'launch': {'node': {'name': 'a', 'pkg': 'p', 'exec': 'e'}}},
])
def test_only_the_ros2_yaml_launch_format_is_read(tmp_path, data):
    with pytest.raises(LaunchSpecError, match=r"expected ROS 2's YAML launch format|"
                                              r"'launch' must be a list of actions"):
        parse_launch(data, tmp_path)
    with pytest.raises(LaunchSpecError, match='module:Class'):
        NodeSpec(name='a', package='p', executable='e', plugin='nocolon')


def test_ros_node_command_has_name_params_and_remaps(tmp_path, monkeypatch):
    exe = tmp_path / 'prefix' / 'lib' / 'pkg' / 'exe'
    exe.parent.mkdir(parents=True)
    exe.write_text('#!/bin/sh\n')
    exe.chmod(0o755)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'prefix'))
    (tmp_path / 'a.yaml').write_text('/**: {ros__parameters: {rate_hz: 20.0}}\n')
    spec = _spec(tmp_path, [{'node': {
        'name': 'n1', 'pkg': 'pkg', 'exec': 'exe', 'namespace': 'rig', 'output': 'screen',
        'args': '--verbose "two words"', 'ros_args': '--log-level debug',
        'param': [{'from': '$(dirname)/a.yaml'}, {'name': 'rate_hz', 'value': 40.0}],
        'remap': [{'from': '~/joy', 'to': 'gamepad'}]}}])
    node = spec.nodes[0]
    assert node.plugin == 'pkg.nodes.exe:Exe'
    assert node.fully_qualified_name == '/rig/n1'
    cmd = node_command(node, tmp_path)
    assert cmd[:-1] == [str(exe), '--verbose', 'two words', '--ros-args', '-r', '__node:=n1',
                        '-r', '__ns:=/rig', '-r', '~/joy:=gamepad', '--log-level', 'debug',
                        '--params-file', str(tmp_path / 'a.yaml'), '--params-file']
    assert yaml.safe_load(Path(cmd[-1]).read_text()) == {'/**': {'ros__parameters':
                                                                 {'rate_hz': 40.0}}}


def test_missing_executable_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    spec = _spec(tmp_path, [{'node': {'name': 'n1', 'pkg': 'pkg', 'exec': 'nope'}}])
    with pytest.raises(LaunchSpecError, match="executable 'nope' of package 'pkg' not found"):
        ProcessLauncher(spec)


def test_sigint_is_forwarded_and_stubborn_children_get_sigterm(tmp_path):
    good, stubborn = tmp_path / 'good.txt', tmp_path / 'stubborn.txt'
    spec = _spec(tmp_path, [
        _exe('good', [sys.executable, '-c', GOOD_CHILD, str(good)]),
        _exe('stubborn', [sys.executable, '-c', STUBBORN_CHILD, str(stubborn)]),
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
        _exe('crash', [sys.executable, '-c', 'import time, sys; time.sleep(0.5); sys.exit(3)'],
             on_exit='shutdown'),
        _exe('other', [sys.executable, '-c', GOOD_CHILD, str(survivor)]),
    ])
    assert [n.required for n in spec.nodes] == [True, False]
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
    spec = _spec(tmp_path, [_exe('flaky', [sys.executable, '-c', script], respawn=True,
                                 respawn_delay=0.25)])
    out = io.StringIO()
    launcher = ProcessLauncher(spec, out=out, shutdown_timeout=1.0)
    launcher.start()
    # supervise in a thread until the third start (respawn_delay 0.25 s; each start is a
    # Python interpreter, slow on a loaded machine), then stop it
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
    assert 'respawn #2 in 0.2 s' in out.getvalue()


def test_cli_refuses_without_localhost_discovery(tmp_path, monkeypatch, capsys):
    f = tmp_path / 'l.yaml'
    f.write_text(yaml.safe_dump({'launch': [_exe('a', ['true'])]}))
    monkeypatch.delenv('ROS_AUTOMATIC_DISCOVERY_RANGE')
    assert main([str(f)]) == 2
    assert 'ROS_AUTOMATIC_DISCOVERY_RANGE is unset' in capsys.readouterr().err


def test_cli_sigint_shuts_children_down_cleanly(tmp_path):
    marks = [tmp_path / f'{n}.txt' for n in ('a', 'b')]
    f = tmp_path / 'l.yaml'
    f.write_text(yaml.safe_dump({'launch': [
        _exe(m.stem, [sys.executable, '-c', GOOD_CHILD, str(m)]) for m in marks]}))
    proc = subprocess.Popen([sys.executable, '-m', 'cgail_rig.launcher', str(f)],
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
    f.write_text('launch: [unclosed')
    with pytest.raises(LaunchSpecError, match='not valid YAML'):
        load_launch_file(f)
    with pytest.raises(LaunchSpecError, match='does not exist'):
        load_launch_file(tmp_path / 'missing.yaml')


def test_launch_files_are_in_the_packages_launch_folder_and_installed_there():
    """ROS users look in share/<pkg>/launch/*.launch.yaml: the source tree has them there, the
    install too, and an installed one finds its parameter files."""
    assert default_launch_file() == SIM_RIG
    names = ['rig.launch.yaml', 'sim_rig.launch.yaml']
    assert sorted(p.name for p in (PACKAGE / 'launch').iterdir()) == names
    shares = [Path(p) / 'share' / 'cgail_rig' for p in
              os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
              if p and (Path(p) / 'share' / 'cgail_rig').is_dir()]
    assert shares, 'cgail_rig is not installed (bash scripts/setup.sh)'
    installed = shares[0] / 'launch'
    assert sorted(p.name for p in installed.glob('*.launch.yaml')) == names
    spec = load_launch_file(installed / 'sim_rig.launch.yaml')
    assert spec.name == 'sim_rig'
    assert all(Path(f).is_file() for n in spec.nodes for f in n.parameters_files)


def test_an_old_layout_path_reads_the_moved_file_with_a_deprecation_warning(tmp_path, caplog):
    pkg = tmp_path / 'pkg'
    (pkg / 'launch').mkdir(parents=True)
    moved = pkg / 'launch' / 'r.launch.yaml'
    moved.write_text(yaml.safe_dump({'launch': [_exe('a', ['true'])]}))
    old = pkg / 'config' / 'launch' / 'r.yaml'
    with caplog.at_level('WARNING'):
        spec = load_launch_file(old)
    assert spec.name == 'r' and [n.name for n in spec.nodes] == ['a']
    assert f'launch file {old} moved to {moved}; the old path is deprecated' in caplog.text
    with pytest.raises(LaunchSpecError, match='does not exist'):
        load_launch_file(pkg / 'config' / 'launch' / 'other.yaml')


def test_in_process_nodes_take_the_launch_files_remaps(rclpy_context):
    """build_node (rig_launch --in-process, the simulated session) applies a node's remaps:
    teleop's own ~/joy and ~/..._command become the rig's joy and catheter/..."""
    (spec,) = load_launch_file(SIM_RIG).select(['teleop']).nodes
    bare = NodeSpec(name='teleop', package=spec.package, executable=spec.executable,
                    plugin=spec.plugin)
    for node_spec, prefix, joy in ((spec, '/catheter', '/joy'), (bare, '/teleop', '/teleop/joy')):
        node = build_node(node_spec, lean=True)
        try:
            assert {f'{prefix}/insertion_command', f'{prefix}/bend_command'} <= \
                {p.topic_name for p in node.publishers}, node_spec.remappings
            assert joy in {s.topic_name for s in node.subscriptions}, node_spec.remappings
        finally:
            node.destroy_node()


def test_lean_in_process_nodes_offer_no_parameter_type_or_lifecycle_services(rclpy_context):
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
                # (rclpy's type description service keeps heap per node it served: LEAN_PARAMETERS)
                has_types = any(s.endswith('/get_type_description') for s in services)
                assert has_params == (not lean), (name, services)
                assert has_types == (not lean), (name, services)
                if name == 'sleeve_driver':
                    assert has_lifecycle == (not lean), services
                    if lean:  # no lifecycle services, so nothing public reports the state
                        assert node._state_machine.current_state[1] == 'active'
                    else:
                        assert lifecycle_state(node) == 'active'
    finally:
        for node in built:
            node.destroy_node()


def test_in_process_lifecycle_nodes_wait_for_a_manager_when_autostart_is_false(rclpy_context):
    spec = NodeSpec(name='sleeve_driver', package='catheter_driver', executable='driver_node',
                    plugin='catheter_driver.nodes.driver_node:DriverNode',
                    parameters={'autostart': False})
    node = build_node(spec, {'can_channel': 'autostart_off'})
    try:
        assert lifecycle_state(node) == 'unconfigured'
    finally:
        node.destroy_node()


def test_launch_arguments_replace_var_with_their_default_or_given_value(tmp_path):
    data = {'launch': [
        {'arg': {'name': 'anatomy', 'default': 'default', 'description': 'the aorta'}},
        {'arg': {'name': 'rate', 'default': '40'}},
        {'let': {'name': 'tag', 'value': '$(var anatomy)-$(var rate)'}},
        {'node': {'name': 'a', 'pkg': 'p', 'exec': 'e', 'args': '--rate=$(var rate)',
                  'env': [{'name': 'ANATOMY', 'value': '$(var anatomy)'}],
                  'param': [{'name': 'anatomy', 'value': '$(var anatomy)'},
                            {'name': 'rate_hz', 'value': 10.0},
                            {'name': 'names', 'value': ['$(var anatomy)/x', 'y']},
                            {'name': 'tag', 'value': '$(var tag)'}]}}]}
    spec = parse_launch(data, tmp_path, name='args')
    assert spec.arguments == {'anatomy': 'default', 'rate': '40'}
    node = spec.nodes[0]
    assert node.parameters == {'anatomy': 'default', 'rate_hz': 10.0,
                               'names': ['default/x', 'y'], 'tag': 'default-40'}
    assert (node.args, node.env) == (('--rate=40',), {'ANATOMY': 'default'})
    node = parse_launch(data, tmp_path, {'anatomy': '/data/p 07'}).nodes[0]
    assert node.parameters['anatomy'] == '/data/p 07' and node.env['ANATOMY'] == '/data/p 07'


def test_parameter_values_are_typed_as_launch_ros_types_them(tmp_path, monkeypatch):
    """A string value is read as YAML after substitution; files come first, in order."""
    share = tmp_path / 'prefix' / 'share' / 'pkg'
    share.mkdir(parents=True)
    (share / 'p.yaml').write_text('n: {ros__parameters: {a: 1, b: 1}}\n')
    (tmp_path / 'q.yaml').write_text('/**: {ros__parameters: {b: 2}}\n')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'prefix'))
    monkeypatch.setenv('RIG_PORT', '8780')
    monkeypatch.chdir(tmp_path)
    spec = _spec(tmp_path, [
        {'arg': {'name': 'empty', 'default': ''}},
        {'node': {'name': 'n', 'pkg': 'p', 'exec': 'e', 'param': [
            {'from': '$(find-pkg-share pkg)/p.yaml'}, {'from': 'q.yaml'},
            {'name': 'port', 'value': '$(env RIG_PORT)'},
            {'name': 'rate', 'value': '$(env RIG_RATE 2.5)'},
            {'name': 'flag', 'value': 'true'}, {'name': 'policy', 'value': '$(var empty)'},
            {'name': 'limits', 'param': [{'name': 'speed', 'value': 0.005},
                                         {'name': 'angle', 'value': '1.5'}]}]}}])
    node = spec.nodes[0]
    assert node.parameters == {'port': 8780, 'rate': 2.5, 'flag': True, 'policy': '',
                               'limits.speed': 0.005, 'limits.angle': 1.5}
    assert node.parameters_files == (str(share / 'p.yaml'), str(tmp_path / 'q.yaml'))
    merged = {}
    for path in node.parameters_files:
        merged.update(load_params_file(path, 'n'))
    assert merged == {'a': 1, 'b': 2}
    assert load_params_file(str(share / 'p.yaml'), 'n', namespace='rig') == {}


@pytest.mark.parametrize('args, given, match', [
    ([{'name': 'anatomy', 'default': 'default'}], {'anatomy2': 'x'},
     r"^launch 'args' has no argument\(s\) \['anatomy2'\]; expected some of \['anatomy'\]$"),
    ([], None, r"^launch 'args': node 'a'\.param\[0\]: \$\(var anatomy\) names no launch "
               r"argument; expected one of \[\]$"),
    ([{'name': 'anatomy', 'default': 40}], None,
     r"'default' must be a string \(quote it in the YAML\), found int 40"),
    ([{'name': 'my-anatomy', 'default': 'x'}], None,
     r"argument names must be identifiers, found 'my-anatomy'"),
    ([{'name': 'anatomy'}], None,
     r"^launch 'args' needs the argument 'anatomy' \(it has no default\): give it as "
     r"anatomy:=VALUE$"),
])
def test_bad_launch_arguments_name_the_problem(tmp_path, args, given, match):
    data = {'launch': [*({'arg': a} for a in args),
                       {'node': {'name': 'a', 'pkg': 'p', 'exec': 'e',
                                 'param': [{'name': 'anatomy', 'value': '$(var anatomy)'}]}}]}
    with pytest.raises(LaunchSpecError, match=match):
        parse_launch(data, tmp_path, given, name='args')


ANATOMY_NODES = ('phantom', 'planner', 'autonomy', 'gui', 'igtl_bridge')


def test_sim_rig_nodes_build_from_their_packages_node_classes():
    """sim_rig.launch.yaml holds only what ``ros2 launch`` reads; the in-process class of each node
    comes from its pkg and exec, and its parameter files from next to the launch file."""
    import importlib

    spec = load_launch_file(SIM_RIG)
    assert spec.name == 'sim_rig' and spec.arguments == {'anatomy': 'default', 'policy_path': ''}
    for node in spec.nodes:
        module, _, cls = node.plugin.partition(':')
        assert isinstance(getattr(importlib.import_module(module), cls), type), node.plugin
    owners = {'phantom': 'cgail_rig', 'planner': 'cgail_planner', 'operator': 'cgail_planner',
              'autonomy': 'cgail_planner', 'igtl_bridge': 'cgail_gui',
              'foxglove_bridge': 'cgail_gui'}  # each node's
    # parameter file is its package's
    assert {n.name: n.parameters_files for n in spec.nodes if n.parameters_files} == {
        name: (str(PACKAGE.parent / owner / 'config' / f'{name}.yaml'),)
        for name, owner in owners.items()}
    assert [n.name for n in spec.nodes if n.required] == ['phantom']


def test_the_real_rig_launch_file_drives_real_devices_with_the_calibration_file(tmp_path):
    """rig.launch.yaml: every node builds from its package's class, every device talks to hardware
    (SocketCAN, the serial port given), and the calibration file comes after the aurora's
    defaults, so its registration and tool_transform win."""
    import importlib

    calibration = tmp_path / 'calibration.yaml'
    calibration.write_text('aurora:\n  ros__parameters:\n    tool_transform: '
                           '[0.0, 0.012, 0.0, 0.0, 0.0, 0.0, 1.0]\n')
    spec = load_launch_file(SIM_RIG.with_name('rig.launch.yaml'),
                            {'aurora_port': '/dev/ttyUSB3', 'calibration': str(calibration),
                             'can_channel': 'can1'})
    nodes = {n.name: n for n in spec.nodes}
    assert set(nodes) == {'aurora', 'pam_controller', 'sleeve_driver', 'joy', 'teleop',
                          'planner', 'gui', 'igtl_bridge', 'foxglove_bridge'}
    for node in spec.nodes:
        module, _, cls = node.plugin.partition(':')
        assert isinstance(getattr(importlib.import_module(module), cls), type), node.plugin
        for path in node.parameters_files:
            assert Path(path).is_file(), (node.name, path)

    def params(name):
        out = {}
        for path in nodes[name].parameters_files:
            out.update(load_params_file(path, name))
        return out | nodes[name].parameters

    aurora = params('aurora')
    assert aurora['port'] == '/dev/ttyUSB3'
    assert aurora['tool_transform'] == [0.0, 0.012, 0.0, 0.0, 0.0, 0.0, 1.0]
    for name, sim in (('pam_controller', 'simulate_regulators'),
                      ('sleeve_driver', 'simulate_device')):
        assert (params(name)['can_interface'], params(name)['can_channel'],
                params(name)[sim]) == ('socketcan', 'can1', False), name
    assert params('igtl_bridge')['host'] == '127.0.0.1'
    assert (params('foxglove_bridge')['host'], params('foxglove_bridge')['allow_remote']) == (
        '127.0.0.1', False)


def test_sim_rig_hands_the_anatomy_argument_to_phantom_planner_gui_and_bridge(tmp_path):
    """In process mode each node gets it in its own params file, in-process as an override;
    both come from the name/value ``param`` entries over the ``from`` files."""
    assert {n.name: n.parameters.get('anatomy') for n in load_launch_file(SIM_RIG).nodes
            if n.name in ANATOMY_NODES} == dict.fromkeys(ANATOMY_NODES, 'default')
    spec = load_launch_file(SIM_RIG, {'anatomy': 'runs/patients/p07',
                                      'policy_path': '/m/p07.onnx'})
    for node in spec.nodes:
        params = {}
        for path in node.parameters_files:
            params.update(load_params_file(path, node.name))
        params.update(node.parameters)
        expected = 'runs/patients/p07' if node.name in ANATOMY_NODES else None
        assert params.get('anatomy') == expected, node.name
        if node.name in ANATOMY_NODES:
            cmd = node_command(node, tmp_path)
            assert cmd[-2] == '--params-file'
            assert yaml.safe_load(Path(cmd[-1]).read_text())['/**']['ros__parameters'][
                'anatomy'] == expected
        if node.name == 'planner':
            assert params['policy_path'] == '/m/p07.onnx'


def test_sim_rig_in_process_runs_phantom_planner_and_gui_in_a_prepared_anatomy(
        rclpy_context, prepared_anatomy, tmp_path):
    """``anatomy:=DIR policy_path:=...`` reaches the nodes: each resolves the same anatomy and
    the planner accepts a policy contracted for it."""
    from cgail_learning.export import default_contract, write_contract
    from cgail_sim.anatomy_spec import resolve_anatomy

    models = PACKAGE.parent / 'cgail_planner' / 'cgail_planner' / 'models'
    policy = write_contract(models / 'cgail_default_static.onnx',
                            default_contract(prepared_anatomy, 'static'), tmp_path / 'p07.onnx')
    spec = load_launch_file(SIM_RIG, {'anatomy': str(prepared_anatomy),
                                      'policy_path': str(policy)}).select(list(ANATOMY_NODES))
    extra = {'phantom': {'aurora_link': str(tmp_path / 'aurora')}, 'gui': {'port': 0}}
    nodes = {}
    try:
        for spec_node in spec.nodes:
            nodes[spec_node.name] = build_node(spec_node, extra.get(spec_node.name))
        assert {name: node.get_parameter('anatomy').value for name, node in nodes.items()} == \
            dict.fromkeys(ANATOMY_NODES, str(prepared_anatomy))
        h = resolve_anatomy(prepared_anatomy).content_hash
        assert nodes['phantom'].world.anatomy.content_hash == h
        assert nodes['phantom'].anatomy_label == 'p07'
        assert nodes['planner'].wall.anatomy.content_hash == h
        assert nodes['planner'].planner is not None and nodes['planner'].contract_notes == []
    finally:
        for node in nodes.values():
            node.destroy_node()


def test_rig_launch_refuses_a_bad_anatomy_in_one_line(tmp_path, capsys):
    missing = tmp_path / 'nowhere'
    assert main([str(SIM_RIG), '--in-process', '--only', 'planner', f'anatomy:={missing}']) == 2
    err = capsys.readouterr().err
    assert err.startswith("cgail launch: error: node 'planner': ") and err.count('\n') == 1, err
    assert f"found '{missing}': no such file or directory" in err


@pytest.mark.parametrize('words, text', [
    (['anatomy=x'], "launch arguments must read NAME:=VALUE, found ['anatomy=x']"),
    ([':=x'], "launch arguments must read NAME:=VALUE, found [':=x']"),
    (['anatomyy:=x'], "launch 'sim_rig' has no argument(s) ['anatomyy']; expected some of "
                      "['anatomy', 'policy_path']"),
])
def test_rig_launch_refuses_bad_launch_arguments(capsys, words, text):
    assert main([str(SIM_RIG), *words]) == 2
    assert capsys.readouterr().err == f'cgail launch: error: {text}\n'


def test_launch_arguments_may_follow_the_options(capsys):
    """As docs/tutorials/rig.md writes it: ``cgail launch FILE --in-process NAME:=VALUE``."""
    assert main([str(SIM_RIG), '--in-process', '--max-duration', '1', 'anatomyy:=x']) == 2
    assert capsys.readouterr().err == ("cgail launch: error: launch 'sim_rig' has no argument(s) "
                                       "['anatomyy']; expected some of ['anatomy', "
                                       "'policy_path']\n")

"""foxglove_bridge in-process, with a Foxglove WebSocket client as the app: each topic arrives
as a ros2msg/cdr channel under its resolved name and decodes from the advertised schema to what
was published, a client that joins late gets the latched state, and the server listens on
loopback only unless asked (a bad host or a busy port is one line)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
import socket
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Path as PathMsg
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
from tf2_msgs.msg import TFMessage
import yaml

from cgail_gui.core.foxglove_view import FoxgloveBridgeConfig, FoxgloveConfigError, STREAMS
from cgail_gui.hw.foxglove_server import FoxgloveServerError
from cgail_gui.nodes.foxglove_bridge import FoxgloveBridge, main, MESSAGE_CLASSES, QOS
from cgail_gui.testing import FoxgloveClient
from cgail_node_utils.testing import spin_until
from cgail_planner.nodes import conversions as conv

TIMEOUT = 30.0
PRESSURES = [61000.0, 12000.5, 30000.0, 29999.25]
#: (remapped) rig name of each private stream, as the launch files give them
REMAPS = [f'{s.own}:={s.rig}' for s in STREAMS if s.own.startswith('~/')]


class Rig:
    """The bridge (remapped as the launch files do), a probe node publishing like the rig, an
    executor and Foxglove clients."""

    def __init__(self) -> None:
        self.node = FoxgloveBridge(
            parameter_overrides=[Parameter('port', value=0)],
            cli_args=['--ros-args', *(w for r in REMAPS for w in ('-r', r))])
        self.probe = rclpy.create_node('probe')
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.pressures = self.probe.create_publisher(Float64MultiArray, 'pam/pressures',
                                                     conv.SENSOR_QOS)
        self.tip = self.probe.create_publisher(PoseStamped, 'em_tracker/tip_pose',
                                               conv.SENSOR_QOS)
        self.diagnostics = self.probe.create_publisher(DiagnosticArray, '/diagnostics',
                                                       conv.DIAGNOSTICS_QOS)
        self.path = self.probe.create_publisher(PathMsg, 'planner/path', conv.LATCHED_QOS)
        self.tf_static = self.probe.create_publisher(TFMessage, '/tf_static', conv.LATCHED_QOS)
        self.probe.create_timer(0.025, self._publish)  # 40 Hz, as the rig's devices
        self.clients: list[FoxgloveClient] = []

    def _publish(self) -> None:
        self.pressures.publish(Float64MultiArray(data=PRESSURES))
        tip = PoseStamped()
        tip.header.frame_id = 'phantom'
        tip.pose.position.z = -0.085
        tip.pose.orientation.w = 1.0
        self.tip.publish(tip)
        self.diagnostics.publish(DiagnosticArray(status=[DiagnosticStatus(
            level=DiagnosticStatus.OK, name='pam_controller', message='ok')]))

    def connect(self, *topics: str) -> FoxgloveClient:
        client = FoxgloveClient(f'ws://127.0.0.1:{self.node.server.port}', topics)
        self.clients.append(client)
        return client

    def receive(self, client: FoxgloveClient, topic: str, count: int = 1) -> list:
        assert spin_until(self.executor, lambda: len(client.received(topic)) >= count), \
            f'{topic}: {len(client.received(topic))} of {count} messages within {TIMEOUT} s ' \
            f'(channels {sorted(client.channels)}, errors {client.errors})'
        return client.received(topic)



@pytest.fixture
def rig(ros) -> Iterator[Rig]:
    """A :class:`Rig`; its clients, executor and nodes are closed after the test."""
    r = Rig()
    yield r
    for client in r.clients:
        client.close()
    r.executor.shutdown()
    for node in (r.node, r.probe):
        node.destroy_node()


def test_every_stream_is_a_ros2msg_cdr_channel_under_its_rig_name(rig) -> None:
    client = rig.connect()
    assert spin_until(rig.executor, lambda: len(client.channels) == len(STREAMS), TIMEOUT)
    want = {'/' + (s.rig or s.own.lstrip('/')): s.msg_type for s in STREAMS}
    assert {t: c['schemaName'] for t, c in client.channels.items()} == want
    assert {(c['encoding'], c['schemaEncoding']) for c in client.channels.values()} == {
        ('cdr', 'ros2msg')}
    assert client.server_info['name'] == 'cgail rig'
    assert set(MESSAGE_CLASSES) == {s.msg_type for s in STREAMS}
    assert all(s.qos in QOS for s in STREAMS)


def test_a_client_decodes_pressures_tip_and_diagnostics_from_the_advertised_schemas(rig):
    client = rig.connect('/pam/pressures', '/em_tracker/tip_pose', '/diagnostics')
    log_time, pressures = rig.receive(client, '/pam/pressures', count=3)[-1]
    assert list(pressures.data) == PRESSURES
    assert log_time > 0
    _, tip = rig.receive(client, '/em_tracker/tip_pose')[-1]
    assert (tip.header.frame_id, tip.pose.position.z) == ('phantom', -0.085)
    _, diagnostics = rig.receive(client, '/diagnostics')[-1]
    assert diagnostics.status[0].name == 'pam_controller'


def test_a_client_that_joins_late_gets_the_latched_path_and_static_transforms(rig) -> None:
    path = PathMsg()
    path.header.frame_id = 'phantom'
    path.poses = [PoseStamped() for _ in range(3)]
    for i, pose in enumerate(path.poses):
        pose.pose.position.x = 0.01 * i
    rig.path.publish(path)
    transform = TransformStamped()
    transform.header.frame_id, transform.child_frame_id = 'aurora', 'phantom'
    transform.transform.rotation.w = 1.0
    rig.tf_static.publish(TFMessage(transforms=[transform]))
    assert spin_until(rig.executor, lambda: all(
        len(rig.node.kept[t]) == 1 for t in ('/planner/path', '/tf_static')))
    time.sleep(0.2)  # published once, long before the client comes
    client = rig.connect('/planner/path', '/tf_static')
    _, got = rig.receive(client, '/planner/path')[0]
    assert [p.pose.position.x for p in got.poses] == [0.0, 0.01, 0.02]
    _, tf = rig.receive(client, '/tf_static')[0]
    assert tf.transforms[0].child_frame_id == 'phantom'


def test_yaml_defaults_equal_the_declared_defaults(ros) -> None:
    cfg = Path(__file__).resolve().parents[2] / 'config' / 'foxglove_bridge.yaml'
    params = yaml.safe_load(cfg.read_text())['foxglove_bridge']['ros__parameters']
    node = FoxgloveBridge(parameter_overrides=[Parameter('port', value=0)])
    try:
        assert {name: node.get_parameter(name).value for name in params if name != 'port'} == \
            {k: v for k, v in params.items() if k != 'port'}
        defaults = FoxgloveBridgeConfig()
        assert (defaults.host, defaults.port, defaults.allow_remote) == (
            params['host'], params['port'], params['allow_remote']) == ('127.0.0.1', 8765, False)
        assert all(node.describe_parameter(n).read_only for n in params)
    finally:
        node.destroy_node()


@pytest.mark.parametrize('host', ['0.0.0.0', '192.168.1.20', '::'])
def test_an_address_other_machines_reach_is_refused_without_allow_remote(ros, host) -> None:
    with pytest.raises(FoxgloveConfigError, match=f'host: expected a loopback address '
                                                  rf'\(127.0.0.1, ::1, localhost\), found '
                                                  f"'{host}'.*allow_remote:=true"):
        FoxgloveBridge(parameter_overrides=[Parameter('host', value=host)])


def test_loopback_hosts_and_allow_remote_are_accepted_without_binding_elsewhere() -> None:
    for host in ('127.0.0.1', '127.0.0.2', '::1', 'localhost'):
        FoxgloveBridgeConfig(host=host)
    FoxgloveBridgeConfig(host='0.0.0.0', allow_remote=True)  # (validated only: no server here)
    with pytest.raises(FoxgloveConfigError, match="expected an IP address or 'localhost', "
                                                  "found 'rig-pc'"):
        FoxgloveBridgeConfig(host='rig-pc', allow_remote=True)


def test_a_busy_port_is_one_line(ros) -> None:
    with socket.socket() as busy:
        busy.bind(('127.0.0.1', 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(FoxgloveServerError, match=f'^expected to serve Foxglove on '
                                                      f'127.0.0.1:{port}, found: .*in use'):
            FoxgloveBridge(parameter_overrides=[Parameter('port', value=port)])


@pytest.mark.parametrize('args, message', [
    (['-p', 'host:=0.0.0.0'], "found '0.0.0.0'"),
    (['-p', 'port:=70000'], 'port'),
])
def test_the_console_script_ends_bad_input_with_one_line(capsys, args, message) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(['foxglove_bridge', '--ros-args', *args])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('foxglove_bridge: error: ') and message in err
    assert len(err.splitlines()) == 1, err

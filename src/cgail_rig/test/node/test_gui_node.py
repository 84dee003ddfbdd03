"""gui_node in-process: static files (no traversal), WebSocket state, reconnect, bad input."""

from __future__ import annotations

from collections.abc import Iterator
import json
from pathlib import Path
import socket
import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
import pytest
import rclpy
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from cgail_gui.nodes.gui_node import GuiNode

REPO = Path(__file__).resolve().parents[4]
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Running:
    """A GuiNode plus a publisher node (and ``extra`` nodes), spun by one executor in a
    background thread. The publisher uses the GUI's own topic names (``/gui/...``); ``cli_args``
    may remap them onto an ``extra`` node's."""

    def __init__(self, *extra: Any, cli_args: list[str] | None = None, **params: Any) -> None:
        overrides = [Parameter('port', value=0), Parameter('anatomy', value='')]
        overrides += [Parameter(k, value=v) for k, v in params.items()]
        self.node = GuiNode(parameter_overrides=overrides, cli_args=cli_args)
        self.pub = rclpy.create_node('gui_test_pub')
        self.tip = self.pub.create_publisher(PoseStamped, '/gui/tip_pose',
                                             qos_profile_sensor_data)
        self.path = self.pub.create_publisher(PathMsg, '/gui/path', LATCHED)
        self.goal = self.pub.create_publisher(PoseStamped, '/gui/goal', 10)
        self.wp = self.pub.create_publisher(PointStamped, '/gui/next_waypoint',
                                            qos_profile_sensor_data)
        self.bend = self.pub.create_publisher(JointState, '/gui/suggested_bend',
                                              qos_profile_sensor_data)
        self.diag = self.pub.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.pub)
        self.extra = extra
        for node in extra:
            self.executor.add_node(node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def ws(self, origin: str | None = None) -> ClientConnection:
        headers = {'Origin': origin} if origin else None
        return connect(f'ws://127.0.0.1:{self.node.port}/ws', additional_headers=headers,
                       open_timeout=5)

    def publish_path(self, n: int = 5) -> None:
        msg = PathMsg()
        msg.header.frame_id = 'phantom'
        for i in range(n):
            ps = PoseStamped()
            ps.pose.position.x = 0.01 * i
            msg.poses.append(ps)
        self.path.publish(msg)

    def publish_tip(self, x: float, qw: float = 1.0) -> None:
        msg = PoseStamped()
        msg.header.frame_id = 'phantom'
        msg.header.stamp = self.pub.get_clock().now().to_msg()
        msg.pose.position.x = x
        msg.pose.orientation.w = qw
        self.tip.publish(msg)

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(5)
        self.node.destroy_node()
        self.pub.destroy_node()
        for node in self.extra:
            node.destroy_node()


@pytest.fixture
def running(ros: None) -> Iterator[Running]:
    r = Running(bags_dir=str(REPO / 'bags'))
    try:
        yield r
    finally:
        r.close()


def recv_until(ws: ClientConnection, predicate: Any, timeout: float = 10.0,
               action: Any = None) -> dict[str, Any]:
    """Merge state messages until predicate(merged, last message) holds; action() each time."""
    merged: dict[str, Any] = {}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if action is not None:
            action()
        try:
            msg = json.loads(ws.recv(timeout=0.1))
        except TimeoutError:
            continue
        assert msg['type'] == 'state'
        ws.send('{"type": "ack"}')          # as the page does after each state
        if msg['full']:
            merged = {'_full': True, '_source': msg['source']}
        merged.update(msg['items'])
        merged['_source'] = msg['source']
        if predicate(merged, msg):
            return merged
    raise AssertionError(f'state never matched; last keys {sorted(merged)}')


def http_get(port: int, target: str) -> tuple[int, bytes]:
    """Raw GET so that nothing normalises the request target."""
    with socket.create_connection(('127.0.0.1', port), timeout=5) as s:
        s.sendall(f'GET {target} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n'.encode())
        data = b''
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b'\r\n\r\n')
    return int(head.split()[1]), body


def test_bad_parameters_raise_at_construction(ros: None) -> None:
    with pytest.raises(InvalidParameterValueException):
        GuiNode(parameter_overrides=[Parameter('port', value=70000)])
    with pytest.raises(ValueError, match='host must be an IPv4 or IPv6 address literal'):
        GuiNode(parameter_overrides=[Parameter('host', value='localhost'),
                                     Parameter('port', value=0)])


def test_serves_its_own_files_only(running: Running) -> None:
    port = running.node.port
    assert port
    status, body = http_get(port, '/')
    assert status == 200 and b'Catheter guidance' in body
    for ok in ('/app.js', '/style.css', '/vendor/three.module.js', '/vendor/three.core.js',
               '/vendor/OrbitControls.js', '/app.js?v=1'):
        assert http_get(port, ok)[0] == 200, ok
    for bad in ('/../setup.py', '/..%2fsetup.py', '/%2e%2e/%2e%2e/setup.py', '//etc/passwd',
                '/vendor/../app.js', '/node_modules/three/package.json', '/package.json/',
                '/web/app.js', '/./app.js', '/.%2e/package.xml', '/index.html/..', '/ws/x',
                '/etc/passwd', '/app.js%00.png'):
        status, body = http_get(port, bad)
        assert status == 404, (bad, status, body[:80])
    assert running.node._server.stats.http_not_found >= 14
    # other methods and garbage get an error or a closed socket; the server keeps serving
    for raw in (b'POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 3\r\n\r\nabc',
                b'\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03' + bytes(200),
                b'GET / HTTP/1.1\r\n' + b'X: ' + b'a' * 20000 + b'\r\n\r\n'):
        with socket.create_connection(('127.0.0.1', port), timeout=1) as s:
            s.sendall(raw)
            try:
                reply = s.recv(100)
            except (ConnectionResetError, TimeoutError):   # dropped, or left to time out
                reply = b''
            assert not reply.startswith(b'HTTP/1.1 200'), raw[:20]
    assert http_get(port, '/')[0] == 200


def test_websocket_full_state_updates_and_reconnect(running: Running) -> None:
    with running.ws() as ws:
        first = recv_until(ws, lambda m, msg: msg['full'])
        assert first['trial']['phase'] == 'armed'
        assert first['config']['trial_limit_s'] == 180.0
        assert {'fixtures/centerline_trial', 'fixtures/cgail_trial'} \
            <= set(first['replay']['bags'])
        running.publish_path(7)
        state = recv_until(ws, lambda m, msg: 'path' in m and 'tip' in m,
                           action=lambda: running.publish_tip(0.02))
        assert len(state['path']['points']) == 7
        assert state['path']['length_m'] == pytest.approx(0.06)
        assert state['tip']['p'] == [0.02, 0.0, 0.0]
        assert state['tip']['heading'] == [0.0, 1.0, 0.0]
    # a new connection gets everything again in its first message
    with running.ws() as ws:
        again = recv_until(ws, lambda m, msg: msg['full'])
        assert len(again['path']['points']) == 7
        assert again['tip']['p'] == [0.02, 0.0, 0.0]


def test_guidance_items_from_planner_topics(running: Running) -> None:
    goal = PoseStamped()
    goal.header.frame_id = 'phantom'
    goal.pose.position.y = 0.05
    wp = PointStamped()
    wp.point.x, wp.point.y = 0.01, 0.01   # 45 deg to the right of the heading (+y)
    bend = JointState(name=['bend_gamma', 'bend_alpha'], position=[-0.3, 0.0])
    diag = DiagnosticArray(status=[DiagnosticStatus(
        level=DiagnosticStatus.WARN, name='aurora: EM tracker', message='tool MISSING',
        hardware_id='ndi_aurora:/dev/ttyUSB0')])

    def publish() -> None:
        running.goal.publish(goal)
        running.wp.publish(wp)
        running.bend.publish(bend)
        running.diag.publish(diag)
        running.publish_tip(0.0)

    with running.ws() as ws:
        s = recv_until(ws, lambda m, msg: 'waypoint' in m.get('guide', {})
                       and 'dist_target' in m.get('guide', {}) and 'bend' in m
                       and m.get('diagnostics', {}).get('tracker'), action=publish)
    assert s['guide']['dist_target'] == pytest.approx(0.05)
    assert s['guide']['waypoint']['angle'] == pytest.approx(0.785398, abs=1e-6)
    assert s['guide']['waypoint']['screen'] == pytest.approx([1.0, 0.0])
    assert s['bend']['magnitude'] == pytest.approx(0.3)
    assert s['bend']['screen'] == pytest.approx([1.0, 0.0])     # gamma < 0 turns right (+x)
    assert s['bend']['fraction'] == pytest.approx(0.3 / (3.141592653589793 / 2), abs=1e-4)
    tracker = s['diagnostics']['statuses'][s['diagnostics']['tracker']]
    assert tracker['level'] == 'WARN' and tracker['message'] == 'tool MISSING'


def test_malformed_messages_are_ignored_and_logged(running: Running) -> None:
    bad = ['not json', '[1, 2]', '{"type": "explode"}', '{"type": "trial", "action": "nuke"}',
           '{"type": "replay", "action": "start", "bag": "../../etc", "rate": 1}',
           '{"type": "replay", "action": "start", "bag": "x", "rate": 1e9}',
           '{"type": "replay", "action": "start", "bag": 3}', b'\x00\x01binary',
           '{' * 3000]
    with running.ws() as ws:
        recv_until(ws, lambda m, msg: msg['full'])
        for b in bad:
            ws.send(b)
        ws.send('{"type": "resync"}')
        recv_until(ws, lambda m, msg: msg['full'])     # still served after all that
    stats = running.node._server.stats
    assert stats.malformed_messages == len(bad) - 1   # the bag name is checked by the node
    assert 'expected' in stats.last_malformed
    # an oversized frame closes that connection (max_size); the node serves the next one
    with running.ws() as ws:
        ws.send('x' * 100_000)
        with pytest.raises(Exception):  # noqa: B017 - closed with 1009 by the server
            for _ in range(50):
                ws.recv(timeout=0.2)
    with running.ws() as ws:
        assert recv_until(ws, lambda m, msg: msg['full'])['_full']


def test_cross_origin_websocket_refused(running: Running) -> None:
    with pytest.raises(InvalidStatus, match='403'):
        running.ws(origin='http://evil.example:80')
    port = running.node.port
    with running.ws(origin=f'http://127.0.0.1:{port}') as ws:
        assert recv_until(ws, lambda m, msg: msg['full'])['_full']
    # DNS rebinding: a foreign name pointing at 127.0.0.1, same-origin by its own measure
    with socket.create_connection(('127.0.0.1', port), timeout=5) as s:
        s.sendall(f'GET /ws HTTP/1.1\r\nHost: evil.example:{port}\r\n'
                  f'Origin: http://evil.example:{port}\r\nUpgrade: websocket\r\n'
                  'Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n'
                  'Sec-WebSocket-Version: 13\r\n\r\n'.encode())
        assert s.recv(100).startswith(b'HTTP/1.1 403')


def test_trial_commands_from_the_page(running: Running) -> None:
    with running.ws() as ws:
        recv_until(ws, lambda m, msg: msg['full'])
        ws.send(json.dumps({'type': 'trial', 'action': 'start'}))
        recv_until(ws, lambda m, msg: m.get('trial', {}).get('phase') == 'running')
        ws.send(json.dumps({'type': 'trial', 'action': 'stop'}))
        recv_until(ws, lambda m, msg: m.get('trial', {}).get('phase') == 'stopped')
        ws.send(json.dumps({'type': 'trial', 'action': 'reset'}))
        s = recv_until(ws, lambda m, msg: m.get('trial', {}).get('phase') == 'armed')
        assert s['trial']['elapsed_s'] == 0.0


def test_replay_a_bag_into_the_page_and_back_to_live(running: Running) -> None:
    with running.ws() as ws:
        recv_until(ws, lambda m, msg: msg['full'])
        ws.send(json.dumps({'type': 'replay', 'action': 'start', 'bag': 'fixtures/cgail_trial',
                            'rate': 10.0}))
        s = recv_until(ws, lambda m, msg: m['_source'] == 'replay' and 'path' in m
                       and m.get('tip', {}).get('seq', 0) > 20 and 'target' in m)
        assert len(s['path']['points']) == 40
        assert s['replay']['bag'] == 'fixtures/cgail_trial'
        s = recv_until(ws, lambda m, msg: m.get('replay', {}).get('phase') == 'finished',
                       timeout=15)
        assert s['trial']['phase'] == 'reached'           # the fixture reaches its target
        ws.send(json.dumps({'type': 'replay', 'action': 'stop'}))
        live = recv_until(ws, lambda m, msg: msg['full'] and m['_source'] == 'live')
        assert 'path' not in live                          # nothing was published live
        ws.send(json.dumps({'type': 'replay', 'action': 'start', 'bag': 'no/such', 'rate': 1}))
        s = recv_until(ws, lambda m, msg: m.get('replay', {}).get('phase') == 'error')
        assert 'no bag named' in s['replay']['message']


def test_port_in_use_is_an_error_not_a_crash(ros: None) -> None:
    blocker = socket.socket()
    blocker.bind(('127.0.0.1', 0))
    blocker.listen(1)
    port = blocker.getsockname()[1]
    node = GuiNode(parameter_overrides=[Parameter('port', value=port),
                                        Parameter('anatomy', value='')])
    got: list[DiagnosticArray] = []
    sub = rclpy.create_node('gui_diag_listener')
    sub.create_subscription(DiagnosticArray, '/diagnostics', got.append, 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(sub)
    try:
        assert node.port is None
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not any(
                s.name == 'gui: guidance page' for m in got for s in m.status):
            executor.spin_once(timeout_sec=0.1)
        status = next(s for m in got for s in m.status if s.name == 'gui: guidance page')
        assert status.level == DiagnosticStatus.ERROR
        assert 'cannot serve' in status.message
        blocker.close()
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and node.port is None:
            executor.spin_once(timeout_sec=0.1)
        assert node.port == port                            # retried and bound once free
    finally:
        blocker.close()
        executor.shutdown()
        node.destroy_node()
        sub.destroy_node()


def test_dynamic_mode_draws_the_phantoms_deforming_wall(ros: None) -> None:
    """The page's wall is the phantom's lumen marker (phantom/lumen), not a heartbeat of the
    GUI's own: its mesh replaces the anatomy's rest mesh and its vertices stream as deform
    frames that move with the phantom's wall."""
    import base64

    import numpy as np

    from cgail_rig.nodes.phantom_node import PhantomNode

    phantom = PhantomNode(parameter_overrides=[
        Parameter('mode', value='dynamic'), Parameter('lumen_rate_hz', value=10.0),
        Parameter('simulate_aurora', value=False), Parameter('simulate_regulators', value=False),
        Parameter('simulate_driver', value=False)])
    lumen_vertices = len(np.unique(phantom.lumen.faces))      # 2420 (the mesh has 2455)

    def frame(s: dict[str, Any], item: str) -> np.ndarray:
        return np.frombuffer(base64.b64decode(s[item]['vertices']), '<f4').reshape(-1, 3)

    r = Running(phantom, cli_args=['--ros-args', '-r', '~/wall_markers:=phantom/lumen'],
                anatomy='default', dynamic=True, mesh_rate_hz=20.0)
    try:
        with r.ws() as ws:
            s = recv_until(ws, lambda m, msg: m.get('mesh', {}).get('vertex_count')
                           == lumen_vertices and 'deform' in m, timeout=60)
            mesh = frame(s, 'mesh')
            assert s['mesh']['face_count'] == len(phantom.lumen.faces)
            t1, first = s['deform']['t'], frame(s, 'deform')
            assert first.shape == mesh.shape
            s = recv_until(ws, lambda m, msg: m['deform']['t'] > t1 + 0.2 and np.abs(
                frame(m, 'deform') - first).max() > 0.001, timeout=30)
            moved = np.linalg.norm(frame(s, 'deform') - first, axis=1)
            assert moved.max() > 0.001                      # the root moves by millimetres
            assert np.median(moved) < 0.001                 # the descending aorta barely
        # the rays hit the phantom's wall
        assert type(r.node._model._wall).__name__ == 'MeshWall'
    finally:
        r.close()

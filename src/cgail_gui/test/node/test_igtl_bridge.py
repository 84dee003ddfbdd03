"""igtl_bridge in-process, with a pyigtl client as 3D Slicer: each message type arrives in the
CT frame (RAS mm), nothing is queued without a client, a new client gets the whole picture, and
the server thread stops with the node."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
import socket
import time

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg
import numpy as np
import pyigtl
import pyigtl.messages
import pytest
import rclpy
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray
import yaml

from cgail_gui.core import igtl
from cgail_gui.hw import igtl_server as srv
from cgail_gui.nodes.igtl_bridge import IgtlBridge
from cgail_node_utils.testing import spin_until
from cgail_planner.core.markers import LumenMesh
from cgail_planner.nodes import conversions as conv
from cgail_sim.anatomy_spec import resolve_anatomy

TIMEOUT = 30.0
RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0])
TIP_POSITION = np.array([0.004, -0.012, -0.085])
TIP_ROTATION = Rotation.from_euler('xyz', [20.0, -35.0, 110.0], degrees=True).as_matrix()
CT_T = np.array([12.5, -140.0, 1020.25])  # the prepared anatomy's record: t_input_mm


@pytest.fixture(autouse=True)
def polydata_decoder(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(pyigtl.messages.message_type_to_class_constructor, 'POLYDATA',
                        srv.PolyDataReader)


class Rig:
    """The bridge, a probe node publishing like the rig, an executor and pyigtl clients."""

    def __init__(self, **params) -> None:
        self.node = IgtlBridge(parameter_overrides=[
            Parameter(k, value=v) for k, v in {'port': 0, **params}.items()])
        self.probe = rclpy.create_node('probe')
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.tip_pub = self.probe.create_publisher(PoseStamped, '/igtl_bridge/tip_pose',
                                                   conv.SENSOR_QOS)
        self.path_pub = self.probe.create_publisher(PathMsg, '/igtl_bridge/path', conv.LATCHED_QOS)
        self.goal_pub = self.probe.create_publisher(PoseStamped, '/igtl_bridge/goal',
                                                    conv.COMMAND_QOS)
        self.markers_pub = self.probe.create_publisher(MarkerArray, '/igtl_bridge/wall_markers',
                                                       conv.LATCHED_QOS)
        self.tip_stamp = self.probe.get_clock().now().to_msg()
        self.probe.create_timer(0.025, lambda: self.tip_pub.publish(conv.pose_msg(
            self.tip_stamp, 'phantom', TIP_POSITION, TIP_ROTATION)))  # 40 Hz, as the Aurora
        self.clients: list[pyigtl.OpenIGTLinkClient] = []
        self.got: dict[str, pyigtl.MessageBase] = {}

    def connect(self) -> pyigtl.OpenIGTLinkClient:
        client = pyigtl.OpenIGTLinkClient(host='127.0.0.1', port=self.node.server.port)
        self.clients.append(client)
        self.got = {}
        return client

    def receive(self, device: str, predicate: Callable[[pyigtl.MessageBase], bool] = bool,
                ) -> pyigtl.MessageBase:
        """Spin until the newest client has a new message of ``device`` that passes."""
        client = self.clients[-1]
        self.got.pop(device, None)

        def arrived() -> bool:
            message = client.wait_for_message(device, timeout=0)
            if message is not None and predicate(message):
                self.got[device] = message
            return device in self.got

        assert spin_until(self.executor, arrived), f'no {device} message within {TIMEOUT} s'
        return self.got[device]

    def close(self) -> None:
        for client in self.clients:
            client.stop()
        self.executor.shutdown()
        self.node.destroy_node()
        self.probe.destroy_node()


@pytest.fixture
def rig(ros) -> Iterator[Rig]:
    r = Rig()
    try:
        yield r
    finally:
        r.close()


def goal_msg(point: np.ndarray) -> PoseStamped:
    msg = PoseStamped(header=Header(frame_id='phantom'))
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in point)
    msg.pose.orientation.w = 1.0
    return msg


def check_tip(message: pyigtl.MessageBase, rotation_ct: np.ndarray, position_ct_mm: np.ndarray,
              ) -> None:
    """The TRANSFORM against the published tip, within 1e-6 (rotation; translation in m: the
    wire carries float32 millimetres)."""
    assert message.message_type == 'TRANSFORM'
    matrix = np.asarray(message.matrix, dtype=np.float64)
    assert matrix[:3, :3] == pytest.approx(rotation_ct, abs=1e-6)
    assert matrix[:3, 3] / 1000.0 == pytest.approx(position_ct_mm / 1000.0, abs=1e-6)
    assert matrix[3].tolist() == [0.0, 0.0, 0.0, 1.0]


def test_builtin_anatomy_streams_every_message_type(rig: Rig) -> None:
    anatomy = resolve_anatomy('default')
    # no client: poses come in and nothing is queued
    assert spin_until(rig.executor, lambda: rig.node.tip is not None)
    end = time.monotonic() + 0.5
    spin_until(rig.executor, lambda: time.monotonic() > end)
    assert rig.node.server.queued == 0 and not rig.node.server.connected

    rig.connect()
    lumen = rig.receive(igtl.LUMEN_DEVICE)
    assert lumen.points.shape == (len(anatomy.vertices), 3)  # (2455 on AVX-512 numpy)
    assert lumen.points == pytest.approx(anatomy.vertices * 1000.0 @ RAS_FROM_LPS, abs=1e-4)
    assert lumen.polygons.reshape(-1, 4)[:, 1:].tolist() == anatomy.faces.tolist()
    assert (lumen.polygons.reshape(-1, 4)[:, 0] == 3).all()
    assert len(lumen.lines) == 0

    check_tip(rig.receive(igtl.TIP_DEVICE), RAS_FROM_LPS @ TIP_ROTATION,
              RAS_FROM_LPS @ TIP_POSITION * 1000.0)
    assert rig.got[igtl.TIP_DEVICE].timestamp == pytest.approx(
        conv.stamp_seconds(rig.tip_stamp), abs=1e-6)

    path = np.column_stack([np.linspace(0.0, 0.01, 7), np.linspace(0.0, -0.02, 7),
                            np.linspace(-0.1, -0.05, 7)])
    rig.path_pub.publish(conv.path_msg(rig.probe.get_clock().now().to_msg(), 'phantom', path))
    planned = rig.receive(igtl.PATH_DEVICE)
    assert planned.points == pytest.approx(path * 1000.0 @ RAS_FROM_LPS, abs=1e-4)
    assert planned.lines.tolist() == [7, 0, 1, 2, 3, 4, 5, 6]
    assert len(planned.polygons) == 0

    rig.goal_pub.publish(goal_msg(np.array([0.011, -0.006, 0.018])))
    target = rig.receive(igtl.TARGET_DEVICE)
    assert target.names == ['target']
    assert np.asarray(target.positions[0]) == pytest.approx([-11.0, 6.0, 18.0], abs=1e-4)


def test_moved_wall_is_sent_and_a_new_client_gets_the_picture_again(rig: Rig) -> None:
    anatomy = resolve_anatomy('default')
    rig.connect()
    rig.receive(igtl.LUMEN_DEVICE)
    moved = anatomy.vertices + np.array([0.0, 0.0, 0.002])  # the wall 2 mm cranial
    marker = LumenMesh(anatomy).marker(moved)
    rig.markers_pub.publish(conv.marker_array_msg(rig.probe.get_clock().now().to_msg(),
                                                  'phantom', [marker]))
    rest_z_mm = 1000.0 * anatomy.vertices[:, 2].mean()
    lumen = rig.receive(igtl.LUMEN_DEVICE, lambda m: m.points[:, 2].mean() > rest_z_mm + 1.0)
    wall = np.unique(anatomy.faces[anatomy.wall_face_mask])
    assert lumen.points[wall] == pytest.approx(moved[wall] * 1000.0 @ RAS_FROM_LPS, abs=1e-4)
    # the first client leaves, a second one gets the lumen (as it now is) and the tip at once
    rig.clients[0].stop()
    assert spin_until(rig.executor, lambda: not rig.node.server.connected)
    rig.connect()
    again = rig.receive(igtl.LUMEN_DEVICE)
    assert again.points == pytest.approx(lumen.points)
    rig.receive(igtl.TIP_DEVICE)
    assert rig.node.server.connections == 2


def test_prepared_anatomy_streams_in_its_ct_frame(ros, prepared: Path) -> None:
    anatomy = resolve_anatomy(prepared)
    rec = {'frame_conversion': {'input_frame': 'RAS', 'phantom_from_input':
                                igtl.PREPARE_FORMULA, 'R': np.diag([-1.0, -1.0, 1.0]).tolist(),
                                't_input_mm': CT_T.tolist()},
           'anatomy': {'content_hash': anatomy.content_hash}}
    (prepared / 'prepare.yaml').write_text(yaml.safe_dump(rec))
    r = Rig(anatomy=str(prepared))
    try:
        r.connect()
        # p_ct = R^-1 (1000 p) + t, R = diag(-1, -1, 1)
        check_tip(r.receive(igtl.TIP_DEVICE), RAS_FROM_LPS @ TIP_ROTATION,
                  RAS_FROM_LPS @ TIP_POSITION * 1000.0 + CT_T)
        lumen = r.receive(igtl.LUMEN_DEVICE)
        assert lumen.points.shape == (len(anatomy.vertices), 3)
        assert lumen.points == pytest.approx(anatomy.vertices * 1000.0 @ RAS_FROM_LPS + CT_T,
                                             abs=1e-3)
    finally:
        r.close()
    # a record of another lumen is refused at construction
    rec['anatomy']['content_hash'] = '0' * 16
    (prepared / 'prepare.yaml').write_text(yaml.safe_dump(rec))
    with pytest.raises(igtl.CtFrameError, match='the lumen changed after cgail prepare-anatomy'):
        IgtlBridge(parameter_overrides=[Parameter('anatomy', value=str(prepared)),
                                        Parameter('port', value=0)])


def test_destroy_stops_the_server_and_frees_the_port(ros) -> None:
    node = IgtlBridge(parameter_overrides=[Parameter('port', value=0)])
    server, port = node.server, node.server.port
    client = pyigtl.OpenIGTLinkClient(host='127.0.0.1', port=port)
    try:
        deadline = time.monotonic() + TIMEOUT
        while not server.connected and time.monotonic() < deadline:
            time.sleep(0.01)
        assert server.connected and server.running
        node.destroy_node()
        assert not server.running
        with socket.socket() as s:  # the port is free again (nobody listens there)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(('127.0.0.1', port))
    finally:
        client.stop()


def test_bad_parameters_raise_at_construction(ros) -> None:
    with pytest.raises(InvalidParameterValueException):
        IgtlBridge(parameter_overrides=[Parameter('port', value=70000)])
    with pytest.raises(ValueError, match="host must be an IPv4 or IPv6 address or 'localhost'"):
        IgtlBridge(parameter_overrides=[Parameter('host', value='slicer-pc')])
    with socket.socket() as busy:
        busy.bind(('127.0.0.1', 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(OSError, match=f'expected to listen on 127.0.0.1:{port} for '
                                          'OpenIGTLink, found: Address already in use'):
            IgtlBridge(parameter_overrides=[Parameter('port', value=port)])


def test_yaml_defaults_equal_the_declared_defaults(ros) -> None:
    cfg = Path(__file__).resolve().parents[2] / 'config' / 'igtl_bridge.yaml'
    params = yaml.safe_load(cfg.read_text())['igtl_bridge']['ros__parameters']
    node = IgtlBridge(parameter_overrides=[Parameter('port', value=0)])
    try:
        declared = {name: node.get_parameter(name).value for name in params
                    if name != 'port'}
        assert declared == {k: v for k, v in params.items() if k != 'port'}
        assert params['port'] == igtl.IgtlBridgeConfig().port
        assert node.config.host == '127.0.0.1'
    finally:
        node.destroy_node()

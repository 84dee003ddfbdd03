"""``gui_node``: the guidance page in the browser, live or from a bag (node name ``gui``).

Serves the page (``src/cgail_gui/web``) on ``http://<host>:<port>/`` and streams the state
over a WebSocket at ``/ws`` (:mod:`cgail_gui`): anatomy mesh, planned path, tip pose,
target, next waypoint, suggested bend, diagnostics, trial clock. In dynamic mode the wall is the
phantom's: the ``lumen`` marker of ``phantom/markers`` (the deformed wall, a TRIANGLE_LIST) is
indexed into a mesh once and its vertices are forwarded as deformation frames (at most
``mesh_rate_hz``), and the wall rays hit it; the rest mesh of ``anatomy`` is shown until it
arrives. The node's own topic names are ``~/tip_pose``, ``~/path``, ``~/goal``,
``~/next_waypoint``, ``~/suggested_bend`` and ``~/wall_markers``; the rig's launch files remap
them to the names used here (docs/interfaces.md). The page can replay a bag from
``bags_dir``: the bag player (:class:`~cgail_bags.play.BagPlayer`) publishes into a sink
that decodes the messages and feeds a second model, so a replay never reaches the live topics
and the page switches between the two sources. The server runs asyncio in its own thread; a
port that cannot be bound is an ERROR on ``/diagnostics`` and is retried every 2 s, never a
crash.
"""

from __future__ import annotations

from collections.abc import Callable
import math
from pathlib import Path
import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker, MarkerArray

from cgail_bags.errors import BagError
from cgail_bags.play import BagPlayer, PlayerConfig
from cgail_gui.bags import list_bags
from cgail_gui.config import GuiConfig
from cgail_gui.errors import ServerError
from cgail_gui.model import GuiModel
from cgail_gui.protocol import ClientCommand
from cgail_gui.server import GuiServer
from cgail_gui.state import GuiState
from cgail_gui.static import build_table, find_web_root, missing_vendor
from cgail_node_utils.entry_point import run_node
from cgail_planner.core.markers import LUMEN_NS
from cgail_planner.nodes import conversions as conv
from cgail_sim.mesh_io import AnatomyError

_D = GuiConfig()
# name -> (default, description, range or None)
_PARAMS: dict[str, tuple[Any, str, tuple[float, float] | None]] = {
    'host': (_D.host, 'bind address of the page (IP literal; loopback by default)', None),
    'port': (_D.port, 'TCP port of the page and WebSocket (0: any free port)', (0, 65535)),
    'max_rate_hz': (_D.max_rate_hz, 'highest update rate per page, Hz', (1.0, 240.0)),
    'mesh_rate_hz': (_D.mesh_rate_hz, 'dynamic mode: highest rate of the deformed-wall frames '
                     'forwarded from phantom/markers to the page, Hz', (0.5, 60.0)),
    'anatomy': (_D.anatomy, "anatomy drawn and raycast: a built-in name, a prepared anatomy "
                            "directory or a mesh file ('' = none)", None),
    'dynamic': (_D.dynamic, "the phantom's deforming wall (phantom/markers) streamed to the "
                            'page', None),
    'max_bend_rad': (_D.max_bend_rad, 'reachable tip bend theta_max, rad', (0.01, math.pi / 2)),
    'trial_limit_s': (_D.trial_limit_s, 'trial time limit, s', (1.0, 3600.0)),
    'success_radius_m': (_D.success_radius_m, 'tip-target distance that ends the trial, m',
                         (0.0005, 0.1)),
    'stale_after_s': (_D.stale_after_s, 'tracker shown stale after this long without a pose, s',
                      (0.05, 60.0)),
    'ray_count': (_D.ray_count, 'wall rays on the cone around the heading', (0, 64)),
    'ray_length_m': (_D.ray_length_m, 'wall ray length, m', (0.001, 0.5)),
    'ray_cone_rad': (_D.ray_cone_rad, 'wall ray cone half-angle, rad', (0.0, math.pi / 2)),
    'bags_dir': (_D.bags_dir, "directory of the bags the page may replay ('' = off)", None),
}
_TOPICS = ('em_tracker/tip_pose', 'planner/path', 'planner/goal', 'planner/next_waypoint',
           'planner/suggested_bend', '/diagnostics')
#: The page's live inputs: each topic as the rig names it (and a bag records it, so a replay
#: feeds it by that name) -> the node's own name, which the rig's launch files remap to it.
_OWN_NAMES = {'em_tracker/tip_pose': '~/tip_pose', 'planner/path': '~/path',
              'planner/goal': '~/goal', 'planner/next_waypoint': '~/next_waypoint',
              'planner/suggested_bend': '~/suggested_bend', '/diagnostics': '/diagnostics'}
_LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
_COMMAND = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
_RETRY_BIND_S = 2.0


def _descriptor(description: str, bounds: tuple[float, float] | None,
                default: Any) -> ParameterDescriptor:
    desc = ParameterDescriptor(description=description)
    if bounds is not None and isinstance(default, int) and not isinstance(default, bool):
        desc.integer_range = [IntegerRange(from_value=int(bounds[0]), to_value=int(bounds[1]),
                                           step=1)]
    elif bounds is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=float(bounds[0]),
                                                        to_value=float(bounds[1]), step=0.0)]
    return desc


def _stamp(msg: Any) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


class _Feed:
    """Message -> model adapters, shared by the live subscriptions and the replay sink."""

    def __init__(self, model: GuiModel, warn: Callable[[str], None],
                 now: Callable[[], float]) -> None:
        self.model = model
        self._warn = warn
        self._now = now

    def handlers(self) -> dict[str, Callable[[Any], None]]:
        return {'em_tracker/tip_pose': self.tip, 'planner/path': self.path,
                'planner/goal': self.goal, 'planner/next_waypoint': self.waypoint,
                'planner/suggested_bend': self.bend, '/diagnostics': self.diagnostics}

    def _guard(self, what: str, fn: Callable[[], None]) -> None:
        try:
            fn()
        except ValueError as exc:
            self._warn(f'ignored {what}: {exc}')

    def tip(self, msg: PoseStamped) -> None:
        p, o = msg.pose.position, msg.pose.orientation
        self._guard('tip pose', lambda: self.model.on_tip(
            np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w]), _stamp(msg),
            self._now()))

    def path(self, msg: PathMsg) -> None:
        pts = np.array([[s.pose.position.x, s.pose.position.y, s.pose.position.z]
                        for s in msg.poses], dtype=float).reshape(-1, 3)
        self._guard('path', lambda: self.model.on_path(pts, msg.header.frame_id))

    def goal(self, msg: PoseStamped) -> None:
        p = msg.pose.position
        self._guard('goal', lambda: self.model.on_goal(np.array([p.x, p.y, p.z]),
                                                       msg.header.frame_id))

    def waypoint(self, msg: PointStamped) -> None:
        p = msg.point
        self._guard('next waypoint', lambda: self.model.on_waypoint(np.array([p.x, p.y, p.z])))

    def bend(self, msg: JointState) -> None:
        names = list(msg.name)
        if 'bend_alpha' not in names or 'bend_gamma' not in names \
                or len(msg.position) != len(names):
            self._warn(f'ignored suggested bend: expected positions for bend_alpha and '
                       f'bend_gamma, found names {names[:4]} with {len(msg.position)} positions')
            return
        a = msg.position[names.index('bend_alpha')]
        g = msg.position[names.index('bend_gamma')]
        self._guard('suggested bend', lambda: self.model.on_bend(a, g))

    def diagnostics(self, msg: DiagnosticArray) -> None:
        self.model.on_diagnostics(
            {'name': s.name, 'level': int.from_bytes(s.level, 'little')
             if isinstance(s.level, bytes) else int(s.level), 'message': s.message,
             'hardware_id': s.hardware_id, 'values': {kv.key: kv.value for kv in s.values}}
            for s in msg.status)


class _SinkPublisher:
    """Stands in for a publisher of the bag player: decodes and feeds the replay model."""

    def __init__(self, msg_class: Any, handler: Callable[[Any], None] | None) -> None:
        self._cls, self._handler = msg_class, handler

    def publish(self, raw: bytes) -> None:
        if self._handler is not None:
            self._handler(deserialize_message(raw, self._cls))

    def get_subscription_count(self) -> int:
        return 1


class _ReplaySink:
    """The 'node' the bag player publishes through (create_publisher + get_logger)."""

    def __init__(self, node: Node, handlers: dict[str, Callable[[Any], None]]) -> None:
        self._node = node
        self._handlers = {'/' + k.lstrip('/'): v for k, v in handlers.items()}

    def create_publisher(self, msg_class: Any, topic: str, qos: Any) -> _SinkPublisher:
        return _SinkPublisher(msg_class, self._handlers.get('/' + topic.lstrip('/')))

    def get_logger(self) -> Any:
        return self._node.get_logger()


class GuiNode(Node):
    """Guidance page server; see the module docstring."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('gui', **kwargs)
        for name, (default, description, bounds) in _PARAMS.items():
            self.declare_parameter(name, default, _descriptor(description, bounds, default))
        values = {name: self.get_parameter(name).value for name in _PARAMS}
        try:
            self.config = GuiConfig(**values)
            # a path is read here (a bad mesh ends the node); the wall is built in a thread
            self._anatomy_source = self._resolve_anatomy()
        except AnatomyError:
            super().destroy_node()
            raise
        self._web_root = find_web_root()
        files = build_table(self._web_root)
        self._missing = missing_vendor(files)
        if self._missing:
            self.get_logger().error(f'three.js is not installed ({self._missing} missing): run '
                                    f'npm ci in {self._web_root}; the 3D views will not load')
        self._live = GuiState()
        self._model = GuiModel(self.config, self._live, clock='wall')
        self._feed = _Feed(self._model, self._warn, self._now)
        self._server = GuiServer(self.config, files, self._on_command, self._log)
        self._live.on_change = lambda: self._server.notify_from(self._live)
        self._server.set_source('live', self._live)
        self._bags = list_bags(self.config.bags_dir)
        self._replay: dict[str, Any] = {}
        self._replay_lock = threading.Lock()
        self._warned: dict[str, float] = {}
        self._set_replay_item(None, 'idle', '')
        qos: dict[str, QoSProfile | int] = {
            'em_tracker/tip_pose': qos_profile_sensor_data, 'planner/path': _LATCHED,
            'planner/goal': _COMMAND, 'planner/next_waypoint': qos_profile_sensor_data,
            'planner/suggested_bend': qos_profile_sensor_data, '/diagnostics': 10}
        types = {'em_tracker/tip_pose': PoseStamped, 'planner/path': PathMsg,
                 'planner/goal': PoseStamped, 'planner/next_waypoint': PointStamped,
                 'planner/suggested_bend': JointState, '/diagnostics': DiagnosticArray}
        for topic, handler in self._feed.handlers().items():
            self.create_subscription(types[topic], _OWN_NAMES[topic], handler, qos[topic])
        self._last_lumen = -math.inf
        if self.config.dynamic:
            self.create_subscription(MarkerArray, '~/wall_markers', self._on_markers, _LATCHED)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._bind_error = ''
        self._next_bind = 0.0
        self._try_bind()
        self._timer = self.create_timer(1.0, self._on_timer)
        self._anatomy_thread = threading.Thread(target=self._load_anatomy, name='gui_anatomy',
                                                daemon=True)
        self._anatomy_thread.start()

    # -- plumbing ------------------------------------------------------------------------------
    @property
    def port(self) -> int | None:
        """The bound TCP port (None while not serving)."""
        return self._server.port if not self._bind_error else None

    @property
    def url(self) -> str:
        """Address of the page."""
        host = self.config.host
        return f'http://{f"[{host}]" if ":" in host else host}:{self.port}/'

    def _now(self) -> float:
        """The node's clock in s: ROS time, so the trial clock follows /clock under
        use_sim_time (an accelerated simulated session)."""
        return self.get_clock().now().nanoseconds * 1e-9

    def _log(self, level: str, text: str) -> None:
        # one call site per severity: rclpy refuses a severity change at the same call site
        if level == 'error':
            self.get_logger().error(text)
        elif level == 'warn':
            self.get_logger().warning(text)
        else:
            self.get_logger().info(text)

    def _warn(self, text: str) -> None:
        key = text[:40]
        now = time.monotonic()
        if now - self._warned.get(key, -1e9) >= 5.0:
            self._warned[key] = now
            self.get_logger().warning(text)

    def _try_bind(self) -> None:
        try:
            self._server.start()
        except ServerError as exc:
            self._bind_error = str(exc)
            self._next_bind = time.monotonic() + _RETRY_BIND_S
            self.get_logger().error(f'{exc}; retrying every {_RETRY_BIND_S:g} s')
            return
        self._bind_error = ''
        self.get_logger().info(f'guidance page on {self.url} (anatomy '
                               f'{self.config.anatomy or "none"}, '
                               f'{"dynamic" if self.config.dynamic else "static"})')

    def _resolve_anatomy(self) -> Any:
        """The configured anatomy (None: none). A built-in one is built (or read from the disk
        cache) in the loading thread; a path is read now, so a bad mesh fails construction."""
        from cgail_sim.anatomy_spec import is_builtin, resolve_anatomy

        spec = self.config.anatomy
        if not spec or is_builtin(spec):
            return spec or None
        return resolve_anatomy(spec)

    def _load_anatomy(self) -> None:
        if self._anatomy_source is None:
            return
        from cgail_sim.anatomy_spec import resolve_anatomy
        from cgail_sim.wall import StaticWall
        try:
            anatomy = resolve_anatomy(self._anatomy_source)
            wall = StaticWall(anatomy)
            wall.raycast(anatomy.start_point[None, :], anatomy.start_direction[None, :], 0.01)
        except (AnatomyError, ValueError, OSError) as exc:
            self.get_logger().error(f'cannot load anatomy {self.config.anatomy!r}: {exc}')
            return
        faces = anatomy.faces[anatomy.wall_face_mask]
        self._anatomy = (anatomy.name, anatomy.vertices, faces, wall)
        self._model.set_anatomy(anatomy.name, anatomy.vertices, faces, wall)
        with self._replay_lock:
            model = self._replay.get('model')
        if model is not None:
            model.set_anatomy(anatomy.name, anatomy.vertices, faces, wall)

    def _on_markers(self, msg: MarkerArray) -> None:
        """Dynamic mode: the phantom's deformed wall (its ``lumen`` marker) to the live page."""
        lumen = next((m for m in msg.markers if m.ns == LUMEN_NS and m.action == Marker.ADD
                      and m.type == Marker.TRIANGLE_LIST), None)
        now = time.monotonic()
        if lumen is None or now - self._last_lumen < 0.999 / self.config.mesh_rate_hz:
            return
        self._last_lumen = now
        if lumen.header.frame_id not in ('', 'phantom'):
            self._warn(f"ignored lumen marker: expected frame 'phantom', found "
                       f'{lumen.header.frame_id!r}')
            return
        try:
            self._model.set_lumen(conv.marker_points(lumen), _stamp(lumen))
        except ValueError as exc:
            self._warn(f'ignored lumen marker: {exc}')

    # -- timer ------------------------------------------------------------------------------
    def _on_timer(self) -> None:
        if self._bind_error and time.monotonic() >= self._next_bind:
            self._try_bind()
        self._model.tick(self._now())
        self._diag_pub.publish(self._diagnostics())

    def _diagnostics(self) -> DiagnosticArray:
        s = self._server.stats
        status = DiagnosticStatus(name='gui: guidance page', hardware_id=f'gui:{self.url}')
        if self._bind_error:
            status.level, status.message = DiagnosticStatus.ERROR, self._bind_error[:200]
        elif self._missing:
            status.level, status.message = DiagnosticStatus.WARN, 'three.js missing: npm ci'
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'serving {s.clients} page(s), source {self._server.source}'
        values = {'url': self.url, 'clients': s.clients, 'connections_total':
                  s.connections_total, 'messages_sent': s.messages_sent,
                  'malformed_messages': s.malformed_messages, 'last_malformed': s.last_malformed,
                  'http_not_found': s.http_not_found, 'source': self._server.source,
                  'anatomy': self.config.anatomy, 'dynamic': self.config.dynamic}
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        return msg

    # -- page commands (server thread) ---------------------------------------------------------
    def _on_command(self, command: ClientCommand) -> None:
        if command.kind == 'trial':
            with self._replay_lock:
                model = self._replay.get('model') if self._server.source == 'replay' else None
            (model or self._model).trial_command(command.action, self._now())
        elif command.kind == 'replay' and command.action == 'stop':
            self._stop_replay()
        elif command.kind == 'replay':
            self._start_replay(command)

    def _set_replay_item(self, bag: str | None, phase: str, message: str,
                         rate: float = 1.0) -> None:
        item = {'bags': sorted(self._bags), 'bag': bag, 'phase': phase, 'message': message,
                'rate': rate}
        self._live.set('replay', item)
        with self._replay_lock:
            state = self._replay.get('state')
        if state is not None:
            state.set('replay', item)

    def _start_replay(self, command: ClientCommand) -> None:
        self._stop_replay(switch_live=False)
        self._bags = list_bags(self.config.bags_dir)
        path = self._bags.get(command.bag)
        if path is None:
            self._warn(f'ignored replay of {command.bag!r}: expected one of {sorted(self._bags)}')
            self._set_replay_item(None, 'error', f'no bag named {command.bag!r}')
            return
        state = GuiState()
        model = GuiModel(self.config, state, clock='stamp')
        anatomy = getattr(self, '_anatomy', None)
        if anatomy is not None:
            model.set_anatomy(*anatomy)
        feed = _Feed(model, self._warn, self._now)
        try:
            player = BagPlayer(_ReplaySink(self, feed.handlers()),
                               PlayerConfig(bag=Path(path), rate=command.rate, loop=command.loop,
                                            topics=tuple('/' + t.lstrip('/') for t in _TOPICS)))
        except (BagError, ValueError) as exc:
            self.get_logger().error(f'cannot replay {command.bag}: {exc}')
            self._set_replay_item(None, 'error', str(exc)[:200])
            return
        stop = threading.Event()
        thread = threading.Thread(target=self._run_replay, args=(player, stop, command),
                                  name='gui_replay', daemon=True)
        with self._replay_lock:
            self._replay = {'state': state, 'model': model, 'stop': stop, 'thread': thread}
        state.on_change = lambda: self._server.notify_from(state)
        self._set_replay_item(command.bag, 'playing', '', command.rate)
        self._server.set_source('replay', state)
        self.get_logger().info(f'replaying {path} at rate {command.rate:g} on the page')
        thread.start()

    def _run_replay(self, player: BagPlayer, stop: threading.Event,
                    command: ClientCommand) -> None:
        try:
            count = player.play(stop)
        except BagError as exc:
            self.get_logger().error(f'replay of {command.bag} failed: {exc}')
            self._set_replay_item(command.bag, 'error', str(exc)[:200], command.rate)
            return
        if not stop.is_set():
            self._set_replay_item(command.bag, 'finished', f'{count} messages', command.rate)

    def _stop_replay(self, switch_live: bool = True) -> None:
        with self._replay_lock:
            replay, self._replay = self._replay, {}
        if replay:
            replay['stop'].set()
            replay['thread'].join(2.0)
        if switch_live:
            self._server.set_source('live', self._live)
            self._set_replay_item(None, 'idle', '')

    def destroy_node(self) -> None:
        """Stop the replay and the server, then the node."""
        with self._replay_lock:
            replay, self._replay = self._replay, {}
        if replay:
            replay['stop'].set()
            replay['thread'].join(2.0)
        self._server.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run ``gui_node``."""
    run_node(GuiNode, 'gui_node', args, fatal=(AnatomyError,))


if __name__ == '__main__':
    main()

"""OpenIGTLink bridge (``igtl_bridge``): the tip, the plan and the lumen for 3D Slicer.

Run: ``ros2 run cgail_gui igtl_bridge --ros-args -p anatomy:=DIR`` (pip-only:
``scripts/ros2run cgail_gui igtl_bridge ...``), then in Slicer's OpenIGTLinkIF module add a
client connector to ``localhost:18944``. What is sent, in which frame and why:
:mod:`cgail_gui.core.igtl`; the server: :mod:`cgail_gui.hw.igtl_server`. Its topics
are its own, under its name (``~/tip_pose``, ``~/path``, ``~/goal``, ``~/wall_markers``); below
they are named as in the rig, whose launch files remap them (docs/interfaces.md).

* ``em_tracker/tip_pose`` (PoseStamped, frame ``phantom``) -> TRANSFORM ``CatheterTip``, the
  newest pose at most ``tip_rate_hz`` times a second, stamped with the pose's stamp;
* ``planner/path`` (nav_msgs/Path) -> POLYDATA ``PlannedPath`` (one polyline), on change;
* ``planner/goal`` (PoseStamped) -> POINT ``Target``, on change;
* the ``anatomy``'s lumen -> POLYDATA ``Lumen`` (every vertex and triangle of the mesh); with
  ``follow_wall``, the wall of ``phantom/markers`` (deformed in dynamic mode) when it moved.

A client that connects gets the lumen, the path and the target at once, then the stream.
Without a client nothing is queued. Messages in a frame other than ``frame_id`` are ignored
(with a throttled warning). Publishes nothing.
"""

from __future__ import annotations

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
import numpy as np
from rclpy.clock import Clock, ClockType
from visualization_msgs.msg import MarkerArray

from cgail_gui.core import igtl
from cgail_gui.hw import igtl_server as srv
from cgail_gui.nodes.server_node import ServerNode
from cgail_node_utils.entry_point import run_node
from cgail_planner.core.errors import InvalidInputError
from cgail_planner.core.markers import LUMEN_NS
from cgail_planner.nodes import conversions as conv
from cgail_sim.mesh_io import AnatomyError


class IgtlBridge(ServerNode):
    """Thin wrapper: messages in, :mod:`cgail_gui.core.igtl` arrays, pyigtl messages out."""

    def __init__(self, **kwargs) -> None:
        super().__init__('igtl_bridge', **kwargs)
        d = igtl.IgtlBridgeConfig()
        self.config = igtl.IgtlBridgeConfig(
            host=conv.declare(self, 'host', d.host, 'address the OpenIGTLink server listens '
                              'on (127.0.0.1: this machine only)'),
            port=conv.declare(self, 'port', d.port, "TCP port (18944: Slicer's default; 0: "
                              'any free port, logged)', lo=0, hi=65535),
            tip_rate_hz=conv.declare(self, 'tip_rate_hz', d.tip_rate_hz,
                                     'largest rate of the CatheterTip TRANSFORM, Hz',
                                     lo=1.0, hi=200.0),
            follow_wall=conv.declare(self, 'follow_wall', d.follow_wall, 'send the lumen '
                                     'again when phantom/markers shows the wall moved'))
        spec = conv.declare(self, 'anatomy', 'default', "the anatomy: a built-in name "
                            "('default', 'elongated'), a prepared anatomy directory or a mesh "
                            'file')
        self.frame_id = conv.declare(self, 'frame_id', 'phantom', 'frame of the inputs')

        from cgail_sim.anatomy_spec import resolve_anatomy

        try:
            anatomy = resolve_anatomy(spec)
            self.ct = igtl.ct_frame_of(spec, anatomy.content_hash)
        except (AnatomyError, igtl.CtFrameError):
            super().destroy_node()  # (no server started yet)
            raise
        self.rest = np.asarray(anatomy.vertices, dtype=np.float64)
        self.wall_faces = np.asarray(anatomy.faces)[np.asarray(anatomy.wall_face_mask)]
        self.lumen_cells = igtl.polygon_cells(anatomy.faces)
        self.lumen = self.rest
        self.tip: tuple[float, np.ndarray] | None = None
        self.path: tuple[float, np.ndarray] | None = None
        self.goal: tuple[float, np.ndarray] | None = None
        self._dirty: set[str] = set()
        self._seen_connections = 0
        self._wall_refused = False

        try:
            self.server = srv.IgtlServer(self.config.host, self.config.port)
        except OSError as exc:
            super().destroy_node()
            raise OSError(exc.errno, f'expected to listen on {self.config.host}:'
                          f'{self.config.port} for OpenIGTLink, found: {exc.strerror}') from None
        self.create_subscription(PoseStamped, '~/tip_pose', self._on_tip, conv.SENSOR_QOS)
        self.create_subscription(Path, '~/path', self._on_path, conv.LATCHED_QOS)
        self.create_subscription(PoseStamped, '~/goal', self._on_goal, conv.COMMAND_QOS)
        if self.config.follow_wall:
            self.create_subscription(MarkerArray, '~/wall_markers', self._on_markers,
                                     conv.LATCHED_QOS)
        # (a viewer: wall-clock pacing even when the rig runs on simulated time)
        self.create_timer(1.0 / self.config.tip_rate_hz, self._on_tick,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'OpenIGTLink server on {self.config.host}:{self.server.port}; '
            f'{len(self.rest)}-vertex lumen of {spec}; CT frame (RAS mm) from {self.ct.source}')

    # ------------------------------------------------------------------ inputs
    def _frame_ok(self, frame_id: str, topic: str) -> bool:
        if frame_id == self.frame_id:
            return True
        self.get_logger().warning(f'{topic} ignored: expected frame {self.frame_id!r}, found '
                                  f'{frame_id!r}', throttle_duration_sec=5.0)
        return False

    def _on_tip(self, msg: PoseStamped) -> None:
        if not self._frame_ok(msg.header.frame_id, 'em_tracker/tip_pose'):
            return
        try:
            position, rotation = conv.pose_from_msg(msg)
        except InvalidInputError as exc:
            self.get_logger().warning(f'tip pose ignored: {exc}', throttle_duration_sec=5.0)
            return
        self.tip = (conv.stamp_seconds(msg.header.stamp),
                    self.ct.pose_mm(position, rotation))
        self._dirty.add('tip')

    def _on_path(self, msg: Path) -> None:
        if not self._frame_ok(msg.header.frame_id, 'planner/path'):
            return
        self.path = (conv.stamp_seconds(msg.header.stamp),
                     self.ct.points_mm(conv.path_points(msg)))
        self._dirty.add('path')

    def _on_goal(self, msg: PoseStamped) -> None:
        if not self._frame_ok(msg.header.frame_id, 'planner/goal'):
            return
        goal = conv.point_from_pose_msg(msg)
        if np.isfinite(goal).all():
            self.goal = (conv.stamp_seconds(msg.header.stamp), self.ct.points_mm(goal))
            self._dirty.add('goal')

    def _on_markers(self, msg: MarkerArray) -> None:
        if not self.server.connected:
            return
        marker = next((m for m in msg.markers if m.ns == LUMEN_NS and m.id == 0), None)
        if marker is None or not self._frame_ok(msg.markers[0].header.frame_id,
                                                'phantom/markers'):
            return
        wall = igtl.wall_from_triangles(self.rest, self.wall_faces, conv.marker_points(marker))
        if wall is None:
            if not self._wall_refused:
                self._wall_refused = True
                self.get_logger().warning(
                    f'phantom/markers lumen ({len(marker.points)} points) is not the wall of '
                    f'this anatomy ({3 * len(self.wall_faces)} points: decimated, or another '
                    'anatomy): the lumen stays at rest')
            return
        if not np.array_equal(wall, self.lumen):
            self.lumen = wall
            self._dirty.add('lumen')

    # ------------------------------------------------------------------ output
    def _on_tick(self) -> None:
        if not self.server.connected:
            return
        connections = self.server.connections
        if connections != self._seen_connections:  # a new client: the whole picture
            self._seen_connections = connections
            self.get_logger().info(f'OpenIGTLink client {self.server.client} connected')
            self._dirty |= {'lumen', 'path', 'goal', 'tip'}
        now = self.get_clock().now().nanoseconds * 1e-9
        if 'lumen' in self._dirty:
            self.server.send(srv.polydata_message(igtl.LUMEN_DEVICE,
                                                  self.ct.points_mm(self.lumen), now,
                                                  polygons=self.lumen_cells))
        if 'path' in self._dirty and self.path is not None:
            stamp, points = self.path
            self.server.send(srv.polydata_message(igtl.PATH_DEVICE, points, stamp,
                                                  lines=igtl.line_cells(len(points))))
        if 'goal' in self._dirty and self.goal is not None:
            stamp, point = self.goal
            self.server.send(srv.point_message(igtl.TARGET_DEVICE, point, ['target'], stamp))
        if 'tip' in self._dirty and self.tip is not None:
            stamp, matrix = self.tip
            self.server.send(srv.transform_message(igtl.TIP_DEVICE, matrix, stamp))
        self._dirty.clear()


def main(args: list[str] | None = None) -> None:
    """Console script ``igtl_bridge``."""
    run_node(IgtlBridge, 'igtl_bridge', args, fatal=(AnatomyError, igtl.CtFrameError, OSError))


if __name__ == '__main__':
    main()

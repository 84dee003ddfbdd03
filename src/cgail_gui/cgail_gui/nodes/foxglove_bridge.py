"""Live Foxglove view (``foxglove_bridge``): the rig's topics over the Foxglove WebSocket protocol.

Run: ``ros2 run cgail_gui foxglove_bridge`` (pip-only: ``scripts/ros2run cgail_gui
foxglove_bridge ...``; the rig's launch files start it, ``cgail session --foxglove`` too), then
in the Foxglove app *Open connection* -> *Foxglove WebSocket* -> ``ws://localhost:8765`` and
import the layout ``cgail_rig/config/foxglove/cgail_layout.json``.

It serves the topics of :data:`cgail_gui.core.foxglove_view.STREAMS` (the tip pose and its
covariance, ``/tf`` and ``/tf_static``, both marker arrays, the path and the goal, the
guidance, the PAM pressures, the bend and insertion states and ``/diagnostics``) under their
rig names, each a ros2msg/cdr channel whose messages are the bytes as published (raw
subscriptions: nothing is decoded). A client that subscribes gets the latched state kept for it
(the markers, the path, the goal, the static transforms) within ``0.1`` s. Each message is
stamped with the node clock at arrival: the simulated time in ``cgail session``, as the
messages' own stamps.

The server listens on ``127.0.0.1`` unless ``host`` says otherwise, and refuses an address
other machines reach unless ``allow_remote`` is true: the protocol has no authentication.
Publishes nothing.
"""

from __future__ import annotations

from collections import deque
from functools import partial
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Path
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from cgail_gui.core.foxglove_view import (
    DEFAULT_PORT,
    FoxgloveBridgeConfig,
    FoxgloveConfigError,
    STREAMS,
)
from cgail_gui.hw.foxglove_server import FoxgloveServer, FoxgloveServerError
from cgail_gui.nodes.server_node import ServerNode
from cgail_node_utils.entry_point import run_node
from cgail_node_utils.parameters import declare
from cgail_planner.nodes import conversions as conv

#: The message class of each stream's type.
MESSAGE_CLASSES: dict[str, Any] = {
    'diagnostic_msgs/msg/DiagnosticArray': DiagnosticArray,
    'geometry_msgs/msg/PointStamped': PointStamped,
    'geometry_msgs/msg/PoseStamped': PoseStamped,
    'geometry_msgs/msg/PoseWithCovarianceStamped': PoseWithCovarianceStamped,
    'nav_msgs/msg/Path': Path,
    'sensor_msgs/msg/JointState': JointState,
    'std_msgs/msg/Float64': Float64,
    'std_msgs/msg/Float64MultiArray': Float64MultiArray,
    'tf2_msgs/msg/TFMessage': TFMessage,
    'visualization_msgs/msg/MarkerArray': MarkerArray,
}
#: tf2's /tf profile: reliable, volatile, a deep queue (several transforms per tick).
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
#: The subscription's QoS for each class of docs/interfaces.md (the publisher's).
QOS = {'sensor': conv.SENSOR_QOS, 'command': conv.COMMAND_QOS, 'latched': conv.LATCHED_QOS,
       'tf': TF_QOS, 'diagnostics': conv.DIAGNOSTICS_QOS}
#: Wall seconds between checks for new client subscriptions (which get the latched state).
RESEND_PERIOD_S = 0.1


class FoxgloveBridge(ServerNode):
    """Thin wrapper: raw subscriptions in, :class:`FoxgloveServer` channels out."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('foxglove_bridge', **kwargs)
        host = declare(self, 'host', '127.0.0.1', 'address the Foxglove WebSocket server '
                       'listens on (127.0.0.1: this machine only; an address other machines '
                       'reach needs allow_remote); read-only', read_only=True)
        port = declare(self, 'port', DEFAULT_PORT, "TCP port (8765: Foxglove's default; 0: any "
                       'free port, logged); read-only', lo=0, hi=65535, read_only=True)
        allow_remote = declare(self, 'allow_remote', False, 'accept a host that is not a '
                               'loopback address (the protocol has no authentication: anyone '
                               'who reaches the port sees the rig); read-only', read_only=True)
        try:
            self.config = FoxgloveBridgeConfig(host=host, port=port, allow_remote=allow_remote)
            self.server = FoxgloveServer(host, port)
        except (FoxgloveConfigError, FoxgloveServerError):
            super().destroy_node()  # (no server running)
            raise
        self.kept: dict[str, deque[bytes]] = {}
        for stream in STREAMS:
            topic = self.resolve_topic_name(stream.own)
            self.server.add_channel(topic, stream.msg_type)
            if stream.keep:
                self.kept[topic] = deque(maxlen=stream.keep)
            qos = QOS[stream.qos]
            if stream.keep > qos.depth:
                qos = QoSProfile(depth=stream.keep, reliability=qos.reliability,
                                 durability=qos.durability)
            self.create_subscription(MESSAGE_CLASSES[stream.msg_type], stream.own,
                                     partial(self._forward, topic), qos, raw=True)
        # (a viewer: wall-clock pacing even when the rig runs on simulated time)
        self.create_timer(RESEND_PERIOD_S, self._send_kept,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'Foxglove WebSocket server on {self.server.url} ({len(STREAMS)} topics, '
            'ros2msg/cdr)' + ('; open to other machines (allow_remote)'
                              if host != 'localhost' and allow_remote else ''))

    def _forward(self, topic: str, data: bytes) -> None:
        self.server.log(topic, data, self.get_clock().now().nanoseconds)
        kept = self.kept.get(topic)
        if kept is not None:
            kept.append(data)

    def _send_kept(self) -> None:
        """Send the kept latched state again on the channels a client just subscribed to (the
        clients subscribed before get it twice: a snapshot, so harmlessly)."""
        topics = self.server.take_subscribed()
        now = self.get_clock().now().nanoseconds
        for topic in sorted(topics & set(self.kept)):
            for data in self.kept[topic]:
                self.server.log(topic, data, now)


def main(args: list[str] | None = None) -> None:
    """Console script ``foxglove_bridge``."""
    run_node(FoxgloveBridge, 'foxglove_bridge', args,
             fatal=(FoxgloveConfigError, FoxgloveServerError, InvalidParameterTypeException,
                    InvalidParameterValueException))


if __name__ == '__main__':
    main()

"""What the live Foxglove view serves, and where (no rclpy, no foxglove-sdk).

``foxglove_bridge`` (:mod:`cgail_gui.nodes.foxglove_bridge`) forwards the rig's topics to the
Foxglove app over the Foxglove WebSocket protocol. :data:`STREAMS` is its fixed list: each
topic under the bridge's own name (``~/tip_pose``), the rig name the launch files remap it to
(``em_tracker/tip_pose``), its type and its QoS class (docs/interfaces.md, Conventions).

**Encoding: ros2msg / cdr.** Every channel carries the ROS 2 message as published (its CDR
bytes, taken from a raw subscription, never decoded) with its ``ros2msg`` schema: the same
bytes and schemas as the trial bags' MCAP, so one Foxglove layout
(``cgail_rig/config/foxglove/cgail_layout.json``) shows a recorded trial and the live rig, as
ROS's own ``foxglove_bridge`` does. The Foxglove schemas (``foxglove.PoseInFrame``,
``FrameTransforms``, ``SceneUpdate``) would mean converting every message in Python and would
leave out the pressures and the diagnostics, which have no Foxglove schema.

**Loopback only, unless asked.** The Foxglove WebSocket protocol has no authentication: whoever
reaches the port sees the rig. :class:`FoxgloveBridgeConfig` refuses a ``host`` that is not a
loopback address unless ``allow_remote`` is true.
"""

from __future__ import annotations

from dataclasses import dataclass
import ipaddress

#: Foxglove's default WebSocket port (the app's "Open connection" dialog proposes it).
DEFAULT_PORT = 8765
#: QoS classes of docs/interfaces.md a stream may have.
QOS_CLASSES = ('sensor', 'command', 'latched', 'tf', 'diagnostics')


class FoxgloveConfigError(ValueError):
    """A parameter of the Foxglove bridge is out of its domain (one line naming it)."""


@dataclass(frozen=True)
class Stream:
    """One topic the bridge serves."""

    own: str
    """The bridge's name for it: private (``~/tip_pose``) or absolute (``/tf``)."""
    rig: str
    """Its rig name (relative) that the launch files remap ``own`` to; '' for an absolute one."""
    msg_type: str
    """``pkg/msg/Name``: the channel's ``ros2msg`` schema name."""
    qos: str
    """The publisher's QoS class (docs/interfaces.md), which the subscription matches."""
    keep: int = 0
    """Samples kept for a client that subscribes later (latched state: the markers, the path,
    the goal, the static transforms); 0: none."""


#: What the live view shows: the tip, TF, the markers (lumen, catheter body, plan), the plan
#: itself, the actuators (PAM pressures, bend and insertion states) and every node's health.
STREAMS: tuple[Stream, ...] = (
    Stream('~/tip_pose', 'em_tracker/tip_pose', 'geometry_msgs/msg/PoseStamped', 'sensor'),
    Stream('~/tip_pose_cov', 'em_tracker/tip_pose_cov',
           'geometry_msgs/msg/PoseWithCovarianceStamped', 'sensor'),
    Stream('~/rms_error', 'em_tracker/rms_error', 'std_msgs/msg/Float64', 'sensor'),
    Stream('/tf', '', 'tf2_msgs/msg/TFMessage', 'tf'),
    Stream('/tf_static', '', 'tf2_msgs/msg/TFMessage', 'latched', keep=16),
    Stream('~/phantom_markers', 'phantom/markers', 'visualization_msgs/msg/MarkerArray',
           'latched', keep=1),
    Stream('~/phantom_lumen', 'phantom/lumen', 'visualization_msgs/msg/MarkerArray',
           'latched', keep=1),
    Stream('~/planner_markers', 'planner/markers', 'visualization_msgs/msg/MarkerArray',
           'latched', keep=1),
    Stream('~/path', 'planner/path', 'nav_msgs/msg/Path', 'latched', keep=1),
    Stream('~/goal', 'planner/goal', 'geometry_msgs/msg/PoseStamped', 'command', keep=1),
    Stream('~/next_waypoint', 'planner/next_waypoint', 'geometry_msgs/msg/PointStamped',
           'sensor'),
    Stream('~/suggested_bend', 'planner/suggested_bend', 'sensor_msgs/msg/JointState',
           'sensor'),
    Stream('~/pressures', 'pam/pressures', 'std_msgs/msg/Float64MultiArray', 'sensor'),
    Stream('~/bend_state', 'catheter/bend_state', 'sensor_msgs/msg/JointState', 'sensor'),
    Stream('~/insertion_state', 'catheter/insertion_state', 'sensor_msgs/msg/JointState',
           'sensor'),
    Stream('/diagnostics', '', 'diagnostic_msgs/msg/DiagnosticArray', 'diagnostics'),
)


def check_host(host: str, allow_remote: bool) -> None:
    """Accept ``host`` as the server's listen address.

    Raises:
        FoxgloveConfigError: not an IP literal nor ``localhost``, or not a loopback address
            while ``allow_remote`` is false.
    """
    if host == 'localhost':
        return
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        raise FoxgloveConfigError(f"host: expected an IP address or 'localhost', found "
                                  f'{host!r}') from None
    if not address.is_loopback and not allow_remote:
        raise FoxgloveConfigError(
            f'host: expected a loopback address (127.0.0.1, ::1, localhost), found {host!r}: '
            'the Foxglove WebSocket has no authentication, so serving other machines needs '
            'allow_remote:=true')


@dataclass(frozen=True)
class FoxgloveBridgeConfig:
    """The bridge's parameters (defaults: ``cgail_gui/config/foxglove_bridge.yaml``)."""

    host: str = '127.0.0.1'
    """Listen address; a non-loopback one needs ``allow_remote``."""
    port: int = DEFAULT_PORT
    """TCP port; 0: any free port."""
    allow_remote: bool = False
    """Accept a ``host`` that other machines reach."""

    def __post_init__(self) -> None:
        check_host(self.host, self.allow_remote)
        if not 0 <= self.port <= 65535:
            raise FoxgloveConfigError(f'port: expected 0..65535, found {self.port}')

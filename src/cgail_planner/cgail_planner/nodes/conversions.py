"""Messages <-> core types for the cgail_planner nodes, the QoS profiles and a parameter helper.

QoS names follow docs/interfaces.md: ``SENSOR_QOS`` (best effort, keep last 5), ``COMMAND_QOS``
(reliable, volatile, keep last 10), ``LATCHED_QOS`` (reliable, transient local, keep last 1),
``DIAGNOSTICS_QOS`` (reliable, keep last 10).
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence
import math
from typing import TypeVar

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PointStamped, Pose, PoseStamped, Quaternion
from nav_msgs.msg import Path
import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    qos_profile_sensor_data,
    QoSProfile,
    ReliabilityPolicy,
)
from sensor_msgs.msg import JointState, Joy
from std_msgs.msg import Float64MultiArray, Header
from visualization_msgs.msg import Marker, MarkerArray

from cgail_planner.core.errors import InvalidInputError
from cgail_planner.core.markers import (
    ARROW,
    LINE_STRIP,
    MarkerGeometry,
    SPHERE,
    TRIANGLE_LIST,
)
from cgail_planner.core.rotations import matrix_to_quaternion, pose_from_quaternion

SENSOR_QOS = qos_profile_sensor_data
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)
DIAGNOSTICS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE,
                             history=HistoryPolicy.KEEP_LAST)

#: Joint names of a bend (docs/interfaces.md).
BEND_JOINTS = ('bend_alpha', 'bend_gamma')

T = TypeVar('T', bool, int, float, str)


def declare(node: Node, name: str, default: T, description: str, *,
            lo: float | None = None, hi: float | None = None) -> T:
    """Declare ``name`` once with a description (and an inclusive range); return its value.

    Raises:
        rclpy.exceptions.InvalidParameterValueException: value outside the range.
        rclpy.exceptions.InvalidParameterTypeException: value of the wrong type.
    """
    descriptor = ParameterDescriptor(name=name, description=description)
    if lo is not None and hi is not None and not isinstance(default, bool):
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi),
                                                     step=1)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(lo), to_value=float(hi), step=0.0)]
    value = node.declare_parameter(name, default, descriptor).value
    return type(default)(value)


def stamp_seconds(stamp: Time) -> float:
    """A ``builtin_interfaces/Time`` in seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def pose_from_msg(msg: PoseStamped) -> tuple[np.ndarray, np.ndarray]:
    """``(position (3,), rotation (3, 3))`` of a PoseStamped.

    Raises:
        InvalidInputError: NaN/inf or a quaternion that is not of unit norm.
    """
    p = msg.pose.position
    q = msg.pose.orientation
    return pose_from_quaternion((p.x, p.y, p.z), (q.x, q.y, q.z, q.w))


def point_from_pose_msg(msg: PoseStamped) -> np.ndarray:
    """The position of a PoseStamped as a (3,) array (not validated)."""
    p = msg.pose.position
    return np.array([p.x, p.y, p.z], dtype=np.float64)


def pose_msg(stamp: Time, frame_id: str, position: np.ndarray,
             rotation: np.ndarray, out: PoseStamped | None = None) -> PoseStamped:
    """A PoseStamped from a position and a rotation matrix; ``out``: one to refill (every
    field is set; :func:`point_msg`).

    This and the other per-pose messages below set their fields in place: a message's
    constructor builds its nested defaults (a Header, a Time, ...) even when they are passed,
    so passing them built each twice (up to 160 messages a simulated second).
    """
    msg = PoseStamped() if out is None else out
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    p, q = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = float(position[0]), float(position[1]), float(position[2])
    q.x, q.y, q.z, q.w = (float(v) for v in matrix_to_quaternion(rotation))
    return msg


def path_msg(stamp: Time, frame_id: str, points: np.ndarray) -> Path:
    """A nav_msgs/Path through ``points`` (N, 3); each pose's orientation is the path tangent
    (y axis along the direction of travel, as the tip frame's heading)."""
    from cgail_sim.ftl_model import frame_from_heading

    header = Header(stamp=stamp, frame_id=frame_id)
    tangents = np.gradient(points, axis=0) if len(points) > 1 else np.array([[0.0, 1.0, 0.0]])
    frames = np.empty((len(points), 3, 3))
    for k, t in enumerate(tangents):
        try:
            frames[k] = frame_from_heading(t)
        except ValueError:  # a zero tangent: the identity
            frames[k] = np.eye(3)
    quats = matrix_to_quaternion(frames).reshape(-1, 4).tolist()  # one scipy call
    poses = [PoseStamped(header=header, pose=Pose(
        position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))
        for p, q in zip(points, quats, strict=True)]
    return Path(header=header, poses=poses)


def path_points(msg: Path) -> np.ndarray:
    """(N, 3) positions of a nav_msgs/Path."""
    return np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                     for p in msg.poses], dtype=np.float64).reshape(-1, 3)


def point_msg(stamp: Time, frame_id: str, point: np.ndarray,
              out: PointStamped | None = None) -> PointStamped:
    """A PointStamped; ``out``: one to refill (every field is set) instead of a new one.

    ``out`` (here and below) serves a node that publishes per tip pose: a publish serializes
    the message before it returns (rclpy, and the lockstep rig's in-process transport), so the
    node can refill one object, where a new message builds all its nested defaults first.
    """
    msg = PointStamped() if out is None else out
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    p = msg.point
    p.x, p.y, p.z = float(point[0]), float(point[1]), float(point[2])
    return msg


def bend_msg(stamp: Time, alpha: float, gamma: float,
             out: JointState | None = None) -> JointState:
    """A bend JointState (``bend_alpha``, ``bend_gamma``; rad); ``out``: one this function
    filled before, to refill (:func:`point_msg`)."""
    msg = JointState() if out is None else out
    msg.header.stamp = stamp
    msg.name = list(BEND_JOINTS)
    msg.position = array('d', (float(alpha), float(gamma)))  # (stored as given, unchecked)
    return msg


_MARKER_TYPES = {TRIANGLE_LIST: Marker.TRIANGLE_LIST, LINE_STRIP: Marker.LINE_STRIP,
                 SPHERE: Marker.SPHERE, ARROW: Marker.ARROW}


def _points(points: np.ndarray) -> list[Point]:
    out = []
    for x, y, z in points.tolist():  # (attribute assignment: ~4x faster than Point(x=...))
        p = Point()
        p.x, p.y, p.z = x, y, z
        out.append(p)
    return out


def marker_msg(header: Header, geometry: MarkerGeometry, out: Marker | None = None) -> Marker:
    """One ADD ``visualization_msgs/Marker`` of a :class:`MarkerGeometry` (a SPHERE's centre
    goes in the pose, the other kinds' points in ``points``; identity orientation); ``out``: a
    Marker this function filled for a geometry of the same namespace, id and kind, to refill
    (:func:`point_msg`; a Marker's constructor is the costliest of the messages here)."""
    if out is None:
        m = Marker(header=header, ns=geometry.ns, id=geometry.id,
                   type=_MARKER_TYPES[geometry.kind], action=Marker.ADD)
    else:
        m = out
        m.header = header
    m.pose.orientation.w = 1.0
    m.scale.x, m.scale.y, m.scale.z = (float(v) for v in geometry.scale)
    color = m.color  # (set in place: the constructor built the default already)
    color.r, color.g, color.b, color.a = (float(c) for c in geometry.color)
    if geometry.kind == SPHERE:
        c = geometry.points[0]
        position = m.pose.position
        position.x, position.y, position.z = float(c[0]), float(c[1]), float(c[2])
    else:
        m.points = _points(geometry.points)
    return m


def marker_array_msg(stamp: Time, frame_id: str, geometries: Sequence[MarkerGeometry],
                     prebuilt: Sequence[Marker] = ()) -> MarkerArray:
    """A full-snapshot MarkerArray: DELETEALL, then ``prebuilt`` markers (their header is set
    to this one) and one ADD per geometry (:mod:`cgail_planner.core.markers`)."""
    header = Header(stamp=stamp, frame_id=frame_id)
    out = [Marker(header=header, action=Marker.DELETEALL)]
    for m in prebuilt:
        m.header = header
        out.append(m)
    out += [marker_msg(header, g) for g in geometries]
    return MarkerArray(markers=out)


def marker_points(msg: Marker) -> np.ndarray:
    """(N, 3) ``points`` of a Marker."""
    return np.array([(p.x, p.y, p.z) for p in msg.points], dtype=np.float64).reshape(-1, 3)


def joint_positions(msg: JointState, names: Sequence[str]) -> list[float]:
    """Positions of ``names`` in a JointState.

    Raises:
        InvalidInputError: a joint missing, or a non-finite value.
    """
    out = []
    joints = list(msg.name)
    for name in names:
        try:
            k = joints.index(name)
            value = float(msg.position[k])
        except (ValueError, IndexError):
            raise InvalidInputError(f'JointState must carry a position for {name!r}, found '
                                    f'names {joints}') from None
        if not math.isfinite(value):  # (a float: math's test, numpy's without its call)
            raise InvalidInputError(f'{name} must be finite, found {value}')
        out.append(value)
    return out


def chamber_pressures(msg: Float64MultiArray) -> np.ndarray:
    """The four chamber pressures (Pa) of a ``pam/pressures`` message.

    Raises:
        InvalidInputError: not 4 values, or a non-finite one.
    """
    p = np.asarray(msg.data, dtype=np.float64)
    if p.shape != (4,) or not np.all(np.isfinite(p)):
        raise InvalidInputError(f'pam/pressures must carry 4 finite pressures, found '
                                f'{list(msg.data)}')
    return p


def diagnostics(stamp: Time, name: str, hardware_id: str, level: bytes, message: str,
                values: Sequence[tuple[str, object]]) -> DiagnosticArray:
    """A DiagnosticArray with one status."""
    status = DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                              values=[KeyValue(key=k, value=str(v)) for k, v in values])
    return DiagnosticArray(header=Header(stamp=stamp), status=[status])


def insertion_msg(stamp: Time, velocity: float) -> JointState:
    """An insertion velocity command (``insertion``, velocity only; m/s), as teleop sends it."""
    return JointState(header=Header(stamp=stamp), name=['insertion'],
                      velocity=[float(velocity)])


def joy_sticks(msg: Joy, enable_button: int, axes: Sequence[int]
               ) -> tuple[bool, tuple[float, float, float]]:
    """The deadman and the ``(insertion, bend_alpha, bend_gamma)`` deflections of a Joy, with
    teleop's layout (``axes``: the three axis indices).

    Raises:
        InvalidInputError: too few buttons or axes, or an axis not finite in [-1, 1].
    """
    if len(msg.buttons) <= enable_button:
        raise InvalidInputError(f'Joy: expected at least {enable_button + 1} buttons, found '
                                f'{len(msg.buttons)}')
    if len(msg.axes) <= max(axes):
        raise InvalidInputError(f'Joy: expected at least {max(axes) + 1} axes, found '
                                f'{len(msg.axes)}')
    values = [float(msg.axes[i]) for i in axes]
    for i, v in zip(axes, values, strict=True):
        if not (np.isfinite(v) and -1.0 <= v <= 1.0):
            raise InvalidInputError(f'Joy axis {i}: expected a finite value in [-1, 1], '
                                    f'found {v!r}')
    return bool(msg.buttons[enable_button]), (values[0], values[1], values[2])

"""Messages <-> core types for the catheter_driver nodes, and the QoS profiles of the contract."""

from __future__ import annotations

from array import array
from collections.abc import Iterable
import math
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import ROSClock
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    qos_profile_sensor_data,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.time import Time
from sensor_msgs.msg import JointState, Joy

from catheter_driver.core.joy_filter import JoyOutput
from catheter_driver.exceptions import CommandError

INSERTION_JOINT = 'insertion'
BEND_JOINTS = ('bend_alpha', 'bend_gamma')

SENSOR_QOS = qos_profile_sensor_data
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
DIAGNOSTICS_QOS = COMMAND_QOS


def insertion_velocity(msg: JointState, max_speed: float) -> float:
    """The insertion velocity (m/s) carried by an ``insertion`` JointState command.

    Raises:
        CommandError: joint missing, no velocity, NaN/inf, or ``|v| > max_speed``.
    """
    names = list(msg.name)
    if INSERTION_JOINT not in names:
        raise CommandError(f"expected joint '{INSERTION_JOINT}' in name, found {names}")
    index = names.index(INSERTION_JOINT)
    if len(msg.velocity) != len(names):
        raise CommandError(
            f'expected {len(names)} velocities (one per name), found {len(msg.velocity)}')
    value = float(msg.velocity[index])
    if not math.isfinite(value):
        raise CommandError(f'expected a finite insertion velocity, found {value!r}')
    if abs(value) > max_speed:
        raise CommandError(
            f'expected |insertion velocity| <= {max_speed} m/s, found {value!r} m/s')
    return value


def insertion_state(stamp: Time, position: float, velocity: float,
                    out: JointState | None = None) -> JointState:
    """``insertion`` JointState with position (m) and velocity (m/s); ``out``: one this
    function filled before, to refill instead of a new one.

    ``out`` (here and below) serves a node that publishes every control tick: a publish
    serializes the message before it returns (rclpy, and the lockstep rig's in-process
    transport), so the node can refill one object, where a new message builds all its nested
    defaults first.
    """
    msg = JointState() if out is None else out
    msg.header.stamp = stamp.to_msg()
    msg.name = [INSERTION_JOINT]
    # (float64 sequences as array('d'), which the generated setters store as given; a list they
    # check value by value and convert to the same array: several messages per 40 Hz tick)
    msg.position = array('d', (float(position),))
    msg.velocity = array('d', (float(velocity),))
    return msg


def insertion_command(stamp: Time, velocity: float, out: JointState | None = None
                      ) -> JointState:
    """``insertion`` JointState carrying only a velocity command (m/s); ``out``: one this
    function filled before (:func:`insertion_state`)."""
    msg = JointState() if out is None else out
    msg.header.stamp = stamp.to_msg()
    msg.name = [INSERTION_JOINT]
    msg.velocity = array('d', (float(velocity),))
    return msg


def bend_command(stamp: Time, bend: tuple[float, float], out: JointState | None = None
                 ) -> JointState:
    """``bend_alpha``/``bend_gamma`` JointState with the bend setpoint (rad); ``out``: one this
    function filled before (:func:`insertion_state`)."""
    msg = JointState() if out is None else out
    msg.header.stamp = stamp.to_msg()
    msg.name = list(BEND_JOINTS)
    msg.position = array('d', (float(bend[0]), float(bend[1])))
    return msg


def joy_message(stamp: Time, output: JoyOutput, frame_id: str = 'joy') -> Joy:
    """sensor_msgs/Joy from the filter's output."""
    msg = Joy()
    msg.header.stamp = stamp.to_msg()
    msg.header.frame_id = frame_id
    msg.axes = [float(a) for a in output.axes]
    msg.buttons = [int(b) for b in output.buttons]
    return msg


def diagnostics(stamp: Time, name: str, hardware_id: str, level: bytes, message: str,
                values: Iterable[tuple[str, object]]) -> DiagnosticArray:
    """A DiagnosticArray with one status; values are stringified."""
    status = DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id)
    status.values = [KeyValue(key=k, value=str(v)) for k, v in values]
    array = DiagnosticArray()
    array.header.stamp = stamp.to_msg()
    array.status = [status]
    return array


def node_seconds(node: Node) -> float:
    """Seconds for watchdogs and timeouts: the node clock when it runs on simulated time (the
    lockstep rig, ``use_sim_time``), else the steady clock (immune to system-time jumps)."""
    clock = node.get_clock()
    sim = isinstance(clock, ROSClock) and clock.ros_time_is_active
    return clock.now().nanoseconds * 1e-9 if sim else time.monotonic()

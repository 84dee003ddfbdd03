"""Messages <-> core types for the pam_controller node (no logic beyond the mapping)."""

from __future__ import annotations

from array import array
from collections.abc import Iterable, Sequence
import math
import time

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
import numpy as np
from numpy.typing import NDArray
from rclpy.clock import ROSClock
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from pam_controller.core.bending_model import BEND_JOINT_NAMES, CHAMBER_LABELS
from pam_controller.errors import CommandRejectedError

PRESSURE_LAYOUT_LABEL = ','.join(CHAMBER_LABELS)
"""``layout.dim[0].label`` of ``pam/pressures``: the chamber order of ``data``."""


def bend_from_joint_state(msg: JointState) -> NDArray[np.float64]:
    """``[alpha, gamma]`` (rad) from a bend command; other joints in the message are ignored.

    Raises:
        CommandRejectedError: a bend joint is missing or has no position.
    """
    names = list(msg.name)
    positions = list(msg.position)
    if len(positions) != len(names):
        raise CommandRejectedError(
            f'expected one position per joint name, found {len(names)} names and '
            f'{len(positions)} positions')
    missing = [n for n in BEND_JOINT_NAMES if n not in names]
    if missing:
        raise CommandRejectedError(
            f'expected joints {list(BEND_JOINT_NAMES)}, found {names} (missing {missing})')
    return np.array([float(positions[names.index(n)]) for n in BEND_JOINT_NAMES])


def bend_to_joint_state(bend: Sequence[float] | np.ndarray, stamp: Time,
                        out: JointState | None = None) -> JointState:
    """JointState with ``bend_alpha``, ``bend_gamma`` positions (rad); ``out``: one this
    function filled before, to refill instead of a new one (a publish serializes the message
    before it returns, so the control loop refills one object per topic: a new message builds
    all its nested defaults first)."""
    msg = JointState() if out is None else out
    msg.header.stamp = stamp
    msg.name = list(BEND_JOINT_NAMES)
    # (an array('d') is stored as given; a list is checked value by value and converted to
    # the same array: the control loop publishes this and the pressures at 40 Hz)
    msg.position = array('d', [float(b) for b in bend])
    return msg


def pressures_to_multiarray(pressures_pa: Sequence[float] | np.ndarray,
                            out: Float64MultiArray | None = None) -> Float64MultiArray:
    """Four chamber pressures (Pa) in the documented layout; ``out``: one this function filled
    before (its layout kept), to refill (:func:`bend_to_joint_state`)."""
    if out is None:
        msg = Float64MultiArray()
        msg.layout.dim = [MultiArrayDimension(label=PRESSURE_LAYOUT_LABEL, size=4, stride=4)]
        msg.layout.data_offset = 0
    else:
        msg = out
    msg.data = array('d', [float(p) for p in pressures_pa])
    return msg


def diagnostic_status(name: str, hardware_id: str, level: bytes, message: str,
                      values: Iterable[tuple[str, object]]) -> DiagnosticStatus:
    """A DiagnosticStatus; floats are written with 6 significant digits, NaN as ``nan``."""
    def fmt(v: object) -> str:
        if isinstance(v, float):
            return 'nan' if math.isnan(v) else f'{v:.6g}'
        if isinstance(v, (list, tuple, np.ndarray)):
            return '[' + ', '.join(fmt(float(x)) for x in v) + ']'
        return str(v)

    return DiagnosticStatus(level=level, name=name, hardware_id=hardware_id, message=message,
                            values=[KeyValue(key=k, value=fmt(v)) for k, v in values])


def node_seconds(node: Node) -> float:
    """Seconds for watchdogs and timeouts: the node clock when it runs on simulated time (the
    lockstep rig, ``use_sim_time``), else the steady clock (immune to system-time jumps)."""
    clock = node.get_clock()
    sim = isinstance(clock, ROSClock) and clock.ros_time_is_active
    return clock.now().nanoseconds * 1e-9 if sim else time.monotonic()

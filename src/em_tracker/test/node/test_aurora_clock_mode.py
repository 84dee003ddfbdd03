"""aurora_node with ``poll_mode: clock``: polls from a timer of its (simulated) clock.

This is how the lockstep simulated rig runs the tracker: no reader thread and no guard
condition, one synchronous poll per frame period of the node clock, poses stamped with it.
"""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data, QoSProfile
from rclpy.signals import SignalHandlerOptions
from rclpy.time import Time
from rclpy.time_source import TimeSource
from rosgraph_msgs.msg import Clock

from em_tracker.hw.aurora import ToolReading, TrackingReply
from em_tracker.nodes.aurora_node import AuroraNode

VALID = dict(handle=0x0A, visible=True, quat_wxyz=(1.0, 0.0, 0.0, 0.0),
             position_mm=(10.0, -20.0, -150.0), error_mm=0.3, port_status=0x31)


class CountingDevice:
    """A device that makes a new frame on every read (unless frozen) and counts the reads."""

    def __init__(self):
        self.reads = 0
        self.frame = 0
        self.frozen = False

    def connect(self):
        return [0x0A]

    def read(self):
        self.reads += 1
        self.frame += 0 if self.frozen else 1
        return TrackingReply((ToolReading(frame_number=self.frame, **VALID),), 0, 0.0)

    def close(self):
        pass


@pytest.fixture
def rig():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    device = CountingDevice()
    node = AuroraNode(device_factory=lambda cfg: device, context=ctx, parameter_overrides=[
        Parameter('poll_mode', value='clock'), Parameter('rate_hz', value=40.0),
        Parameter('diagnostics_period_s', value=0.5), Parameter('stale_after_s', value=0.2)])
    time_source = TimeSource()
    time_source.ros_time_is_active = True
    time_source.attach_clock(node.get_clock())
    listener = rclpy.create_node('clock_mode_listener', context=ctx)
    time_source.attach_clock(listener.get_clock())
    poses: list[PoseStamped] = []
    diags: list[DiagnosticStatus] = []
    listener.create_subscription(PoseStamped, '/aurora/tip_pose', poses.append,
                                 qos_profile_sensor_data)
    listener.create_subscription(DiagnosticArray, '/diagnostics',
                                 lambda m: diags.extend(m.status), QoSProfile(depth=10))
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    executor.add_node(listener)

    def set_time(seconds: float) -> None:
        time_source.clock_callback(Clock(clock=Time(nanoseconds=round(seconds * 1e9)).to_msg()))
        for _ in range(8):  # the timers due at that time, then what they published
            executor.spin_once(timeout_sec=0.005)

    set_time(10.0)
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    try:
        yield node, device, set_time, poses, diags
    finally:
        executor.shutdown()
        node.destroy_node()
        listener.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_polls_once_per_frame_period_of_the_node_clock(rig) -> None:
    node, device, set_time, poses, _ = rig
    assert node.guards == [] or not list(node.guards)  # no thread wakes the executor
    for _ in range(30):  # wall time passes, the node clock does not: no poll
        set_time(10.0)
    assert device.reads == 0 and poses == []
    t = 10.0
    for _ in range(8):
        t += 0.025
        set_time(t)
    # the first timer call connects and polls: one read per 25 ms period
    assert device.reads == 8
    assert len(poses) == 8
    assert Time.from_msg(poses[-1].header.stamp).nanoseconds == round(t * 1e9)


def test_diagnostics_go_stale_in_node_clock_seconds(rig) -> None:
    _, device, set_time, _, diags = rig
    for k in range(1, 21):
        set_time(10.0 + 0.025 * k)  # a frame every 25 ms up to the diagnostics at 10.5 s
    assert diags and diags[-1].level == DiagnosticStatus.OK, diags[-1].message
    device.frozen = True  # the device repeats its last frame from now on
    set_time(10.525)
    set_time(11.0)  # 0.5 s of node clock without a new frame, stale_after_s 0.2
    assert device.reads > 20 and diags[-1].level == DiagnosticStatus.STALE

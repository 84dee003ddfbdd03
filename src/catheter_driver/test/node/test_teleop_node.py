"""teleop node in-process: deadman, one stop on release, joy timeout, caps, parameters.

Joy comes from a 50 Hz timer of the probe node (a gamepad's rate), never from a busy loop.
"""

import math
import time

import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import JointState, Joy

from catheter_driver.nodes import conversions as conv
from catheter_driver.nodes.teleop_node import TeleopNode

PARAMS = {'enable_button': 0, 'axis_insertion': 1, 'axis_bend_alpha': 2, 'axis_bend_gamma': 3,
          'scale_bend': 1.0, 'bend_mode': 'rate', 'joy_timeout_s': 1.0}


def _node(harness, **params):
    merged = {**PARAMS, **params}
    return harness.add(TeleopNode(
        parameter_overrides=[Parameter(k, value=v) for k, v in merged.items()]))


JOY_RATE_HZ = 50.0


def _joy(axes, held):
    msg = Joy()
    msg.axes = [float(a) for a in axes]
    msg.buttons = [int(held), 0]
    return msg


class Gamepad:
    """Publishes one Joy at JOY_RATE_HZ from a timer of the probe node until :meth:`stop`."""

    def __init__(self, harness, pub, msg) -> None:
        self.harness = harness
        self.sent_at: list[float] = []

        def send() -> None:
            pub.publish(msg)
            self.sent_at.append(time.monotonic())
        self.timer = harness.repeat(1.0 / JOY_RATE_HZ, send)

    def stop(self) -> None:
        self.harness.stop(self.timer)


@pytest.fixture
def rig(harness):
    node = _node(harness)
    insertion = harness.collect(JointState, '/teleop/insertion_command', conv.COMMAND_QOS)
    bend = harness.collect(JointState, '/teleop/bend_command', conv.COMMAND_QOS)
    joy = harness.probe.create_publisher(Joy, '/teleop/joy', conv.SENSOR_QOS)
    assert harness.spin_until(lambda: node.count_publishers('/teleop/joy') >= 1
                              and joy.get_subscription_count() >= 1)
    return node, joy, insertion, bend


def test_qos_matches_the_contract(harness, rig):
    node = rig[0]
    for topic in ('/teleop/insertion_command', '/teleop/bend_command'):
        info = node.get_publishers_info_by_topic(topic)[0]
        assert info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    sub = node.get_subscriptions_info_by_topic('/teleop/joy')[0]
    assert sub.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT


def test_deadman_held_commands_release_sends_one_stop_then_quiet(harness, rig):
    _, joy, insertion, bend = rig
    harness.spin_for(0.1)
    joy.publish(_joy([0, 1.0, 0, 0], held=False))
    harness.spin_for(0.2)
    assert insertion == [] and bend == []

    pad = Gamepad(harness, joy, _joy([0, 0.5, 1.0, -1.0], held=True))
    assert harness.spin_until(lambda: len(insertion) >= 3)
    pad.stop()
    # every held Joy gives one insertion command: wait for those still in flight
    assert harness.spin_until(lambda: len(insertion) >= len(pad.sent_at))
    assert insertion[-1].name == ['insertion']
    assert insertion[-1].velocity[0] == pytest.approx(0.0025)
    assert bend[-1].name == ['bend_alpha', 'bend_gamma']
    assert bend[-1].position[0] > 0.0 > bend[-1].position[1]
    n = len(insertion)
    for _ in range(10):
        joy.publish(_joy([0, 1.0, 1.0, 1.0], held=False))
        harness.spin_for(0.03)
    harness.spin_for(0.2)
    assert len(insertion) == n + 1 and insertion[-1].velocity[0] == 0.0


def _enable(harness, joy, insertion) -> float:
    """Hold the deadman with the stick pushed until commands flow, then silence the pad (no
    more Joy, the deadman still held in the last one); returns when the last Joy was sent."""
    pad = Gamepad(harness, joy, _joy([0, 1.0, 0, 0], True))
    assert harness.spin_until(lambda: len(insertion) >= 1)
    pad.stop()
    # every held Joy gives one insertion command: wait for those still in flight
    assert harness.spin_until(lambda: len(insertion) >= len(pad.sent_at))
    return pad.sent_at[-1]


def test_joy_timeout_sends_one_stop(harness):
    _node(harness, joy_timeout_s=0.3)
    insertion = harness.collect(JointState, '/teleop/insertion_command', conv.COMMAND_QOS)
    joy = harness.probe.create_publisher(Joy, '/teleop/joy', conv.SENSOR_QOS)
    last_joy = _enable(harness, joy, insertion)  # joy goes silent while the deadman is held
    assert harness.spin_until(lambda: insertion[-1].velocity[0] == 0.0)
    assert time.monotonic() - last_joy >= 0.3  # never before joy_timeout_s
    harness.spin_for(0.3)  # and only one stop
    velocities = [m.velocity[0] for m in insertion]
    assert velocities[-1] == 0.0 and velocities.count(0.0) == 1
    assert set(velocities[:-1]) == {0.005}


def test_nan_joy_while_enabled_fails_safe(harness, rig):
    _, joy, insertion, _ = rig
    _enable(harness, joy, insertion)
    n = len(insertion)
    assert insertion[-1].velocity[0] == 0.005
    joy.publish(_joy([0, math.nan, 0, 0], True))
    assert harness.spin_until(lambda: len(insertion) > n)
    assert insertion[-1].velocity[0] == 0.0


def test_position_mode_and_caps(harness):
    _node(harness, bend_mode='position', scale_bend=math.pi / 2)
    bend = harness.collect(JointState, '/teleop/bend_command', conv.COMMAND_QOS)
    insertion = harness.collect(JointState, '/teleop/insertion_command', conv.COMMAND_QOS)
    joy = harness.probe.create_publisher(Joy, '/teleop/joy', conv.SENSOR_QOS)
    Gamepad(harness, joy, _joy([0, -1.0, -1.0, 0.5], True))
    assert harness.spin_until(lambda: len(bend) >= 2)
    # full alpha and half gamma deflection: the total bend is capped at pi/2 (the cap the PAM
    # controller enforces) with the direction kept (alpha = -2 gamma)
    alpha, gamma = bend[-1].position
    assert math.hypot(alpha, gamma) == pytest.approx(math.pi / 2)
    assert alpha / gamma == pytest.approx(-2.0)
    assert all(abs(m.velocity[0]) <= 0.005 for m in insertion)


@pytest.mark.parametrize(('params', 'error', 'match'), [
    ({'scale_insertion': 0.01}, InvalidParameterValueException, 'scale_insertion'),
    ({'scale_insertion': 0.0}, ValueError, 'scale_insertion must satisfy'),
    ({'max_bend': 3.0}, InvalidParameterValueException, 'max_bend'),
    ({'bend_mode': 'torque'}, ValueError, "bend_mode must be 'rate' or 'position'"),
    ({'axis_bend_alpha': 1}, ValueError, 'must differ'),
    ({'joy_timeout_s': -1.0}, ValueError, 'joy_timeout must be a finite number > 0'),
])
def test_bad_parameters_raise(harness, params, error, match):
    with pytest.raises(error, match=match):
        TeleopNode(parameter_overrides=[Parameter(k, value=v) for k, v in
                                        {**PARAMS, **params}.items()])


def test_refilled_command_messages_equal_new_ones() -> None:
    # the driver and teleop nodes refill their per-tick JointStates (conversions' out=)
    from rclpy.clock import ClockType
    from rclpy.time import Time
    from sensor_msgs.msg import JointState

    from catheter_driver.nodes import conversions as conv

    outs = [JointState(), JointState(), JointState()]
    for k in range(2):
        stamp = Time(nanoseconds=10 + k, clock_type=ClockType.ROS_TIME)
        outs[0] = conv.insertion_state(stamp, 0.01 * k, -0.002, out=outs[0])
        assert outs[0] == conv.insertion_state(stamp, 0.01 * k, -0.002)
        outs[1] = conv.insertion_command(stamp, 0.001 * k, out=outs[1])
        assert outs[1] == conv.insertion_command(stamp, 0.001 * k)
        outs[2] = conv.bend_command(stamp, (0.1, -0.1 * k), out=outs[2])
        assert outs[2] == conv.bend_command(stamp, (0.1, -0.1 * k))

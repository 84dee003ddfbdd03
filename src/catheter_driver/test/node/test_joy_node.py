"""joy node in-process with a fake gamepad: conventions, hot-plug, diagnostics, parameters."""

from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import Joy

from catheter_driver.hw.gamepad import FakeGamepad, FakeGamepadFactory
from catheter_driver.nodes import conversions as conv
from catheter_driver.nodes.joy_node import JoyNode


def _node(harness, factory, **params):
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    return harness.add(JoyNode(gamepad_factory=factory, parameter_overrides=overrides))


def test_publishes_with_joy_conventions_and_sensor_qos(harness):
    pad = FakeGamepad(n_axes=2, n_buttons=3, n_hats=1)
    node = _node(harness, FakeGamepadFactory(pad), autorepeat_rate=0.0)
    msgs = harness.collect(Joy, '/joy/joy', conv.SENSOR_QOS)
    info = node.get_publishers_info_by_topic('/joy/joy')[0]
    assert info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    assert harness.spin_until(lambda: len(msgs) >= 1)
    assert list(msgs[0].axes) == [0.0, 0.0, 0.0, 0.0] and list(msgs[0].buttons) == [0, 0, 0]
    assert msgs[0].header.frame_id == 'joy'
    pad.set(axes=(32767, -32768), buttons=(False, True, False), hats=[(-1, 1)])
    assert harness.spin_until(lambda: len(msgs) >= 2)
    assert list(msgs[-1].axes) == pytest.approx([-1.0, 1.0, 1.0, 1.0])
    assert list(msgs[-1].buttons) == [0, 1, 0]
    pad.set(axes=(1000, 0))  # inside the 0.05 deadzone
    assert harness.spin_until(lambda: msgs[-1].axes[0] == 0.0)


def test_autorepeat_rate(harness):
    _node(harness, FakeGamepadFactory(FakeGamepad()), autorepeat_rate=20.0)
    msgs = harness.collect(Joy, '/joy/joy', conv.SENSOR_QOS)
    assert harness.spin_until(lambda: len(msgs) >= 1)
    first = len(msgs)
    harness.spin_for(1.0)
    assert 12 <= len(msgs) - first <= 22  # 20 Hz, loosely (shared CPU)


def test_no_device_is_a_clear_error_and_it_keeps_retrying(harness):
    factory = FakeGamepadFactory(None)
    node = _node(harness, factory, reconnect_interval_s=0.05)
    msgs = harness.collect(Joy, '/joy/joy', conv.SENSOR_QOS)
    assert harness.spin_until(lambda: factory.attempts >= 3)
    diag = node.diagnostics_message().status[0]
    assert diag.level == DiagnosticStatus.ERROR
    assert diag.message.startswith('no gamepad: expected a gamepad with device_id 0')
    assert 'plug in a gamepad' in diag.message
    assert msgs == []
    pad = FakeGamepad()
    factory.gamepad = pad
    assert harness.spin_until(lambda: msgs)
    assert node.diagnostics_message().status[0].level == DiagnosticStatus.OK
    pad.plugged = False
    assert harness.spin_until(
        lambda: node.diagnostics_message().status[0].level == DiagnosticStatus.ERROR)
    assert 'unplugged' in node.diagnostics_message().status[0].message
    pad.plugged = True
    assert harness.spin_until(
        lambda: node.diagnostics_message().status[0].level == DiagnosticStatus.OK)


def test_device_name_is_passed_to_the_factory(harness):
    factory = FakeGamepadFactory(FakeGamepad(name='Yues Pad'))
    node = _node(harness, factory, device_name='Other Pad', reconnect_interval_s=0.05)
    assert harness.spin_until(lambda: factory.attempts >= 2)
    assert "named 'Other Pad'" in node.diagnostics_message().status[0].message


@pytest.mark.parametrize(('params', 'error', 'match'), [
    ({'deadzone': 1.5}, InvalidParameterValueException, 'deadzone'),
    ({'deadzone': 1.0}, ValueError, r'deadzone must be in \[0.0, 1.0\), found 1.0'),
    ({'autorepeat_rate': -1.0}, InvalidParameterValueException, 'autorepeat_rate'),
    ({'coalesce_interval_ms': -5}, InvalidParameterValueException, 'coalesce_interval_ms'),
    ({'device_id': -1}, InvalidParameterValueException, 'device_id'),
])
def test_bad_parameters_raise(harness, params, error, match):
    with pytest.raises(error, match=match):
        JoyNode(gamepad_factory=FakeGamepadFactory(None),
                parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


def test_real_sdl_without_a_gamepad_reports_and_retries(harness):
    # The test machines have no gamepad: the default (pygame/SDL2) factory must say so.
    node = harness.add(JoyNode(parameter_overrides=[Parameter('reconnect_interval_s',
                                                              value=0.05)]))
    assert harness.spin_until(lambda: node.open_attempts >= 2)
    diag = node.diagnostics_message().status[0]
    assert diag.level == DiagnosticStatus.ERROR
    assert diag.message.startswith('no gamepad: expected a gamepad with device_id 0, found 0')

"""ROS joy conventions: axis scaling, deadzone, hats, buttons, coalescing and autorepeat."""

import math

import pytest

from catheter_driver.core.joy_filter import (
    axis_to_ros,
    hat_to_ros,
    JoyConfig,
    JoyFilter,
    JoyOutput,
    JoySample,
)
from catheter_driver.exceptions import DeviceDisconnectedError, GamepadNotFoundError
from catheter_driver.hw.gamepad import FakeGamepad, FakeGamepadFactory, SdlGamepad


@pytest.mark.parametrize(('raw', 'deadzone', 'expected'), [
    (0, 0.05, 0.0),
    (32767, 0.05, -1.0),          # SDL positive = ROS negative
    (-32768, 0.05, 1.0),          # -32768 counts as -32767
    (-32767, 0.0, 1.0),
    (1638, 0.05, 0.0),            # inside 0.05 * 32767 = 1638.35
    (-1639, 0.05, 0.65 / (32767 * 0.95)),
    (16384, 0.0, -16384 / 32767),
    (16384, 0.5, -(16384 - 16383.5) / 16383.5),
])
def test_axis_to_ros(raw, deadzone, expected):
    assert axis_to_ros(raw, deadzone) == pytest.approx(expected, rel=1e-12, abs=1e-15)


def test_axis_is_always_within_unit_range():
    for dz in (0.0, 0.05, 0.3, 0.99):
        values = [axis_to_ros(r, dz) for r in range(-32768, 32768, 97)]
        assert max(values) <= 1.0 and min(values) >= -1.0


@pytest.mark.parametrize(('hat', 'expected'), [
    ((0, 0), (0.0, 0.0)), ((-1, 0), (1.0, 0.0)), ((1, 0), (-1.0, 0.0)),
    ((0, 1), (0.0, 1.0)), ((1, -1), (-1.0, -1.0)),
])
def test_hat_to_ros(hat, expected):
    assert hat_to_ros(*hat) == expected


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'deadzone': 1.0}, r'deadzone must be in \[0.0, 1.0\), found 1.0'),
    ({'deadzone': -0.1}, 'deadzone must be in'),
    ({'autorepeat_rate': -1.0}, r'autorepeat_rate must be in \[0.0, 1000.0\] Hz'),
    ({'autorepeat_rate': 1001.0}, 'autorepeat_rate must be in'),
    ({'coalesce_interval': math.nan}, 'coalesce_interval must be >= 0 s, found nan'),
])
def test_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        JoyConfig(**kwargs)


def _sample(axes=(0, 0), buttons=(False, False), hats=((0, 0),)):
    return JoySample(tuple(axes), tuple(buttons), tuple(hats))


def test_first_reading_publishes_with_hats_appended():
    f = JoyFilter(JoyConfig(autorepeat_rate=0.0))
    out = f.update(_sample(axes=(32767, 0), hats=((0, 1),)), 0.0)
    assert out == JoyOutput((-1.0, 0.0, 0.0, 1.0), (0, 0))


def test_button_change_publishes_immediately_and_unchanged_state_does_not():
    f = JoyFilter(JoyConfig(autorepeat_rate=0.0, coalesce_interval=0.05))
    f.update(_sample(), 0.0)
    assert f.update(_sample(), 0.01) is None
    out = f.update(_sample(buttons=(True, False)), 0.02)
    assert out is not None and out.buttons == (1, 0)
    assert f.update(_sample(buttons=(True, False)), 0.03) is None


def test_axis_changes_are_coalesced():
    f = JoyFilter(JoyConfig(autorepeat_rate=0.0, coalesce_interval=0.05))
    f.update(_sample(), 0.0)
    assert f.update(_sample(axes=(1000, 2000)), 1.00) is None     # change starts the window
    assert f.update(_sample(axes=(5000, 2000)), 1.02) is None     # merged
    out = f.update(_sample(axes=(8000, 2000)), 1.05)
    assert out is not None and out.axes[0] == pytest.approx(axis_to_ros(8000, 0.05))
    assert f.update(_sample(axes=(8000, 2000)), 1.2) is None


def test_zero_coalesce_publishes_every_axis_change():
    f = JoyFilter(JoyConfig(autorepeat_rate=0.0, coalesce_interval=0.0))
    f.update(_sample(), 0.0)
    assert f.update(_sample(axes=(9000, 0)), 0.001) is not None


def test_autorepeat_republishes_unchanged_state_at_the_rate():
    f = JoyFilter(JoyConfig(autorepeat_rate=20.0))
    times = [i * 0.01 for i in range(101)]  # 1 s of 100 Hz polling
    published = [t for t in times if f.update(_sample(), t) is not None]
    assert len(published) == 21  # t = 0, 0.05, ..., 1.0
    assert published[1] == pytest.approx(0.05)


def test_sticky_buttons_toggle_on_press():
    f = JoyFilter(JoyConfig(autorepeat_rate=0.0, sticky_buttons=True))
    f.update(_sample(), 0.0)
    assert f.update(_sample(buttons=(True, False)), 0.1).buttons == (1, 0)
    assert f.update(_sample(buttons=(False, False)), 0.2) is None
    assert f.update(_sample(buttons=(True, False)), 0.3).buttons == (0, 0)


def test_fake_gamepad_and_factory():
    pad = FakeGamepad(n_axes=2, n_buttons=3, n_hats=0)
    factory = FakeGamepadFactory(None)
    with pytest.raises(GamepadNotFoundError, match='device_id 0'):
        factory(0, '')
    factory.gamepad = pad
    assert factory(0, '') is pad
    with pytest.raises(GamepadNotFoundError, match="named 'Other'"):
        factory(0, 'Other')
    pad.set(axes=(1, -1), buttons=(True, False, False))
    assert pad.read() == JoySample((1, -1), (True, False, False), ())
    pad.plugged = False
    with pytest.raises(DeviceDisconnectedError, match='unplugged'):
        pad.read()


def test_sdl_reports_missing_device_clearly():
    # No gamepad is plugged into the test machines; SDL must say so, not crash.
    with pytest.raises(GamepadNotFoundError, match='expected a gamepad with device_id 7'):
        SdlGamepad.open(7, '')
    with pytest.raises(GamepadNotFoundError, match="named 'No Such Pad'"):
        SdlGamepad.open(0, 'No Such Pad')

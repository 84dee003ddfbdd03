"""Teleop deadman behaviour, caps and bend modes."""

import math

import pytest

from catheter_driver.core.teleop import Teleop, TeleopConfig, TeleopOutput
from catheter_driver.exceptions import CommandError

CFG = TeleopConfig(enable_button=0, axis_insertion=1, axis_bend_alpha=2, axis_bend_gamma=3,
                   scale_insertion=0.005, scale_bend=1.0)
HELD, RELEASED = [1, 0], [0, 0]


def test_no_output_until_the_deadman_is_held():
    t = Teleop(CFG)
    assert t.on_joy([0, 1.0, 0, 0], RELEASED, 0.0) == TeleopOutput()
    assert not t.enabled


def test_held_deadman_commands_then_one_stop_then_quiet():
    t = Teleop(CFG)
    out = t.on_joy([0, 0.5, 0, 0], HELD, 0.0)
    assert out.insertion_velocity == pytest.approx(0.0025) and out.bend == (0.0, 0.0)
    out = t.on_joy([0, -1.0, 0, 0], HELD, 0.05)
    assert out.insertion_velocity == pytest.approx(-0.005)
    assert t.on_joy([0, 1.0, 0, 0], RELEASED, 0.10) == TeleopOutput(insertion_velocity=0.0)
    for k in range(5):
        assert t.on_joy([0, 1.0, 0, 0], RELEASED, 0.15 + 0.05 * k) == TeleopOutput()


def test_rate_mode_integrates_and_holds_bend_across_release():
    t = Teleop(CFG)
    t.on_joy([0, 0, 1.0, -0.5], HELD, 0.0)          # enabling message: no integration
    out = t.on_joy([0, 0, 1.0, -0.5], HELD, 0.05)
    assert out.bend == pytest.approx((0.05, -0.025))
    out = t.on_joy([0, 0, 1.0, -0.5], HELD, 10.0)   # long gap: step capped at max_dt
    assert out.bend == pytest.approx((0.15, -0.075))
    t.on_joy([0, 0, 0, 0], RELEASED, 10.05)
    assert t.on_joy([0, 0, 0, 0], HELD, 20.0).bend == pytest.approx((0.15, -0.075))


def test_bend_and_speed_caps_hold_whatever_the_input():
    t = Teleop(CFG)
    now = 0.0
    for _ in range(200):
        now += 0.1
        out = t.on_joy([0, 1.0, 1.0, -1.0], HELD, now)
        assert abs(out.insertion_velocity) <= 0.005
        assert math.hypot(*out.bend) <= math.pi / 2 + 1e-12
    # the total bend saturates at pi/2 along the commanded diagonal
    assert out.bend == pytest.approx((math.pi / 2 / math.sqrt(2), -math.pi / 2 / math.sqrt(2)))


def test_position_mode_maps_axes_to_angles():
    t = Teleop(TeleopConfig(enable_button=0, axis_insertion=1, axis_bend_alpha=2,
                            axis_bend_gamma=3, bend_mode='position', scale_bend=math.pi / 2))
    # within the cap: the axes map linearly
    assert t.on_joy([0, 0, 0.5, -0.5], HELD, 0.0).bend == pytest.approx(
        (math.pi / 4, -math.pi / 4))
    # beyond it: scaled onto hypot = pi/2, direction kept
    alpha, gamma = t.on_joy([0, 0, 0.5, -1.0], HELD, 0.1).bend
    assert math.hypot(alpha, gamma) == pytest.approx(math.pi / 2)
    assert gamma / alpha == pytest.approx(-2.0)


def test_joy_timeout_sends_one_stop():
    t = Teleop(CFG)
    t.on_joy([0, 1.0, 0, 0], HELD, 0.0)
    assert t.on_tick(0.4) == TeleopOutput()
    assert t.on_tick(0.6) == TeleopOutput(insertion_velocity=0.0)
    assert t.on_tick(0.7) == TeleopOutput()


@pytest.mark.parametrize(('axes', 'buttons', 'match'), [
    ([0, 1.0], HELD, 'expected at least 4 Joy axes, found 2'),
    ([0, 1.0, 0, 0], [], 'expected at least 1 Joy buttons, found 0'),
    ([0, math.nan, 0, 0], HELD, 'expected Joy axis 1 finite in'),
    ([0, 0, 1.5, 0], HELD, r'expected Joy axis 2 finite in \[-1, 1\], found 1.5'),
])
def test_malformed_joy_is_rejected_and_fails_safe(axes, buttons, match):
    t = Teleop(CFG)
    t.on_joy([0, 1.0, 0, 0], HELD, 0.0)
    with pytest.raises(CommandError, match=match):
        t.on_joy(axes, buttons, 0.05)
    assert t.on_invalid() == TeleopOutput(insertion_velocity=0.0)
    assert t.on_invalid() == TeleopOutput()


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'scale_insertion': 0.01}, r'scale_insertion must satisfy'),
    ({'scale_insertion': 0.0}, r'scale_insertion must satisfy'),
    ({'max_insertion_speed': 0.006}, r'max_insertion_speed must be in \(0, 0.005\]'),
    ({'max_bend': 2.0}, r'max_bend must be in \(0, pi/2\] rad, found 2.0'),
    ({'bend_mode': 'torque'}, "bend_mode must be 'rate' or 'position', found 'torque'"),
    ({'bend_mode': 'position', 'scale_bend': 2.0}, 'scale_bend must satisfy'),
    ({'enable_button': -1}, 'enable_button must be an index >= 0, found -1'),
    ({'axis_bend_alpha': 1}, 'must differ'),
    ({'joy_timeout': 0.0}, 'joy_timeout must be a finite number > 0 s'),
])
def test_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TeleopConfig(**kwargs)

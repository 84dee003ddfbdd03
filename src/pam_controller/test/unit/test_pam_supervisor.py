"""Supervisor: slew limit, caps, watchdog, e-stop, rejection, backoff (explicit clock)."""

import contextlib
import math

import numpy as np
import pytest

from pam_controller.core.bending_model import BendingModel, BendingModelConfig
from pam_controller.core.supervisor import (
    Backoff,
    BankMode,
    PamSupervisor,
    Phase,
    SupervisorConfig,
)
from pam_controller.errors import CommandRejectedError


def make(**kwargs) -> PamSupervisor:
    return PamSupervisor(BendingModel(), SupervisorConfig(**kwargs), now=0.0)


def test_starts_vented_and_idle():
    sup = make()
    out = sup.tick(0.01)
    np.testing.assert_array_equal(out.setpoints_pa, np.zeros(4))
    assert out.mode is BankMode.IDLE and out.phase is Phase.WAITING


def test_setpoints_ramp_at_the_rate_limit():
    sup = make(max_pressure_rate_pa_s=100e3)
    target = sup.command([0.0, 0.0], now=0.0)          # all chambers to the 150 kPa bias
    np.testing.assert_array_equal(target, np.full(4, 150e3))
    out = sup.tick(0.1)
    np.testing.assert_allclose(out.setpoints_pa, np.full(4, 10e3))
    assert out.mode is BankMode.RUN and out.phase is Phase.ACTIVE
    sup.command([0.0, 0.0], now=0.4)
    out = sup.tick(0.5)
    np.testing.assert_allclose(out.setpoints_pa, np.full(4, 50e3))


def test_setpoints_reach_target_and_never_overshoot():
    sup = make(max_pressure_rate_pa_s=1e6)
    target = sup.command([1.0, -0.5], now=0.0)
    t = 0.0
    for _ in range(30):
        t += 0.02
        sup.command([1.0, -0.5], now=t)
        out = sup.tick(t)
        assert np.all(out.setpoints_pa <= np.maximum(target, 0.0) + 1e-9)
    np.testing.assert_allclose(out.setpoints_pa, target)


def test_watchdog_vents_stale_commands_and_waits_for_fresh_one():
    sup = make(command_timeout_s=0.2, max_pressure_rate_pa_s=1e7)
    sup.command([0.5, 0.5], now=0.0)
    assert sup.tick(0.1).phase is Phase.ACTIVE
    assert np.all(sup.setpoints_pa > 0)
    out = sup.tick(0.25)
    assert out.phase is Phase.STALE
    np.testing.assert_array_equal(out.setpoints_pa, np.zeros(4))
    assert out.mode is BankMode.IDLE
    assert sup.tick(5.0).phase is Phase.STALE       # stays vented
    sup.command([0.0, 0.0], now=5.0)
    assert sup.tick(5.01).phase is Phase.ACTIVE


def test_watchdog_vents_to_configured_safe_pressure_in_run_mode():
    sup = make(command_timeout_s=0.1, vent_pressure_pa=20e3)
    sup.command([0.3, 0.0], now=0.0)
    out = sup.tick(0.2)
    np.testing.assert_array_equal(out.setpoints_pa, np.full(4, 20e3))
    assert out.mode is BankMode.RUN


def test_estop_vents_refuses_and_release_stays_vented():
    sup = make(max_pressure_rate_pa_s=1e7)
    sup.command([0.5, 0.0], now=0.0)
    sup.tick(0.1)
    sup.engage_estop()
    out = sup.tick(0.11)
    assert out.mode is BankMode.VENT and out.phase is Phase.ESTOP
    np.testing.assert_array_equal(out.setpoints_pa, np.zeros(4))
    with pytest.raises(CommandRejectedError, match='e-stop is engaged'):
        sup.command([0.1, 0.0], now=0.12)
    assert sup.rejected_count == 1
    sup.release_estop()
    out = sup.tick(0.2)
    assert out.phase is Phase.WAITING
    np.testing.assert_array_equal(out.setpoints_pa, np.zeros(4))
    sup.command([0.1, 0.0], now=0.3)
    assert sup.tick(0.31).phase is Phase.ACTIVE


@pytest.mark.parametrize('bend', [[float('nan'), 0.0], [0.0, -float('inf')], [1.5, 1.5]])
def test_bad_command_rejected_nothing_changes(bend):
    sup = make(max_pressure_rate_pa_s=1e7)
    sup.command([0.2, 0.1], now=0.0)
    before = sup.target_pa
    with pytest.raises(CommandRejectedError):
        sup.command(bend, now=0.05)
    np.testing.assert_array_equal(sup.target_pa, before)
    assert sup.rejected_count == 1 and 'expected' in sup.last_rejection
    # The rejected command does not feed the watchdog either.
    assert sup.tick(0.6).phase is Phase.STALE


def test_pressure_cap_holds_for_any_accepted_command_sequence():
    cfg = BendingModelConfig(max_pressure_pa=200e3, bias_pressure_pa=100e3,
                             max_bend_rad=math.pi / 2)
    sup = PamSupervisor(BendingModel(cfg), SupervisorConfig(max_pressure_rate_pa_s=1e7), 0.0)
    rng = np.random.default_rng(3)
    t = 0.0
    for _ in range(400):
        t += 0.02
        bend = rng.uniform(-2.0, 2.0, 2)
        with contextlib.suppress(CommandRejectedError):
            sup.command(bend, now=t)
        out = sup.tick(t)
        assert out.setpoints_pa.max() <= 200e3 and out.setpoints_pa.min() >= 0.0


def test_vent_pressure_outside_limits_raises():
    with pytest.raises(ValueError, match='vent_pressure_pa must be in'):
        make(vent_pressure_pa=350e3)


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'command_timeout_s': 0.0}, 'command_timeout_s must be in'),
    ({'max_pressure_rate_pa_s': -1.0}, 'max_pressure_rate_pa_s must be in'),
    ({'vent_pressure_pa': float('nan')}, 'vent_pressure_pa must be'),
])
def test_bad_supervisor_config_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SupervisorConfig(**kwargs)


def test_backoff_doubles_caps_and_resets():
    b = Backoff(0.1, 0.5)
    assert b.due(0.0)
    assert [b.failed(0.0) for _ in range(5)] == [0.1, 0.2, 0.4, 0.5, 0.5]
    assert not b.due(0.4) and b.due(0.5)
    assert b.seconds_to_next(0.3) == pytest.approx(0.2)
    b.succeeded()
    assert b.attempts == 0 and b.due(0.0) and b.failed(1.0) == 0.1
    with pytest.raises(ValueError, match='max_s must be >= initial_s'):
        Backoff(1.0, 0.5)

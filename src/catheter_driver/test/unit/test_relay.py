"""Relay state machine: the never-ungripped invariant, the speed cap and position tracking."""

import itertools
import math

import numpy as np
import pytest

from catheter_driver.core.mechanism import SleeveMechanism
from catheter_driver.core.relay import (
    ActuatorCommand,
    catheter_velocity,
    clamp_velocity,
    GripperState,
    Phase,
    RelayConfig,
    RelayController,
    SleeveFeedback,
)

CFG = RelayConfig()


def _loop(cfg, velocities, dts, estops=None):
    """Run controller + mechanism; yield (controller, mechanism, command) after every step.

    The controller's tracked position refers to the feedback it was given, i.e. to the
    mechanism before the step; ``mech.tracked_reference`` keeps that value for the tests.
    """
    mech = SleeveMechanism(cfg)
    ctrl = RelayController(cfg, mech.feedback())
    for i, (v, dt) in enumerate(zip(velocities, dts, strict=True)):
        if estops is not None:
            ctrl.set_estop(bool(estops[i]))
        mech.tracked_reference = mech.catheter_position
        cmd = ctrl.step(float(v), mech.feedback(), float(dt))
        mech.step(cmd, float(dt))
        yield ctrl, mech, cmd


def _random_velocities(rng, n):
    """Piecewise-constant random commands, including zero, the cap and far out of range."""
    out = np.empty(n)
    i = 0
    while i < n:
        length = int(rng.integers(1, 120))
        kind = rng.integers(0, 5)
        if kind == 0:
            v = 0.0
        elif kind == 1:
            v = float(rng.choice([-1.0, 1.0, 1.0])) * CFG.max_speed  # drift inwards
        elif kind == 2:
            v = float(rng.uniform(-1.0, 1.0)) * 10.0  # far beyond the cap
        elif kind == 3:
            v = float(rng.choice([-math.inf, math.inf]))
        else:
            v = float(rng.uniform(-CFG.max_speed, CFG.max_speed))
        out[i:i + length] = v
        i += length
    return out


@pytest.mark.parametrize('seed', range(40))
def test_invariants_hold_for_random_velocity_sequences(seed):
    rng = np.random.default_rng(seed)
    n = 2500
    cfg = RelayConfig(stroke_max=float(rng.uniform(0.004, 0.015)),
                      position_max=float(rng.uniform(0.05, 0.3)),
                      gripper_close_time=float(rng.uniform(0.02, 0.3)),
                      gripper_open_time=float(rng.uniform(0.02, 0.3)))
    velocities = _random_velocities(rng, n)
    dts = rng.uniform(0.002, 0.06, n)
    estops = rng.random(n) < 0.004
    estops = np.convolve(estops, np.ones(25), mode='same') > 0  # e-stop held for a while
    phases = set()
    for ctrl, mech, cmd in _loop(cfg, velocities, dts, estops):
        phases.add(ctrl.phase)
        assert mech.min_held >= 1, 'both grippers released the catheter'
        assert abs(mech.catheter_velocity) <= cfg.max_speed * (1 + 1e-9)
        assert not mech.interlock, f'sleeve commanded to move in phase {ctrl.phase.name}'
        assert cfg.position_min - 1e-9 <= mech.catheter_position <= cfg.position_max + 1e-9
        assert ctrl.position == pytest.approx(mech.tracked_reference, abs=1e-9)
        if ctrl.estop:
            assert cmd.sleeve_velocity == 0.0
    assert phases == set(Phase), f'a random run should visit every phase, saw {phases}'


def test_continuous_insertion_goes_past_the_stroke_and_back():
    dt = 0.01
    n = 6000  # 60 s at 5 mm/s would be 0.3 m without relay pauses
    run = list(_loop(CFG, [1.0] * n, [dt] * n))  # 1 m/s is clamped to 5 mm/s
    ctrl = run[-1][0]
    phases = [c.phase for c, _, _ in _loop(CFG, [1.0] * n, [dt] * n)]
    relays = sum(1 for a, b in itertools.pairwise(phases)
                 if a == Phase.DRIVE and b == Phase.CLOSE_FIXED)
    assert ctrl.position > 5 * (CFG.stroke_max - CFG.stroke_min)
    assert relays >= 5
    # Cycle: 30 mm at 5 mm/s (6 s) + 4 gripper moves (0.6 s) + 30 mm at 20 mm/s (1.5 s) plus
    # one control period of latency per phase change.
    mean_rate = ctrl.position / (n * dt)
    assert 0.7 * CFG.max_speed < mean_rate < CFG.max_speed
    back = list(_loop(CFG, [-0.005] * n, [dt] * n))
    assert back[-1][1].catheter_position == pytest.approx(CFG.position_min, abs=1e-9)


def test_retraction_stops_at_position_min_and_insertion_at_position_max():
    cfg = RelayConfig(position_max=0.05)
    run = list(_loop(cfg, [0.005] * 3000, [0.01] * 3000))
    assert run[-1][1].catheter_position == pytest.approx(0.05, abs=1e-9)
    assert run[-1][0].phase == Phase.DRIVE  # no useless relay at the end of travel
    run = list(_loop(cfg, [-0.005] * 300, [0.01] * 300))
    assert run[-1][1].catheter_position == 0.0


def test_startup_grasps_with_both_before_opening_fixed():
    mech = SleeveMechanism(CFG)
    ctrl = RelayController(CFG, mech.feedback())
    cmd = ctrl.step(0.005, mech.feedback(), 0.01)
    assert cmd == ActuatorCommand(0.0, moving_close=True, fixed_close=True)
    assert ctrl.phase == Phase.CLOSE_MOVING


def test_open_moving_waits_for_measured_fixed_closed():
    ctrl = RelayController(CFG, SleeveFeedback(CFG.stroke_max, GripperState.CLOSED,
                                                GripperState.OPEN))
    ctrl._set_phase(Phase.OPEN_MOVING)  # as if the device had lost the fixed gripper
    cmd = ctrl.step(0.005, SleeveFeedback(CFG.stroke_max, GripperState.CLOSED,
                                          GripperState.CLOSING), 0.01)
    assert cmd.moving_close and cmd.fixed_close
    assert ctrl.phase == Phase.CLOSE_FIXED


def test_gripper_that_never_closes_is_reported_and_catheter_stays_held():
    fb = SleeveFeedback(0.0, GripperState.OPEN, GripperState.CLOSED)
    ctrl = RelayController(CFG, fb)
    for _ in range(150):
        cmd = ctrl.step(0.005, fb, 0.01)  # moving gripper stuck open
        assert cmd.fixed_close and cmd.sleeve_velocity == 0.0
    assert ctrl.fault is not None
    assert 'CLOSE_MOVING' in ctrl.fault and 'moving OPEN' in ctrl.fault


def test_estop_freezes_sleeve_and_phase():
    run = list(_loop(CFG, [0.005] * 200, [0.01] * 200, estops=[0] * 100 + [1] * 100))
    frozen = run[100][0].phase
    for ctrl, mech, cmd in run[101:]:
        assert cmd.sleeve_velocity == 0.0 and mech.catheter_velocity == 0.0
        assert ctrl.phase == frozen


def test_catheter_velocity_follows_the_sleeve_only_when_coupled():
    drive = SleeveFeedback(0.01, GripperState.CLOSED, GripperState.OPEN)
    assert catheter_velocity(drive, 0.004) == 0.004
    for moving, fixed in [(GripperState.OPEN, GripperState.CLOSED),
                          (GripperState.CLOSED, GripperState.CLOSED),
                          (GripperState.CLOSED, GripperState.OPENING)]:
        assert catheter_velocity(SleeveFeedback(0.01, moving, fixed), 0.02) == 0.0


def test_clamp_velocity():
    assert clamp_velocity(1.0, 0.005) == 0.005
    assert clamp_velocity(-math.inf, 0.005) == -0.005
    assert clamp_velocity(0.001, 0.005) == 0.001
    with pytest.raises(ValueError, match='expected a finite velocity, found nan'):
        clamp_velocity(math.nan, 0.005)


def test_step_rejects_nan_and_bad_dt():
    ctrl = RelayController(CFG, SleeveFeedback(0.0, GripperState.OPEN, GripperState.CLOSED))
    fb = SleeveFeedback(0.0, GripperState.OPEN, GripperState.CLOSED)
    with pytest.raises(ValueError, match='finite velocity'):
        ctrl.step(math.nan, fb, 0.01)
    with pytest.raises(ValueError, match=r'dt must be a finite number > 0, found 0\.0'):
        ctrl.step(0.0, fb, 0.0)


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'max_speed': 0.006}, r'max_speed must be <= 0.005 m/s'),
    ({'max_speed': 0.0}, r'max_speed must be a finite number > 0, found 0.0'),
    ({'return_speed': math.nan}, r'return_speed must be a finite number > 0'),
    ({'stroke_max': 0.0}, r'stroke_max must exceed stroke_min'),
    ({'position_max': -1.0}, r'position_max must be > position_min'),
    ({'stroke_min': math.inf}, r'stroke_min must be finite'),
    ({'gripper_timeout': 0.1}, r'gripper_timeout must exceed'),
])
def test_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RelayConfig(**kwargs)


def test_mechanism_interlock_refuses_motion_with_both_closed():
    mech = SleeveMechanism(CFG)
    for _ in range(30):
        mech.step(ActuatorCommand(0.0, True, True), 0.01)
    mech.step(ActuatorCommand(0.005, True, True), 0.01)
    assert mech.interlock and mech.sleeve_position == CFG.stroke_min

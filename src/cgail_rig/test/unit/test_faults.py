"""Fault injection's pure logic (cgail_rig.core.faults): the plan from the seed, the push, the
sleeve slip, the cap monitor."""

import math

import numpy as np
import pytest

from cgail_rig.core.faults import (
    CapMonitor,
    Caps,
    DETECTION_BOUNDS_S,
    Fault,
    FAULT_KINDS,
    FaultConfig,
    plan_fault,
    push_direction,
    push_offset,
    SleeveSlip,
)


def test_every_kind_has_a_detection_bound() -> None:
    assert set(DETECTION_BOUNDS_S) == set(FAULT_KINDS)
    assert all(b > 0.0 for b in DETECTION_BOUNDS_S.values())


@pytest.mark.parametrize('kind', FAULT_KINDS)
def test_plan_is_a_function_of_the_seed_within_the_onset_window(kind: str) -> None:
    cfg = FaultConfig()
    faults = [plan_fault(kind, seed, 1.0) for seed in range(40)]
    assert faults == [plan_fault(kind, seed, 1.0) for seed in range(40)]
    onsets = [f.onset_s for f in faults]
    assert all(1.0 + cfg.onset_min_s <= t <= 1.0 + cfg.onset_max_s for t in onsets)
    assert len(set(onsets)) == 40  # drawn, not fixed
    assert all(f.kind == kind for f in faults)


def test_plan_of_each_kind() -> None:
    cfg = FaultConfig()
    dropout = plan_fault('dropout', 3, 0.0)
    assert dropout.duration_s == cfg.dropout_s
    slip = plan_fault('slipping_sleeve', 3, 0.0)
    assert slip.duration_s == cfg.slip_s
    stuck = [plan_fault('stuck_pam', s, 0.0) for s in range(40)]
    assert {f.channel for f in stuck} == {0, 1, 2, 3}
    assert all(f.duration_s == math.inf for f in stuck)
    push = plan_fault('wall_push', 3, 0.0)
    assert (push.push_m, push.ramp_s, push.duration_s) == (cfg.push_m, cfg.push_ramp_s, math.inf)
    assert -math.pi <= push.angle <= math.pi


@pytest.mark.parametrize(('args', 'match'), [
    (('flood', 0, 1.0), r"fault: expected one of \('dropout', .*\), found 'flood'"),
    (('dropout', -1, 1.0), r'seed: expected an integer >= 0, found -1'),
])
def test_plan_refuses_bad_input(args: tuple, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        plan_fault(*args)


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('push_m', 0.0, r'push_m: expected a number in \(0, 0.1\], found 0.0'),
    ('dropout_s', math.nan, r'dropout_s: expected a number in \(0, 60\], found nan'),
    ('onset_max_s', 1.0, r'onset_max_s: expected >= onset_min_s \(3.0\), found 1.0'),
])
def test_config_refuses_out_of_range(field: str, value: float, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        FaultConfig(**{field: value})


def test_active_between_onset_and_end() -> None:
    f = Fault('dropout', 2.0, 1.0)
    assert [f.active(t) for t in (1.99, 2.0, 2.5, 2.99, 3.0)] == [False, True, True, True, False]


def test_push_ramps_perpendicular_to_the_heading_then_holds() -> None:
    rotation = np.eye(3)  # heading y
    direction = push_direction(rotation, math.pi / 2)
    np.testing.assert_allclose(direction, [0.0, 0.0, 1.0], atol=1e-15)
    assert abs(push_direction(rotation, 0.7) @ rotation[:, 1]) < 1e-15
    f = Fault('wall_push', 5.0, math.inf, push_m=0.02, ramp_s=0.1)
    assert push_offset(f, 4.9, direction).tolist() == [0.0, 0.0, 0.0]
    np.testing.assert_allclose(push_offset(f, 5.05, direction), [0.0, 0.0, 0.01], atol=1e-12)
    np.testing.assert_allclose(push_offset(f, 9.0, direction), [0.0, 0.0, 0.02], atol=1e-12)
    assert push_offset(Fault('dropout', 5.0, 1.0), 6.0, direction).tolist() == [0.0] * 3


def test_a_slipping_grip_transmits_nothing_and_resumes_without_a_jump() -> None:
    slip = SleeveSlip()
    grip = [0.0, 0.001, 0.002, 0.003, 0.004, 0.005]
    slipping = [False, False, True, True, False, False]
    out = [slip.transmit(g, s) for g, s in zip(grip, slipping, strict=True)]
    assert out == pytest.approx([0.0, 0.001, 0.001, 0.001, 0.002, 0.003])
    assert slip.transmit(None, True) is None


def test_cap_monitor_keeps_the_largest_and_names_what_exceeded() -> None:
    caps = CapMonitor(Caps(max_insertion_speed=0.005, max_bend=1.0, max_pressure_pa=300e3))
    caps.observe(0.025, 0.0001, (0.6, 0.8), np.array([1e5, 0.0, 2e5, 0.0]))
    assert caps.exceeded() == []
    assert caps.max_speed == pytest.approx(0.004) and caps.max_bend == pytest.approx(1.0)
    caps.observe(0.025, -0.0002, (1.2, 0.0), np.array([0.0, 3.1e5, 0.0, 0.0]))
    assert caps.exceeded() == ['tip speed 8.00 mm/s > 5.00 mm/s', 'bend 1.200 rad > 1.000 rad',
                               'pressure 310.0 kPa > 300.0 kPa']

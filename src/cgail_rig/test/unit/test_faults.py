"""Fault injection's pure logic (cgail_rig.core.faults): the plan from the seed, the push, the
sleeve slip, the cap monitor, the detection time; the session's fault record and its report
rows (cgail_rig.session, no rig)."""

import math

import numpy as np
import pytest

from cgail_rig.core.faults import (
    CapMonitor,
    Caps,
    DETECTION_BOUNDS_S,
    detection_time,
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


def test_the_other_kinds_keep_their_bounds() -> None:
    assert {k: b for k, b in DETECTION_BOUNDS_S.items() if k != 'stuck_pam'} == {
        'dropout': 0.35, 'slipping_sleeve': 6.5, 'wall_push': 0.3}
    # stuck_pam: the chain bank -> pam_controller -> autonomy, from when it became observable
    assert DETECTION_BOUNDS_S['stuck_pam'] == 1.25


@pytest.mark.parametrize(('kind', 'onset', 'stop', 'observable', 'expected'), [
    ('dropout', 10.0, 10.27, math.nan, 0.27),
    ('wall_push', 10.0, 10.05, 11.0, 0.05),  # (observable: stuck_pam's only)
    ('dropout', 10.0, 9.0, math.nan, math.nan),  # stopped before the onset
    ('dropout', 10.0, math.nan, math.nan, math.nan),  # no stop
    ('dropout', math.nan, 9.0, math.nan, math.nan),  # the trial ended before the onset
    ('stuck_pam', 10.0, 31.0, 30.0, 1.0),  # from observable, not from the onset
    ('stuck_pam', 10.0, 12.0, 30.0, 0.0),  # stopped after the onset, before observable
    ('stuck_pam', 10.0, 12.0, math.nan, 0.0),  # stopped after the onset, never observable
    ('stuck_pam', 10.0, 9.0, math.nan, math.nan),  # stopped before the onset
    ('stuck_pam', 10.0, math.nan, 30.0, math.nan),  # not stopped
])
def test_detection_time(kind: str, onset: float, stop: float, observable: float,
                        expected: float) -> None:
    got = detection_time(kind, onset, stop, observable)
    if math.isnan(expected):
        assert math.isnan(got)
    else:
        assert got == pytest.approx(expected, abs=1e-12)


def _stuck(onset: float, stop: float, observable: float, reason: str = 'device_fault'):
    from cgail_rig import session as s

    return s.FaultRecord('stuck_pam', onset, reason if stop == stop else '',
                         detection_time('stuck_pam', onset, stop, observable),
                         DETECTION_BOUNDS_S['stuck_pam'], observable - onset)


@pytest.mark.parametrize(('onset', 'stop', 'observable', 'caught', 'missed', 'never'), [
    (5.0, 7.0, 20.0, True, False, False),  # stopped (another reason) before observable
    (5.0, 7.0, math.nan, True, False, False),  # the same, never observable
    (5.0, 21.2, 20.0, True, False, False),  # within the bound after observable (was 16.2 s)
    (5.0, 21.3, 20.0, False, True, False),  # beyond the bound after observable: missed
    (5.0, math.nan, 20.0, False, True, False),  # observable, never stopped: missed
    (5.0, math.nan, math.nan, False, False, True),  # never observable, not stopped: neither
    (math.nan, math.nan, math.nan, False, False, False),  # the trial ended before the onset
])
def test_a_stuck_pam_is_caught_from_when_it_became_observable(
        onset: float, stop: float, observable: float, caught: bool, missed: bool,
        never: bool) -> None:
    f = _stuck(onset, stop, observable)
    assert (f.caught, f.missed, f.never_observable) == (caught, missed, never), f


def test_the_other_kinds_are_caught_from_the_onset_and_never_unobservable() -> None:
    from cgail_rig import session as s

    for stop, caught in ((5.3, True), (5.4, False), (math.nan, False)):
        f = s.FaultRecord('dropout', 5.0, 'tracking_lost' if stop == stop else '',
                          detection_time('dropout', 5.0, stop), DETECTION_BOUNDS_S['dropout'])
        assert (f.caught, f.missed, f.never_observable) == (caught, not caught, False), f
        assert math.isnan(f.observable_s)


def test_the_report_counts_never_observable_stuck_pams_apart() -> None:
    from cgail_rig import session as s

    def result(k: int, outcome: str, fault) -> s.TrialResult:
        spec = s.TrialSpec('autonomous', k, 0, 0, k, f'autonomous_{k + 1:02d}.mcap',
                           fault=fault.kind)
        return s.TrialResult(spec, outcome=outcome, fault=fault)

    results = [
        result(0, 'stopped:device_fault: regulator bank fault', _stuck(5.0, 21.0, 20.0)),
        result(1, 'stopped:path_deviation: 10.2 mm', _stuck(5.0, 7.0, math.nan, 'path_deviation')),
        result(2, 'at the target (1.2 mm)', _stuck(5.0, math.nan, math.nan)),
        result(3, 'stopped:device_fault: regulator bank fault', _stuck(6.0, 14.0, 12.0)),
        result(4, 'stopped:tracking_lost: no pose', s.FaultRecord(
            'dropout', 4.0, 'tracking_lost', 0.27, DETECTION_BOUNDS_S['dropout'])),
    ]
    lines = s.autonomy_report(results)
    text = '\n'.join(lines)
    # the end states count every trial as usual, the never observable one's arrival included
    assert '| autonomous | 5 | 1 | device_fault: 2, path_deviation: 1, tracking_lost: 1 | 0 |' \
        in lines
    assert 'never observable' in text and 'became observable' in text
    # caught: 1.0 s after observable (trial 1), 0 (trial 2, before); missed: 2.0 s (trial 4);
    # never observable: trial 3; onset to observable: 15 s and 6 s
    assert ('| stuck_pam | 4/4 | 2 | 1.000 | 2.000 | 1.25 | device_fault, path_deviation | '
            '**MISSED: autonomous_04** | 1 | 10.500 / 15.000 |') in lines, text
    assert '| dropout | 1/1 | 1 | 0.270 | 0.270 | 0.35 | tracking_lost | none | - | - |' in lines


def test_success_over_every_trial_counts_a_trial_without_metrics_as_a_failure() -> None:
    from types import SimpleNamespace

    from cgail_rig.session import success_over_every_trial

    trials = [SimpleNamespace(condition='shared', success=True) for _ in range(28)]
    trials += [SimpleNamespace(condition='cgail', success=True) for _ in range(29)]
    trials += [SimpleNamespace(condition='cgail', success=False)]
    outcomes = [('shared', k, 'at the target') for k in range(1, 29)]
    outcomes += [('shared', 29, 'no path: planning failed'), ('shared', 30, 'no path: x')]
    outcomes += [('cgail', k, 'at the target') for k in range(1, 31)]
    lines = success_over_every_trial(trials, outcomes)
    rows = {line.split('|')[1].strip(): line for line in lines if line.startswith('| ')}
    assert rows['shared'] == '| shared | 30 | 28 | 28 | 93 % [79-98] |'
    assert rows['cgail'] == '| cgail | 30 | 30 | 29 | 97 % [83-99] |'

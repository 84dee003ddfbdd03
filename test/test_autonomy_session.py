"""The simulated session's autonomy conditions and fault injection (issue 36), in process.

Default: one trial with each fault injected (each ends within ~15 simulated s of the goal):
the trial ends in a defined state, the supervisor caught the fault within its stated bound (a
stuck PAM's from when it became observable, recorded by the phantom), and no cap was exceeded
on the true plant. Slow (-m slow): one whole trial of each autonomy
condition, static, reaching its target.
"""

from pathlib import Path

import pytest

from cgail_rig import session as s
from cgail_rig.core.faults import DETECTION_BOUNDS_S, FAULT_KINDS


def _run(tmp_path: Path, conditions: tuple[str, ...], faults: tuple[str, ...] = (),
         trials: int = 1, time_limit: float = 180.0) -> list[s.TrialResult]:
    from cgail_rig.domain import reserve_domain

    settings = s.SessionSettings(policy=str(s.default_policy()), plant='true', plant_seed=0,
                                 time_limit=time_limit)
    specs = s.plan_trials(conditions, trials, 0, tmp_path / 'bags', faults=faults)
    lease = reserve_domain(env={})
    try:
        return s.run_trials(settings, specs, jobs=1, domain_id=lease.domain_id,
                            log_dir=tmp_path, on_result=lambda r: None)
    finally:
        lease.release()


def test_each_injected_fault_is_caught_within_its_bound_and_no_cap_is_exceeded(
        tmp_path: Path) -> None:
    results = _run(tmp_path, ('autonomous',), FAULT_KINDS, trials=len(FAULT_KINDS),
                   time_limit=60.0)
    assert [r.spec.fault for r in results] == list(FAULT_KINDS)
    for r in results:
        assert not r.failed and not r.callback_errors, (r.spec.label, r.outcome)
        assert r.outcome.startswith('stopped:'), (r.spec.fault, r.outcome)
        f = r.fault
        assert f is not None and f.kind == r.spec.fault and f.injected, (r.spec.label, f)
        assert f.caught and 0.0 <= f.detection_s <= DETECTION_BOUNDS_S[f.kind], (f, r.outcome)
        if f.kind == 'stuck_pam':  # stopped by the bank's flag: observable after the onset
            assert f.stop_reason == 'device_fault' and f.observable_s >= 0.0, f
            assert f.detection_s >= 0.5, f  # (the bank flags it stuck_detect_s after)
        else:
            assert f.observable_s != f.observable_s, f
        assert r.outcome.split(':')[1] == f.stop_reason
        assert r.caps_exceeded == [], (r.spec.label, r.caps_exceeded)
        assert 0.0 < r.caps[0] <= 0.005 and r.caps[2] <= 300e3, r.caps
    lines = s.autonomy_report(results)
    assert '| dropout | 1/1 | 1 |' in '\n'.join(lines)
    assert '**MISSED' not in '\n'.join(lines) and 'Caps exceeded: none.' in lines


def test_the_guided_conditions_take_no_fault_and_no_autonomy(tmp_path: Path) -> None:
    specs = s.plan_trials(('cgail', 'autonomous', 'shared'), 2, 0, tmp_path,
                          faults=('dropout', 'wall_push'))
    assert [(x.condition, x.fault) for x in specs] == [
        ('cgail', ''), ('cgail', ''), ('autonomous', 'dropout'), ('autonomous', 'wall_push'),
        ('shared', 'dropout'), ('shared', 'wall_push')]
    # the guided conditions' seeds are those of a session without the autonomy's
    assert [x.seed for x in specs[:2]] == [x.seed for x in s.plan_trials(('cgail',), 2, 0,
                                                                          tmp_path)]


def test_faults_need_an_autonomy_condition(tmp_path: Path, capsys) -> None:
    assert s.main(['--out', str(tmp_path), '--conditions', 'cgail', '--faults', 'dropout']) == 2
    assert ("--faults: expected an autonomy condition ('autonomous', 'autonomous-policy', "
            "'shared') in --conditions, found ['cgail']") in capsys.readouterr().err


@pytest.mark.slow
def test_each_autonomy_condition_ends_in_a_defined_state_within_the_caps(tmp_path: Path) -> None:
    """The path tracker reaches the target, alone and supervised; the policy controller ends
    at the target or in a supervisor stop with a reason code (it does not always reach)."""
    from cgail_planner.core.safety import STOP_REASONS

    results = _run(tmp_path, s.AUTONOMY_CONDITIONS)
    arrived = ('at the target', 'closest approach passed')
    for r in results:
        assert not r.failed and not r.callback_errors, (r.spec.label, r.outcome)
        if r.spec.condition == 'autonomous-policy':
            assert r.outcome.startswith(arrived) or r.outcome.split(':')[1] in STOP_REASONS, \
                r.outcome
        else:
            assert r.outcome.startswith(arrived), (r.spec.label, r.outcome)
        assert r.caps_exceeded == [] and r.fault is None, r.spec.label
    assert [r.spec.condition for r in results] == list(s.AUTONOMY_CONDITIONS)

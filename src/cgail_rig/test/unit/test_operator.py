"""Scripted operator: deadman, reaction delay, stick rate, protocol stops, look-ahead,
correction gain, stick overshoot, learning curve."""

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from cgail_planner.core.guidance import GuidanceConfig, PathFollower, suggested_bend
from cgail_planner.core.operator import (
    aimed_bend,
    OperatorConfig,
    Percept,
    PRACTICE_EXPONENT,
    ScriptedOperator,
    skill_after,
    step_overshoot,
)

#: An operator without the human imperfections: no noise, full correction, no stick dynamics.
QUIET = dict(stick_noise=0.0, correction_gain=1.0, stick_frequency=0.0)


def test_idle_operator_does_not_hold_the_deadman() -> None:
    op = ScriptedOperator(OperatorConfig(**QUIET))
    s = op.step(0.0)
    assert not s.deadman and (s.insertion, s.alpha, s.gamma) == (0.0, 0.0, 0.0)


def test_running_operator_holds_the_deadman_and_reacts_after_the_delay() -> None:
    op = ScriptedOperator(OperatorConfig(reaction_delay_s=0.25, max_stick_rate=100.0, **QUIET))
    op.start(0.0)
    op.perceive(Percept(t=0.0, bend=(0.5, 0.0), heading_error=0.0, distance=0.2))
    s = op.step(0.1)
    assert s.deadman and s.insertion == 0.0 and s.alpha == 0.0  # not seen yet
    s = op.step(0.3)
    assert s.insertion == pytest.approx(1.0)
    assert s.alpha == pytest.approx(0.5 / (math.pi / 2))


def test_stick_rate_is_bounded() -> None:
    op = ScriptedOperator(OperatorConfig(reaction_delay_s=0.0, max_stick_rate=2.0, **QUIET))
    op.start(0.0)
    op.step(0.0)
    op.perceive(Percept(t=0.0, bend=(0.0, 0.0), heading_error=0.0, distance=0.2))
    assert op.step(0.1).insertion == pytest.approx(0.2)
    assert op.step(0.2).insertion == pytest.approx(0.4)


def test_stops_at_the_target_and_releases_the_deadman() -> None:
    op = ScriptedOperator(OperatorConfig(reaction_delay_s=0.0, **QUIET))
    op.start(0.0)
    op.perceive(Percept(t=1.0, bend=(0.0, 0.0), heading_error=0.0, distance=0.0015))
    s = op.step(1.0)
    assert not s.deadman and op.state == 'done' and 'at the target' in op.reason


def test_stops_when_the_closest_approach_has_passed() -> None:
    op = ScriptedOperator(OperatorConfig(reaction_delay_s=0.0, **QUIET))
    op.start(0.0)
    for t, d in ((1.0, 0.006), (1.1, 0.005), (1.2, 0.0065), (1.3, 0.0075)):
        op.perceive(Percept(t=t, bend=(0.0, 0.0), heading_error=0.0, distance=d))
        s = op.step(t)
    assert not s.deadman and op.reason == 'closest approach passed (5.0 mm)'


def test_stops_at_the_time_limit() -> None:
    op = ScriptedOperator(OperatorConfig(time_limit_s=180.0, **QUIET))
    op.start(10.0)
    assert op.step(189.9).deadman
    assert not op.step(190.0).deadman and 'time limit' in op.reason


def test_bend_sticks_stay_inside_the_cap() -> None:
    op = ScriptedOperator(OperatorConfig(reaction_delay_s=0.0, max_stick_rate=100.0, **QUIET))
    op.start(0.0)
    op.step(0.0)
    op.perceive(Percept(t=0.0, bend=(1.5, 1.5), heading_error=0.0, distance=0.2))
    s = op.step(0.5)
    assert math.hypot(s.alpha, s.gamma) == pytest.approx(0.99)


def test_slows_down_near_the_target_and_when_turning() -> None:
    cfg = OperatorConfig(reaction_delay_s=0.0, max_stick_rate=100.0, **QUIET)
    op = ScriptedOperator(cfg)
    op.start(0.0)
    op.step(0.0)
    op.perceive(Percept(t=0.0, bend=(0.0, 0.0), heading_error=math.pi / 3, distance=0.015))
    s = op.step(1.0)
    assert s.insertion == pytest.approx(0.5 * (0.15 + 0.85 * 0.5))


def test_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match='epsilon must be >= stop_distance'):
        OperatorConfig(stop_distance=0.02, epsilon=0.01)
    with pytest.raises(ValueError, match=r'reaction_delay_s must be in \[0.0, 2.0\]'):
        OperatorConfig(reaction_delay_s=-1.0)
    with pytest.raises(ValueError, match=r'stick_damping must be in \(0.0, 0.99\], found 1.0'):
        OperatorConfig(stick_damping=1.0)
    with pytest.raises(ValueError, match=r'skill must be in \[0.0, 1.0\], found 1.5'):
        OperatorConfig(skill=1.5)


# ---------------------------------------------------------------------- imperfect following
def bend_step_response(cfg: OperatorConfig, bend: float, duration: float = 3.0,
                       dt: float = 0.001) -> np.ndarray:
    """alpha stick after a step of the shown bend from 0 to ``bend`` at t = 0 (no delay)."""
    op = ScriptedOperator(cfg)
    op.start(0.0)
    op.step(0.0)
    op.perceive(Percept(t=0.0, bend=(bend, 0.0), heading_error=0.0, distance=0.2))
    return np.array([op.step(k * dt).alpha for k in range(1, round(duration / dt) + 1)])


STEP = dict(reaction_delay_s=0.0, stick_noise=0.0, max_stick_rate=100.0)


@pytest.mark.parametrize('damping', [0.35, 0.6])
def test_a_bend_step_overshoots_by_the_documented_fraction(damping) -> None:
    cfg = OperatorConfig(stick_damping=damping, correction_gain=1.0, **STEP)
    alpha = bend_step_response(cfg, 0.3)
    final = 0.3 / cfg.bend_scale
    assert alpha[-1] == pytest.approx(final, rel=1e-3)          # settles on the aim
    assert alpha.max() / final - 1.0 == pytest.approx(step_overshoot(damping), rel=1e-3)


def test_documented_overshoots() -> None:
    assert step_overshoot(0.6) == pytest.approx(0.0948, abs=1e-4)    # practised
    assert step_overshoot(0.35) == pytest.approx(0.3092, abs=1e-4)   # first trial
    with pytest.raises(ValueError, match=r'damping must be in \(0, 1\)'):
        step_overshoot(1.0)


def test_a_larger_correction_overshoots_by_more() -> None:
    cfg = OperatorConfig(correction_gain=1.0, **STEP)
    small, large = (bend_step_response(cfg, b) for b in (0.1, 0.4))
    over_small = small.max() - small[-1]
    over_large = large.max() - large[-1]
    assert over_large == pytest.approx(4.0 * over_small, rel=1e-6)


def test_the_stick_peaks_at_the_documented_time() -> None:
    cfg = OperatorConfig(correction_gain=1.0, **STEP)
    alpha = bend_step_response(cfg, 0.3)
    omega_d = cfg.stick_frequency * math.sqrt(1.0 - cfg.stick_damping ** 2)
    assert (int(np.argmax(alpha)) + 1) * 0.001 == pytest.approx(math.pi / omega_d, abs=0.002)


@pytest.mark.parametrize('gain', [0.0, 0.7, 0.9])
def test_the_stick_settles_on_the_correction_gain_times_the_bend(gain) -> None:
    alpha = bend_step_response(OperatorConfig(correction_gain=gain, **STEP), 0.3)
    assert alpha[-1] == pytest.approx(gain * 0.3 / (math.pi / 2), abs=1e-6)
    if gain == 0.0:
        assert not alpha.any()                                    # the bend sticks never move


def test_the_stick_response_respects_the_rate_limit() -> None:
    cfg = OperatorConfig(reaction_delay_s=0.0, stick_noise=0.0, max_stick_rate=0.5,
                         correction_gain=1.0)
    alpha = bend_step_response(cfg, 1.0, duration=1.0, dt=0.05)
    assert np.abs(np.diff(np.concatenate([[0.0], alpha]))).max() <= 0.5 * 0.05 + 1e-12


def curved_path() -> PathFollower:
    """20 mm straight along +y, then a quarter circle of radius 30 mm towards +x."""
    straight = np.stack([np.zeros(21), np.linspace(0.0, 0.02, 21), np.zeros(21)], axis=1)
    phi = np.linspace(0.0, math.pi / 2, 60)[1:]
    arc = np.stack([0.03 * (1 - np.cos(phi)), 0.02 + 0.03 * np.sin(phi), 0 * phi], axis=1)
    return PathFollower(np.concatenate([straight, arc]))


def test_look_ahead_aims_beyond_the_waypoint_and_turns_early() -> None:
    path = curved_path()
    tip, rot = np.zeros(3), np.eye(3)                # at the start, heading +y
    waypoint = path.point_at(0.018)                  # still on the straight part
    shown = suggested_bend(tip, rot, waypoint, GuidanceConfig().segment_length,
                           GuidanceConfig().max_bend)[:2]
    assert shown == pytest.approx((0.0, 0.0), abs=1e-12)
    assert aimed_bend(path, tip, rot, waypoint, shown, 0.0) == shown
    alpha, gamma = aimed_bend(path, tip, rot, waypoint, shown, 0.010)
    aim = path.point_at(0.028)                       # 10 mm further on: in the curve
    expected = suggested_bend(tip, rot, aim, GuidanceConfig().segment_length,
                              GuidanceConfig().max_bend)[:2]
    assert (alpha, gamma) == pytest.approx(expected, rel=1e-9)
    assert alpha == pytest.approx(0.0, abs=1e-12) and gamma < -0.01   # turning towards +x


# ---------------------------------------------------------------------- learning curve
def test_skill_follows_the_power_law_of_practice() -> None:
    assert PRACTICE_EXPONENT == 1.0
    assert skill_after(0) == 0.0
    assert skill_after(10) == pytest.approx(10 / 11)                 # first measured trial
    assert skill_after(19) == pytest.approx(19 / 20)                 # last measured trial
    assert skill_after(3, exponent=0.5) == pytest.approx(0.5)
    levels = [skill_after(n) for n in range(60)]
    assert all(b > a for a, b in itertools.pairwise(levels)) and levels[-1] < 1.0
    with pytest.raises(ValueError, match='practice must be an integer >= 0, found -1'):
        skill_after(-1)


def test_every_skill_value_improves_monotonically_from_novice_to_practised() -> None:
    d = OperatorConfig()
    first, practised = (OperatorConfig(skill=s).proficiency() for s in (0.0, 1.0))
    assert first == pytest.approx((0.40, 0.05, 0.7, 0.35))
    assert practised == pytest.approx((d.reaction_delay_s, d.stick_noise, d.correction_gain,
                                       d.stick_damping))
    assert practised == pytest.approx((0.25, 0.02, 0.9, 0.6))
    curve = [OperatorConfig(skill=skill_after(n)).proficiency() for n in range(30)]
    for a, b in itertools.pairwise(curve):
        assert b.reaction_delay_s < a.reaction_delay_s and b.stick_noise < a.stick_noise
        assert b.correction_gain > a.correction_gain and b.stick_damping > a.stick_damping
    at_10 = curve[10]                                 # after the paper's 10 pre-training trials
    assert at_10.reaction_delay_s == pytest.approx(0.25 + 0.15 / 11)
    assert at_10.correction_gain == pytest.approx(0.9 - 0.2 / 11)


def test_the_skill_sets_the_reaction_delay() -> None:
    op = ScriptedOperator(OperatorConfig(skill=0.0, max_stick_rate=100.0, novice_stick_noise=0.0,
                                        **QUIET))
    op.start(0.0)
    op.step(0.0)
    op.perceive(Percept(t=0.0, bend=(0.0, 0.0), heading_error=0.0, distance=0.2))
    assert op.step(0.3).insertion == 0.0              # a novice has not reacted yet (0.4 s)
    assert op.step(0.45).insertion == pytest.approx(1.0)


def test_session_trials_carry_the_skill_after_their_practice() -> None:
    from cgail_rig.session import plan_trials

    specs = plan_trials(['cgail', 'centerline'], 3, 7, Path('/tmp/bags'), pretrain=10)
    assert [(s.condition, s.practice) for s in specs] == [
        ('cgail', 10), ('cgail', 11), ('cgail', 12),
        ('centerline', 10), ('centerline', 11), ('centerline', 12)]
    assert [s.skill for s in specs] == [skill_after(s.practice) for s in specs]
    # a trial's skill depends on its condition and index only, not on the others planned
    alone = plan_trials(['centerline'], 2, 7, Path('/tmp/bags'), pretrain=10)
    assert alone == specs[3:5]
    assert plan_trials(['cgail'], 1, 7, Path('/tmp/bags'), pretrain=0)[0].skill == 0.0


# ---------------------------------------------------------------- supervising (shared autonomy)
def _supervisor_run(deviations: list[float], dt: float = 0.05):
    from cgail_planner.core.operator import SupervisingOperator

    op = SupervisingOperator(OperatorConfig(reaction_delay_s=0.25), threshold=0.005,
                             bend_scale=0.5)
    op.start(0.0)
    out = []
    for k, deviation in enumerate(deviations):
        t = k * dt
        op.perceive(Percept(t=t, bend=(0.2, -0.1), heading_error=0.0, distance=0.05,
                            deviation=deviation))
        out.append(op.step(t))
    return op, out


def test_supervising_operator_holds_the_deadman_with_centred_sticks_on_the_path() -> None:
    op, out = _supervisor_run([0.004] * 40)
    assert all(s.deadman for s in out)
    assert all((s.insertion, s.alpha, s.gamma) == (0.0, 0.0, 0.0) for s in out)
    assert op.corrections == 0
    # never stops at the target: the autonomy does (distance 0 would stop a driving operator)
    op.perceive(Percept(t=2.0, bend=(0.0, 0.0), heading_error=0.0, distance=0.0))
    assert op.step(2.5).deadman and op.state == 'running'


def test_supervising_operator_corrects_beyond_the_threshold_after_its_delay() -> None:
    op, out = _supervisor_run([0.004] * 10 + [0.008] * 30)
    # deviation seen from t = 0.5 s, acted on after the 0.25 s delay: not before t = 0.75 s
    assert all((s.alpha, s.gamma) == (0.0, 0.0) for s in out[:15])
    late = out[-1]
    assert late.insertion == 0.0 and late.deadman
    # towards K * bend / bend_scale = 0.9 * (0.2, -0.1) / 0.5 (second-order response)
    assert late.alpha == pytest.approx(0.36, abs=0.05)
    assert late.gamma == pytest.approx(-0.18, abs=0.05)
    assert op.corrections > 0


def test_supervising_operator_releases_the_deadman_at_the_time_limit() -> None:
    from cgail_planner.core.operator import SupervisingOperator

    op = SupervisingOperator(OperatorConfig(time_limit_s=1.0))
    op.start(0.0)
    assert op.step(0.5).deadman
    assert not op.step(1.0).deadman and op.state == 'done' and 'time limit' in op.reason


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'threshold': 0.0}, r'threshold: expected a number in \(0, 0.05\], found 0.0'),
    ({'bend_scale': 2.0}, r'bend_scale: expected a number in \(0, 1.5708\], found 2.0'),
])
def test_supervising_operator_refuses_bad_settings(kwargs: dict, match: str) -> None:
    from cgail_planner.core.operator import SupervisingOperator

    with pytest.raises(ValueError, match=match):
        SupervisingOperator(**kwargs)

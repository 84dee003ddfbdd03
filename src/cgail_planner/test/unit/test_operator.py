"""Scripted operator: deadman, reaction delay, stick rate, protocol stops."""

import math

import pytest

from cgail_planner.core.operator import OperatorConfig, Percept, ScriptedOperator

QUIET = dict(stick_noise=0.0)


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

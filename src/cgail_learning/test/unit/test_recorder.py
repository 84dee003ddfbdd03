"""record_demos' pure logic: teleop commands -> env action, episode order, page commands."""

from __future__ import annotations

import itertools
import math
import re

import numpy as np
import pytest

from cgail_gui.errors import ProtocolError
from cgail_gui.protocol import parse_client_message
from cgail_learning.recorder import command_action, RecorderConfig, scenario_pairs

MODEL = {'theta_max': math.pi / 2, 'segment_length': 0.05, 'max_step_insertion': 0.0005,
         'dt': 0.1}


@pytest.mark.parametrize(('bend', 'velocity', 'expected'), [
    ((0.0, 0.0), 0.005, [0.0, 0.0, 1.0]),
    ((math.pi / 4, -math.pi / 8), 0.0025, [0.5, -0.25, 0.5]),
    ((math.pi / 2, 0.0), -0.005, [1.0, 0.0, -1.0]),
    ((0.3, 0.2), 0.0, [0.0, 0.0, 0.0]),         # no insertion: the catheter does not move
    ((0.0, 0.0), 0.01, [0.0, 0.0, 1.0]),          # capped at the step's maximum
])
def test_teleop_commands_become_the_env_action(bend, velocity, expected) -> None:
    np.testing.assert_allclose(command_action(bend, velocity, **MODEL), expected, atol=1e-6)


def test_the_env_steps_the_commanded_segment_bend() -> None:
    from cgail_sim.ftl_model import action_to_command, segment_bend_step

    a = command_action((0.4, -0.2), 0.003, **MODEL)
    alpha, gamma, dl = action_to_command(a[None].astype(np.float64), MODEL['theta_max'],
                                         MODEL['segment_length'], MODEL['max_step_insertion'],
                                         False)
    assert dl[0] == pytest.approx(0.0003)
    np.testing.assert_allclose([alpha[0], gamma[0]],
                               segment_bend_step((0.4, -0.2), 0.0003, math.pi / 2, 0.05),
                               rtol=1e-6)


def test_sequential_order_is_make_demos_order_and_random_is_seeded() -> None:
    assert list(itertools.islice(scenario_pairs(3, 5, 'sequential', 0), 7)) == [
        (0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (2, 1), (0, 2)]
    a = list(itertools.islice(scenario_pairs(3, 5, 'random', 4), 20))
    assert a == list(itertools.islice(scenario_pairs(3, 5, 'random', 4), 20))
    assert all(0 <= s < 3 and 0 <= t < 5 for s, t in a) and len(set(a)) > 5


@pytest.mark.parametrize(('field', 'value', 'message'), [
    ('episodes', 0, 'episodes must be an int in [1, 10000], found 0'),
    ('order', 'shuffled', "order must be one of ('sequential', 'random'), found 'shuffled'"),
    ('time_limit_s', math.nan, 'time_limit_s must be in (0, 3600] s, found nan'),
    ('pause_s', -1.0, 'pause_s must be in (0, 60] s, found -1.0'),
    ('seed', -2, 'seed must be an int >= 0, found -2'),
])
def test_bad_recorder_settings_raise(field, value, message) -> None:
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        RecorderConfig(**{field: value})


def test_page_keyboard_and_discard_commands() -> None:
    c = parse_client_message('{"type": "joy", "axes": [0, 1, 0, -1, 0.5], '
                             '"buttons": [0, 0, 0, 0, 1]}')
    assert (c.kind, c.axes, c.buttons) == ('joy', (0.0, 1.0, 0.0, -1.0, 0.5), (0, 0, 0, 0, 1))
    assert parse_client_message('{"type": "record", "action": "discard"}').action == 'discard'


@pytest.mark.parametrize(('text', 'message'), [
    ('{"type": "joy", "axes": [NaN], "buttons": []}', 'expected joy axes'),
    ('{"type": "joy", "axes": [2], "buttons": []}', 'expected joy axes'),
    ('{"type": "joy", "axes": [0], "buttons": [2]}', 'expected joy buttons'),
    ('{"type": "joy", "axes": [0], "buttons": [0.5]}', 'expected joy buttons'),
    ('{"type": "record", "action": "keep"}', 'expected record action discard'),
])
def test_bad_page_commands_are_refused(text, message) -> None:
    with pytest.raises(ProtocolError, match=message):
        parse_client_message(text)

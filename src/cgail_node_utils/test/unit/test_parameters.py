"""Pure-logic tests of the parameter helpers: descriptors and the configure-time decision.

No rclpy context: descriptors are plain messages and the decision is a function of plain data.
"""

from __future__ import annotations

from typing import Any

import pytest

from cgail_node_utils.parameters import (
    AUTOSTART_DESCRIPTION,
    configure_time_refusal,
    descriptor,
)


def test_float_bounds_give_a_floating_point_range_with_any_step() -> None:
    desc = descriptor('rate_hz', 'poll rate, Hz', default=40.0, bounds=(1.0, 1000.0))
    assert (desc.name, desc.description, desc.read_only) == ('rate_hz', 'poll rate, Hz', False)
    assert len(desc.floating_point_range) == 1
    rng = desc.floating_point_range[0]
    assert (rng.from_value, rng.to_value, rng.step) == (1.0, 1000.0, 0.0)
    assert len(desc.integer_range) == 0


def test_int_bounds_give_an_integer_range_of_step_one() -> None:
    desc = descriptor('tool_handle', 'port handle', default=0, bounds=(0, 255))
    assert len(desc.integer_range) == 1
    rng = desc.integer_range[0]
    assert (rng.from_value, rng.to_value, rng.step) == (0, 255, 1)
    assert len(desc.floating_point_range) == 0


def test_a_float_default_keeps_int_bounds_as_a_floating_point_range() -> None:
    desc = descriptor('scale', 'gain', default=1.0, bounds=(0, 2))
    rng = desc.floating_point_range[0]
    assert (type(rng.from_value), rng.from_value, rng.to_value) == (float, 0.0, 2.0)


@pytest.mark.parametrize('default', [True, 'virtual', [0.0, 1.0]])
def test_no_bounds_no_range_for_any_type(default: Any) -> None:
    desc = descriptor('p', 'a parameter', default=default, read_only=True)
    assert desc.read_only is True
    assert len(desc.integer_range) == 0
    assert len(desc.floating_point_range) == 0


@pytest.mark.parametrize(('default', 'kind'), [(True, 'bool'), ('can0', 'str'),
                                               ([1.0], 'list')])
def test_bounds_on_a_parameter_that_is_not_a_number_are_refused(default: Any, kind: str) -> None:
    with pytest.raises(ValueError, match=f'^p: expected bounds only for an int or float '
                                         f'parameter, found a {kind} default'):
        descriptor('p', 'a parameter', default=default, bounds=(0.0, 1.0))


def test_bounds_in_the_wrong_order_are_refused() -> None:
    with pytest.raises(ValueError, match=r'^rate_hz: expected bounds \(lo, hi\) with lo <= hi, '
                                         r'found \(10.0, 1.0\)$'):
        descriptor('rate_hz', 'rate', default=5.0, bounds=(10.0, 1.0))


def test_autostart_description_names_the_lifecycle_service() -> None:
    assert '<node>/change_state' in AUTOSTART_DESCRIPTION
    assert AUTOSTART_DESCRIPTION.endswith('read-only')


def _validate(values: dict[str, Any]) -> None:
    """A configuration with a cross-parameter rule, as a node's build_config has."""
    if values['rate_hz'] <= 0.0:
        raise ValueError(f'rate_hz: expected > 0, found {values["rate_hz"]}')
    if values['mode'] == 'fast' and values['rate_hz'] < 100.0:
        raise ValueError(f"mode 'fast': expected rate_hz >= 100, found {values['rate_hz']}")


CURRENT = {'rate_hz': 40.0, 'mode': 'slow'}


def test_a_valid_change_while_unconfigured_is_accepted() -> None:
    assert configure_time_refusal({'rate_hz': 200.0}, CURRENT, 'unconfigured', _validate) is None


def test_the_change_is_validated_with_the_other_current_values() -> None:
    # alone, mode 'fast' is fine; with the current rate it is not
    assert configure_time_refusal({'mode': 'fast'}, CURRENT, 'unconfigured', _validate) == (
        "mode: mode 'fast': expected rate_hz >= 100, found 40.0")
    # both at once: validated together
    assert configure_time_refusal({'mode': 'fast', 'rate_hz': 100.0}, CURRENT, 'unconfigured',
                                  _validate) is None


@pytest.mark.parametrize('state', ['inactive', 'active', 'configuring', 'finalized'])
def test_any_state_but_unconfigured_refuses_with_the_way_out(state: str) -> None:
    assert configure_time_refusal({'rate_hz': 200.0, 'mode': 'fast'}, CURRENT, state,
                                  _validate) == (
        'rate_hz, mode: read at configure, so changeable only while unconfigured; found the '
        f'node {state}: deactivate it, clean it up, set, then configure')


def test_only_the_given_errors_become_a_refusal() -> None:
    def broken(values: dict[str, Any]) -> None:
        raise KeyError('rate_hz')

    with pytest.raises(KeyError):
        configure_time_refusal({'rate_hz': 1.0}, CURRENT, 'unconfigured', broken)
    assert configure_time_refusal({'rate_hz': 1.0}, CURRENT, 'unconfigured', broken,
                                  errors=(KeyError,)) == "rate_hz: 'rate_hz'"

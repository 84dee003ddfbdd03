"""declare and configure_time_guard on real nodes: ranges, types, read-only values, and the
configure-time rule answered to ``set_parameters``."""

from __future__ import annotations

from typing import Any

import pytest
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node
from rclpy.parameter import Parameter

from cgail_node_utils.parameters import AUTOSTART_DESCRIPTION, configure_time_guard, declare

CONFIGURE_TIME = ('rate_hz', 'mode')


def _validate(values: dict[str, Any]) -> None:
    if values['mode'] == 'fast' and values['rate_hz'] < 100.0:
        raise ValueError(f"mode 'fast': expected rate_hz >= 100, found {values['rate_hz']}")


class Device(LifecycleNode):
    """A lifecycle device node declared the way the workspace's device nodes are."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('device', **kwargs)
        declare(self, 'rate_hz', 40.0, 'poll rate, Hz', lo=1.0, hi=1000.0)
        declare(self, 'mode', 'slow', "'slow' or 'fast'")
        declare(self, 'log_every', 10, 'log every n-th frame (read any time)', lo=1, hi=1000)
        self.autostart = declare(self, 'autostart', True, AUTOSTART_DESCRIPTION, read_only=True)
        _validate({name: self.get_parameter(name).value for name in CONFIGURE_TIME})
        self.add_on_set_parameters_callback(configure_time_guard(self, CONFIGURE_TIME,
                                                                 _validate))


def test_declare_returns_the_value_typed_like_the_default(ros: None) -> None:
    node = Node('typed', parameter_overrides=[Parameter('rate_hz', value=250.0),
                                              Parameter('count', value=7)])
    try:
        rate = declare(node, 'rate_hz', 40.0, 'rate, Hz', lo=1.0, hi=1000.0)
        count = declare(node, 'count', 3, 'count', lo=0, hi=10)
        name = declare(node, 'frame_id', 'phantom', 'frame')
        flag = declare(node, 'publish_tf', True, 'publish TF')
        assert (rate, count, name, flag) == (250.0, 7, 'phantom', True)
        assert [type(v) for v in (rate, count, name, flag)] == [float, int, str, bool]
        desc = node.describe_parameter('count')
        assert (desc.description, desc.integer_range[0].to_value) == ('count', 10)
    finally:
        node.destroy_node()


def test_a_value_out_of_range_or_of_the_wrong_type_raises_at_construction(ros: None) -> None:
    with pytest.raises(InvalidParameterValueException):
        Device(parameter_overrides=[Parameter('rate_hz', value=5000.0)])
    with pytest.raises(InvalidParameterTypeException):
        Device(parameter_overrides=[Parameter('mode', value=3)])


def test_declare_refuses_half_a_range(ros: None) -> None:
    node = Node('half')
    try:
        with pytest.raises(ValueError, match=r'^rate_hz: expected both lo and hi or neither, '
                                             r'found lo=1.0, hi=None$'):
            declare(node, 'rate_hz', 40.0, 'rate', lo=1.0)
        assert not node.has_parameter('rate_hz')
    finally:
        node.destroy_node()


def test_read_only_is_read_only(ros: None) -> None:
    node = Device()
    try:
        assert node.describe_parameter('autostart').read_only
        result = node.set_parameters([Parameter('autostart', value=False)])[0]
        assert not result.successful
        assert node.autostart is True
    finally:
        node.destroy_node()


def test_a_configure_time_change_applies_only_while_unconfigured(ros: None) -> None:
    node = Device()
    try:
        # unconfigured: validated with the other current values, then accepted
        refused = node.set_parameters([Parameter('mode', value='fast')])[0]
        assert not refused.successful
        assert refused.reason == "mode: mode 'fast': expected rate_hz >= 100, found 40.0"
        assert node.get_parameter('mode').value == 'slow'
        accepted = node.set_parameters_atomically([Parameter('rate_hz', value=200.0),
                                                   Parameter('mode', value='fast')])
        assert accepted.successful, accepted.reason
        assert node.get_parameter('mode').value == 'fast'
        # configured: refused with the way out; other parameters still change
        node.trigger_configure()
        refused = node.set_parameters([Parameter('rate_hz', value=300.0)])[0]
        assert not refused.successful
        assert refused.reason == ('rate_hz: read at configure, so changeable only while '
                                  'unconfigured; found the node inactive: deactivate it, clean '
                                  'it up, set, then configure')
        assert node.get_parameter('rate_hz').value == 200.0
        assert node.set_parameters([Parameter('log_every', value=5)])[0].successful
        node.trigger_activate()
        assert 'found the node active' in node.set_parameters(
            [Parameter('mode', value='slow')])[0].reason
        # cleaned up: changeable again
        node.trigger_deactivate()
        node.trigger_cleanup()
        assert node.set_parameters([Parameter('rate_hz', value=300.0)])[0].successful
    finally:
        node.destroy_node()


def test_a_node_without_lifecycle_services_refuses_configure_time_changes(ros: None) -> None:
    node = Device(enable_communication_interface=False)
    try:
        result = node.set_parameters([Parameter('rate_hz', value=300.0)])[0]
        assert not result.successful
        assert result.reason.startswith('rate_hz: read at configure, so changeable only while '
                                        'unconfigured; found the state unknown: '
                                        'lifecycle_state: expected the get_state service')
        assert node.set_parameters([Parameter('log_every', value=5)])[0].successful
    finally:
        node.destroy_node()


def test_the_guard_refuses_a_plain_node_and_undeclared_names(ros: None) -> None:
    plain = Node('plain')
    node = Device()
    try:
        with pytest.raises(ValueError, match=r"^configure_time_guard: expected a lifecycle "
                                             r"node, found Node '/plain'$"):
            configure_time_guard(plain, ['x'], _validate)
        with pytest.raises(ValueError, match=r"^configure_time_guard: expected declared "
                                             r"parameters, found rate, modes undeclared on "
                                             r"'/device'$"):
            configure_time_guard(node, ['rate_hz', 'rate', 'modes'], _validate)
    finally:
        plain.destroy_node()
        node.destroy_node()

"""Parameter helpers: every parameter declared once, with a description and range; the
parameters of a lifecycle device node read at configure and changeable only while unconfigured.

A device node (``driver_node``) builds its configuration from its parameters in the constructor
(bad values raise there) and again in ``on_configure``. :func:`configure_time_guard` is its
on-set-parameters callback: while the node is unconfigured a change is validated against the
whole configuration and applies at the next configure; in any other state it is refused with a
reason (``successful=False``), so ``set_parameters`` never reports a change that does not
happen. ``autostart`` (read-only) tells ``main()`` whether to configure and activate the node.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from typing import Any, TypeVar

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node
from rclpy.parameter import Parameter

T = TypeVar('T', bool, int, float, str)

AUTOSTART_DESCRIPTION = ('main() configures and activates the node at start; false: it stays '
                         'unconfigured for a lifecycle manager (<node>/change_state); read-only')


def declare(node: Node, name: str, default: T, description: str, *,
            lo: float | None = None, hi: float | None = None, read_only: bool = False) -> T:
    """Declare ``name`` with a descriptor (and an inclusive range when ``lo``/``hi`` given;
    read-only when told) and return its value, typed like ``default``.

    Raises:
        rclpy.exceptions.InvalidParameterValueException: value outside the range.
        rclpy.exceptions.InvalidParameterTypeException: value of the wrong type.
    """
    descriptor = ParameterDescriptor(name=name, description=description, read_only=read_only)
    if lo is not None and hi is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi),
                                                     step=1)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                                  to_value=float(hi), step=0.0)]
    value = node.declare_parameter(name, default, descriptor).value
    return type(default)(value)


def lifecycle_state(node: LifecycleNode) -> str:
    """Label of the node's lifecycle state: ``'unconfigured'``, ``'inactive'``, ``'active'``,
    ``'finalized'`` or a transition (``'configuring'`` ...)."""
    return str(node._state_machine.current_state[1])  # (no public getter in rclpy 7)


def configure_time_guard(node: LifecycleNode, names: Collection[str],
                         validate: Callable[[dict[str, Any]], object],
                         errors: tuple[type[BaseException], ...] = (ValueError,),
                         ) -> Callable[[list[Parameter]], SetParametersResult]:
    """The on-set-parameters callback for the configure-time parameters ``names``.

    Args:
        node: the lifecycle node.
        names: the parameters read at configure (others pass untouched).
        validate: builds the configuration from ``{name: value}`` of all ``names`` and raises
            one of ``errors`` on a bad one (the constructor's own check).
        errors: what ``validate`` raises on a bad value.
    """
    def on_set(params: list[Parameter]) -> SetParametersResult:
        ours = [p for p in params if p.name in names]
        if not ours:
            return SetParametersResult(successful=True)
        listed = ', '.join(p.name for p in ours)
        state = lifecycle_state(node)
        if state != 'unconfigured':
            return SetParametersResult(successful=False, reason=(
                f'{listed}: read at configure, so changeable only while unconfigured; found the '
                f'node {state}: deactivate it, clean it up, set, then configure'))
        values = {name: node.get_parameter(name).value for name in names}
        values.update({p.name: p.value for p in ours})
        try:
            validate(values)
        except errors as exc:
            return SetParametersResult(successful=False, reason=f'{listed}: {exc}')
        return SetParametersResult(successful=True)

    return on_set

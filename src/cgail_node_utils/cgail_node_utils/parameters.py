"""Parameters declared once with a description and a range; configure-time parameters.

Every parameter of a node is declared once, with a description and, for numbers, an inclusive
range (:func:`declare`, :func:`descriptor`); a value out of range or of the wrong type then
raises while the node is constructed.

A lifecycle device node builds its configuration from its parameters in the constructor (bad
values raise there) and again in ``on_configure``. :func:`configure_time_guard` is its
on-set-parameters callback: while the node is unconfigured a change is validated against the
whole configuration and applies at the next configure; in any other state it is refused with a
reason (``successful=False``), so ``set_parameters`` never reports a change that does not happen.
The decision itself is the pure function :func:`configure_time_refusal`. ``autostart``
(read-only, :data:`AUTOSTART_DESCRIPTION`) tells ``main()`` whether to configure and activate the
node itself.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from typing import Any, TypeVar

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.lifecycle import LifecycleNodeMixin
from rclpy.node import Node
from rclpy.parameter import Parameter

from cgail_node_utils.lifecycle import lifecycle_state

T = TypeVar('T', bool, int, float, str)

#: Description of a lifecycle device node's read-only ``autostart`` parameter.
AUTOSTART_DESCRIPTION = ('main() configures and activates the node at start; false: it stays '
                         'unconfigured for a lifecycle manager (<node>/change_state); read-only')


def descriptor(name: str, description: str, *, default: object,
               bounds: tuple[float, float] | None = None,
               read_only: bool = False) -> ParameterDescriptor:
    """The descriptor of parameter ``name``: its description, range and read-only flag.

    Args:
        name: the parameter's name.
        description: what it means, with its unit.
        default: its default value; its type picks the range: an ``IntegerRange`` (step 1) for
            an ``int``, a ``FloatingPointRange`` (any step) for a ``float``.
        bounds: the inclusive ``(lo, hi)`` of a number; ``None``: no range.
        read_only: the value is fixed for the node's life.

    Raises:
        ValueError: ``bounds`` for a default that is not an int or a float (a bool is not a
            number here), or ``lo > hi``.
    """
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only)
    if bounds is None:
        return desc
    lo, hi = bounds
    if isinstance(default, bool) or not isinstance(default, int | float):
        raise ValueError(f'{name}: expected bounds only for an int or float parameter, found a '
                         f'{type(default).__name__} default {default!r}')
    if not lo <= hi:
        raise ValueError(f'{name}: expected bounds (lo, hi) with lo <= hi, found ({lo}, {hi})')
    if isinstance(default, int):
        desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    else:
        desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                        to_value=float(hi), step=0.0)]
    return desc


def declare(node: Node, name: str, default: T, description: str, *,
            lo: float | None = None, hi: float | None = None, read_only: bool = False) -> T:
    """Declare ``name`` with its :func:`descriptor` and return its value, typed like ``default``.

    Args:
        node: the node that owns the parameter.
        name: the parameter's name.
        default: its default value (``bool``, ``int``, ``float`` or ``str``).
        description: what it means, with its unit.
        lo: inclusive lower bound of a number (given with ``hi``).
        hi: inclusive upper bound of a number (given with ``lo``).
        read_only: the value is fixed for the node's life.

    Raises:
        ValueError: only one of ``lo`` and ``hi``, or bounds that :func:`descriptor` refuses.
        rclpy.exceptions.InvalidParameterValueException: the value is outside the range.
        rclpy.exceptions.InvalidParameterTypeException: the value has the wrong type.
    """
    if (lo is None) != (hi is None):
        raise ValueError(f'{name}: expected both lo and hi or neither, found lo={lo}, hi={hi}')
    bounds = (lo, hi) if lo is not None and hi is not None else None
    desc = descriptor(name, description, default=default, bounds=bounds, read_only=read_only)
    value = node.declare_parameter(name, default, desc).value
    return type(default)(value)


def configure_time_refusal(changes: Mapping[str, Any], current: Mapping[str, Any], state: str,
                           validate: Callable[[dict[str, Any]], object],
                           errors: tuple[type[BaseException], ...] = (ValueError,),
                           ) -> str | None:
    """Why a change of configure-time parameters is refused; ``None`` when it is accepted.

    Args:
        changes: ``{name: new value}`` of the configure-time parameters being set (not empty).
        current: ``{name: value}`` of every configure-time parameter now.
        state: the node's lifecycle state (:func:`~cgail_node_utils.lifecycle.lifecycle_state`).
        validate: builds the configuration from ``{name: value}`` of every configure-time
            parameter and raises one of ``errors`` on a bad one (the constructor's own check).
        errors: what ``validate`` raises on a bad value.

    Returns:
        ``None`` when the node is unconfigured and the configuration with ``changes`` is valid;
        otherwise the reason, starting with the names of ``changes``.
    """
    listed = ', '.join(changes)
    if state != 'unconfigured':
        return (f'{listed}: read at configure, so changeable only while unconfigured; found the '
                f'node {state}: deactivate it, clean it up, set, then configure')
    try:
        validate({**current, **changes})
    except errors as exc:
        return f'{listed}: {exc}'
    return None


def configure_time_guard(node: Node, names: Collection[str],
                         validate: Callable[[dict[str, Any]], object],
                         errors: tuple[type[BaseException], ...] = (ValueError,),
                         ) -> Callable[[list[Parameter]], SetParametersResult]:
    """The on-set-parameters callback for the configure-time parameters ``names``.

    Register it with ``node.add_on_set_parameters_callback(...)`` after declaring ``names``.
    A change of any of ``names`` is accepted only while the node is unconfigured and the whole
    configuration validates (:func:`configure_time_refusal`); other parameters pass untouched.
    A node without lifecycle services (``enable_communication_interface=False``) cannot tell its
    state, so a change of ``names`` is refused there.

    Args:
        node: the lifecycle node.
        names: the parameters read at configure, all declared already.
        validate: builds the configuration from ``{name: value}`` of all ``names`` and raises
            one of ``errors`` on a bad one (the constructor's own check).
        errors: what ``validate`` raises on a bad value.

    Raises:
        ValueError: ``node`` is not a lifecycle node, or one of ``names`` is not declared.
    """
    if not isinstance(node, LifecycleNodeMixin):
        raise ValueError(f'configure_time_guard: expected a lifecycle node, found '
                         f'{type(node).__name__} {node.get_fully_qualified_name()!r}')
    names = tuple(names)
    undeclared = ', '.join(name for name in names if not node.has_parameter(name))
    if undeclared:
        raise ValueError(f'configure_time_guard: expected declared parameters, found '
                         f'{undeclared} undeclared on {node.get_fully_qualified_name()!r}')

    def on_set(params: list[Parameter]) -> SetParametersResult:
        changes = {p.name: p.value for p in params if p.name in names}
        if not changes:
            return SetParametersResult(successful=True)
        try:
            state = lifecycle_state(node)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=(
                f'{", ".join(changes)}: read at configure, so changeable only while '
                f'unconfigured; found the state unknown: {exc}'))
        current = {name: node.get_parameter(name).value for name in names}
        reason = configure_time_refusal(changes, current, state, validate, errors)
        return SetParametersResult(successful=reason is None, reason=reason or '')

    return on_set

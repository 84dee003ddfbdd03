"""Parameter declaration helper: every parameter declared once, with a description and range."""

from __future__ import annotations

from typing import TypeVar

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

T = TypeVar('T', bool, int, float, str)


def declare(node: Node, name: str, default: T, description: str, *,
            lo: float | None = None, hi: float | None = None) -> T:
    """Declare ``name`` with a descriptor (and an inclusive range when ``lo``/``hi`` given) and
    return its value, typed like ``default``.

    Raises:
        rclpy.exceptions.InvalidParameterValueException: value outside the range.
        rclpy.exceptions.InvalidParameterTypeException: value of the wrong type.
    """
    descriptor = ParameterDescriptor(name=name, description=description)
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

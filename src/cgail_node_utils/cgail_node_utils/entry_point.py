"""What a node's console entry point needs around the spin, whatever the timing of a Ctrl-C.

A ``main()`` is one call (:func:`run_node`), which runs ros2/demos' shape::

    rclpy.init(args=args)
    node = None
    try:
        node = ThingNode()
        spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        if rclpy.ok():  # not ok: Ctrl-C while starting, a clean stop
            raise
    finally:
        if node is not None:
            node.destroy_node()
        try_shutdown()

plus the node's own fatal input errors (one line, exit status 2) and, for a lifecycle node, its
autostart (:func:`start_lifecycle`).
"""

from __future__ import annotations

from collections.abc import Callable
import contextlib
import sys
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node

#: rclpy's error type. A node's ``main()`` that gets one while ``rclpy.ok()`` is False was
#: stopped by Ctrl-C while it was starting (rclpy's SIGINT handler had shut the context down
#: before the spin built its executor): a clean stop, not a failure.
RCLError = rclpy_implementation.RCLError


def try_shutdown() -> None:
    """``rclpy.try_shutdown()`` that tolerates rclpy's SIGINT handler.

    The handler shuts the context down from its own thread, without the context's lock, so
    between ``try_shutdown``'s check and its call the context can be down already (``RCLError``
    'rcl_shutdown already called', seen on Ctrl-C under load). Either way the context ends shut
    down.
    """
    with contextlib.suppress(RCLError):
        rclpy.try_shutdown()


def spin(node: Node) -> None:
    """``rclpy.spin(node)`` that tolerates a Ctrl-C before it starts.

    rclpy's SIGINT handler can shut the context down between the node's start-up and the spin,
    and ``rclpy.spin``'s global executor is then ``None`` (``AttributeError: 'NoneType' object
    has no attribute 'add_node'``, seen once in CI on a console-entry-point test). Here a private
    executor of the node's context spins until that context is shut down, and returns at once
    if it already is; an ``RCLError`` from a context shut down meanwhile is the caller's clean
    stop (:data:`RCLError`).

    Args:
        node: the node to spin (any ``rclpy.node.Node``, lifecycle nodes included).
    """
    if not node.context.ok():
        return
    executor = SingleThreadedExecutor(context=node.context)
    try:
        executor.add_node(node)
        executor.spin()
    finally:
        executor.shutdown(timeout_sec=0)


def run_node(make: Callable[[], Node], prog: str, args: list[str] | None = None, *,
             fatal: tuple[type[BaseException], ...] = (),
             start: Callable[[Any], None] | None = None) -> None:
    """A node's console entry point: init, ``make()`` the node, ``start`` it, spin until
    Ctrl-C or shutdown, then destroy it and shut down (the module docstring's shape).

    Args:
        make: builds the node (its constructor).
        prog: the console script's name, for the error line.
        args: the command line (rclpy's, default ``sys.argv``).
        fatal: input errors that end the node with ``<prog>: error: <message>`` on stderr and
            exit status 2 (a bad anatomy or contract, a port in use).
        start: called with the node before the spin (:func:`start_lifecycle`).
    """
    rclpy.init(args=args)
    node = None
    try:
        node = make()
        if start is not None:
            start(node)
        spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        if rclpy.ok():  # (not ok: Ctrl-C while starting, see RCLError)
            raise
    except fatal as exc:
        print(f'{prog}: error: {exc}', file=sys.stderr)
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node.destroy_node()
        try_shutdown()


def start_lifecycle(node: Any) -> None:
    """A lifecycle device node's start: configure and activate it, unless its ``autostart``
    is false (then it waits, unconfigured, for ``<name>/change_state``)."""
    if node.autostart:
        node.trigger_configure()
        node.trigger_activate()
    else:
        node.get_logger().info('autostart is false: unconfigured, waiting for '
                               f'{node.get_name()}/change_state')

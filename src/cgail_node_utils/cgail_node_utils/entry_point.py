"""What a node's console entry point needs around the spin, whatever the timing of a Ctrl-C.

A ``main()`` reads (ros2/demos' shape, with these two helpers)::

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
"""

from __future__ import annotations

import contextlib

import rclpy
from rclpy.executors import SingleThreadedExecutor
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

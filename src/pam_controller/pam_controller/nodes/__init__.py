"""ROS 2 nodes of ``pam_controller``, and what their entry points share."""

import contextlib
from typing import Any

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation

#: rclpy's error type. A node's ``main()`` that gets one while ``rclpy.ok()`` is False was
#: stopped by Ctrl-C while it was starting (rclpy's SIGINT handler had shut the context down
#: before ``rclpy.spin`` built its executor): a clean stop, not a failure.
RCLError = rclpy_implementation.RCLError


def try_shutdown() -> None:
    """``rclpy.try_shutdown()`` that tolerates rclpy's SIGINT handler: the handler shuts the
    context down from its own thread, without the context's lock, so between try_shutdown's check
    and its call the context can be down already (RCLError 'rcl_shutdown already called', seen
    on Ctrl-C under load). Either way the context ends shut down."""
    with contextlib.suppress(RCLError):
        rclpy.try_shutdown()


def spin(node: Any) -> None:
    """``rclpy.spin(node)`` that tolerates Ctrl-C before it starts: rclpy's SIGINT handler can
    shut the context down between the node's start-up and the spin, and ``rclpy.spin``'s global
    executor is then ``None`` (``AttributeError: 'NoneType' object has no attribute
    'add_node'``, seen once in CI on the console-entry-point test). A private executor of the
    node's context spins until that context is shut down, and returns at once if it already is;
    an ``RCLError`` from a context shut down meanwhile is the caller's clean stop (``RCLError``
    above)."""
    from rclpy.executors import SingleThreadedExecutor

    if not node.context.ok():
        return
    executor = SingleThreadedExecutor(context=node.context)
    try:
        executor.add_node(node)
        executor.spin()
    finally:
        executor.shutdown(timeout_sec=0)

"""ROS 2 nodes of ``catheter_driver``, and what their entry points share."""

import contextlib

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation


def try_shutdown() -> None:
    """``rclpy.try_shutdown()`` that tolerates rclpy's SIGINT handler: the handler shuts the
    context down from its own thread, without the context's lock, so between try_shutdown's check
    and its call the context can be down already (RCLError 'rcl_shutdown already called', seen
    on Ctrl-C under load). Either way the context ends shut down."""
    with contextlib.suppress(rclpy_implementation.RCLError):
        rclpy.try_shutdown()

"""ROS 2 nodes of ``cgail_planner``, and what their entry points share."""

import contextlib

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

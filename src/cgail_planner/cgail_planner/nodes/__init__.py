"""ROS 2 nodes of ``cgail_planner``, and what their entry points share.

The entry-point helpers (``RCLError``, ``try_shutdown``, ``spin``) are ``em_tracker.nodes``'s,
which this package depends on already; the three device packages do not depend on each other
and keep one copy each."""

from em_tracker.nodes import RCLError, spin, try_shutdown

__all__ = ['RCLError', 'spin', 'try_shutdown']

"""ROS 2 nodes of ``cgail_planner``, and what their entry points share.

The entry-point helpers (``RCLError``, ``try_shutdown``, ``spin``) are
:mod:`cgail_node_utils.entry_point`'s, the one copy every node package uses."""

from cgail_node_utils.entry_point import RCLError, spin, try_shutdown

__all__ = ['RCLError', 'spin', 'try_shutdown']

"""ROS 2 nodes of ``cgail_planner``. Their entry points are
:func:`cgail_node_utils.entry_point.run_node`, the one copy every node package uses."""

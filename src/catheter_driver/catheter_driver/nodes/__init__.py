"""ROS 2 nodes of ``catheter_driver``.

Their entry points and parameters use the shared helpers of ``cgail_node_utils``
(:mod:`cgail_node_utils.entry_point`, :mod:`cgail_node_utils.parameters`).
"""

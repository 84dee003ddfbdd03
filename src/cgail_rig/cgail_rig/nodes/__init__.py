"""ROS 2 nodes of ``cgail_rig``: ``phantom_node`` and the demonstration recorder's node."""

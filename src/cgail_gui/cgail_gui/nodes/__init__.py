"""ROS 2 nodes of ``cgail_gui``: ``gui_node`` and ``igtl_bridge``."""

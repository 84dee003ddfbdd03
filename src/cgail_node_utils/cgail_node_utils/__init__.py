"""Helpers shared by the workspace's ROS 2 nodes (one copy, used by every node package).

Modules, each imported on its own:

* :mod:`cgail_node_utils.entry_point`: what a node's ``main()`` needs around ``rclpy.spin``
  (``spin``, ``try_shutdown`` and ``RCLError``, tolerant of a Ctrl-C while starting);
* :mod:`cgail_node_utils.parameters`: parameters declared once with a description and a range
  (``declare``, ``descriptor``), and the configure-time parameters of a lifecycle device node
  (``configure_time_guard``, ``AUTOSTART_DESCRIPTION``);
* :mod:`cgail_node_utils.lifecycle`: a lifecycle node's state read through rclpy's public API
  (``lifecycle_state``);
* :mod:`cgail_node_utils.rotations`: one rotation's quaternion <-> matrix in plain floats,
  bit-identical to scipy's ``Rotation`` and ten times faster (no rclpy, no numpy);
* :mod:`cgail_node_utils.can_codec`: the device nodes' CAN frames packed and unpacked by shifts,
  bit-identical to cantools (``FastCodec``; no cantools import).
"""

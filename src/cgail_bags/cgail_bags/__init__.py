"""Bag tools on rosbags + rclpy raw pub/sub (no rosbag2/ros2cli on PyPI).

* :mod:`.record` (``cgail bag record``): record topics to a rosbag2 MCAP bag with their QoS.
* :mod:`.play` (``cgail bag play``): play a bag back with its timing and recorded QoS.
* :mod:`.metrics_cli` (``cgail bag metrics``): the paper's in-vitro metrics from trial bags
  (definitions in :mod:`cgail_planner.core.metrics`), markdown table, CSV and box plots.
* :mod:`.bagio` / :mod:`.reader`: reading/writing bags; every broken bag is a
  :class:`~cgail_bags.errors.BagError` naming the file and the problem.
"""

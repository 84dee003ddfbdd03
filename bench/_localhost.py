"""Imported by every benchmark that starts rclpy, before it does: DDS stays on this machine.

``scripts/ws`` already sets this (``scripts/env.sh``); the import makes a benchmark started
with a bare ``python`` just as safe instead of multicasting discovery onto the network.
"""

import os

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ["ROS_STATIC_PEERS"] = ""

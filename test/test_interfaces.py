"""The workspace's interface package (src/interfaces/tf2_msgs) is ROS 2 Jazzy's tf2_msgs.

The ros-jazzy-* wheels have no tf2_msgs, so scripts/build_interfaces.sh generates it here. The
generated type must be the real one, hash for hash, or RViz2, Foxglove and rosbags would see a
different type under the same name, and a bag's TF would not decode elsewhere.
"""

from __future__ import annotations

import json
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from rosbags.typesys import get_typestore, Stores


def test_tf_message_is_jazzys_type_hash_for_hash() -> None:
    share = Path(get_package_share_directory('tf2_msgs'))
    hashes = {h['type_name']: h['hash_string'] for h in json.loads(
        (share / 'msg' / 'TFMessage.json').read_text())['type_hashes']}
    store = get_typestore(Stores.ROS2_JAZZY)
    assert hashes['tf2_msgs/msg/TFMessage'] == store.hash_rihs01('tf2_msgs/msg/TFMessage')
    assert hashes['geometry_msgs/msg/TransformStamped'] == store.hash_rihs01(
        'geometry_msgs/msg/TransformStamped')


def test_tf_message_round_trips_through_cdr_into_rosbags() -> None:
    from geometry_msgs.msg import TransformStamped
    from rclpy.serialization import serialize_message
    from tf2_msgs.msg import TFMessage

    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = 'aurora', 'phantom'
    t.transform.translation.x, t.transform.rotation.w = 0.25, 1.0
    raw = serialize_message(TFMessage(transforms=[t]))
    back = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(raw, 'tf2_msgs/msg/TFMessage')
    (got,) = back.transforms
    assert (got.header.frame_id, got.child_frame_id) == ('aurora', 'phantom')
    assert (got.transform.translation.x, got.transform.rotation.w) == (0.25, 1.0)

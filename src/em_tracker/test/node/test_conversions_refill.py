"""Refilled pose messages (the Aurora node's ``out=``) are the messages built afresh."""

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
import numpy as np
from tf2_msgs.msg import TFMessage

from em_tracker.core.pose import TipPose
from em_tracker.nodes.conversions import tip_pose_to_cov_msg, tip_pose_to_msg, tip_tf


def test_a_refilled_message_equals_a_new_one_and_keeps_nothing_of_the_last() -> None:
    first = TipPose(np.array([0.01, -0.02, 0.03]), np.array([0.0, 0.6, 0.0, 0.8]), 0.0005)
    second = TipPose(np.array([0.04, 0.05, -0.06]), np.array([0.6, 0.0, 0.0, 0.8]), 0.0007)
    outs = (PoseStamped(), PoseWithCovarianceStamped(), TFMessage(transforms=[TransformStamped()]))
    for k, pose in enumerate((first, second)):
        stamp = Time(sec=3 + k, nanosec=25_000_000 * k)
        frame = f'phantom{k}'
        assert tip_pose_to_msg(pose, stamp, frame, out=outs[0]) == \
            tip_pose_to_msg(pose, stamp, frame)
        assert tip_pose_to_cov_msg(pose, stamp, frame, out=outs[1]) == \
            tip_pose_to_cov_msg(pose, stamp, frame)
        assert tip_tf(pose, stamp, frame, 'tip', out=outs[2]) == tip_tf(pose, stamp, frame, 'tip')

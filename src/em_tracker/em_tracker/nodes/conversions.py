"""Messages <-> em_tracker core types."""

from __future__ import annotations

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped

from em_tracker.core.pose import pose_covariance, TipPose
from em_tracker.core.tracking import Level

LEVEL_BYTES = {
    Level.OK: DiagnosticStatus.OK,
    Level.WARN: DiagnosticStatus.WARN,
    Level.ERROR: DiagnosticStatus.ERROR,
    Level.STALE: DiagnosticStatus.STALE,
}


def tip_pose_to_msg(pose: TipPose, stamp: Time, frame_id: str) -> PoseStamped:
    """A :class:`TipPose` (phantom frame, SI) as ``geometry_msgs/PoseStamped``."""
    msg = PoseStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    p, q = pose.position_m, pose.quat_xyzw
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in p)
    (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
     msg.pose.orientation.w) = (float(v) for v in q)
    return msg


def tip_pose_to_cov_msg(pose: TipPose, stamp: Time,
                        frame_id: str) -> PoseWithCovarianceStamped:
    """A :class:`TipPose` as ``geometry_msgs/PoseWithCovarianceStamped``, its covariance from
    the RMS error (:func:`~em_tracker.core.pose.pose_covariance`)."""
    stamped = tip_pose_to_msg(pose, stamp, frame_id)
    msg = PoseWithCovarianceStamped()
    msg.header = stamped.header
    msg.pose.pose = stamped.pose
    msg.pose.covariance = [float(v) for v in pose_covariance(pose.rms_error_m).ravel()]
    return msg


def diagnostic_status(name: str, hardware_id: str, level: Level, message: str,
                      values: dict[str, str]) -> DiagnosticStatus:
    """Build one ``DiagnosticStatus`` with the bytes level constant."""
    status = DiagnosticStatus()
    status.name = name
    status.hardware_id = hardware_id
    status.level = LEVEL_BYTES[level]
    status.message = message
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    return status

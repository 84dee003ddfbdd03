"""Messages <-> em_tracker core types."""

from __future__ import annotations

from functools import lru_cache

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
import numpy as np
from tf2_msgs.msg import TFMessage

from em_tracker.core.pose import pose_covariance, Registration, TipPose
from em_tracker.core.tracking import Level

LEVEL_BYTES = {
    Level.OK: DiagnosticStatus.OK,
    Level.WARN: DiagnosticStatus.WARN,
    Level.ERROR: DiagnosticStatus.ERROR,
    Level.STALE: DiagnosticStatus.STALE,
}


def _floats(values: np.ndarray) -> list[float]:
    """``values`` as Python floats (the float64 values a message field stores)."""
    out: list[float] = np.asarray(values, dtype=np.float64).tolist()
    return out


def _fill(header, pose, tip: TipPose, stamp: Time, frame_id: str) -> None:
    """Set a ``std_msgs/Header`` and a ``geometry_msgs/Pose`` from a :class:`TipPose`."""
    header.stamp = stamp
    header.frame_id = frame_id
    p, q = pose.position, pose.orientation
    p.x, p.y, p.z = _floats(tip.position_m)
    q.x, q.y, q.z, q.w = _floats(tip.quat_xyzw)


def tip_pose_to_msg(pose: TipPose, stamp: Time, frame_id: str,
                    out: PoseStamped | None = None) -> PoseStamped:
    """A :class:`TipPose` (phantom frame, SI) as ``geometry_msgs/PoseStamped``; ``out``: a
    message to refill (every field is set) instead of a new one.

    ``out`` (here and below) serves a node that publishes a pose per tracker frame: a publish
    serializes the message before it returns (rclpy, and the lockstep rig's in-process
    transport), so the node can refill one object, where a new message builds all its nested
    defaults first (~10 us for each of the three messages of a 40 Hz frame).
    """
    msg = PoseStamped() if out is None else out
    _fill(msg.header, msg.pose, pose, stamp, frame_id)
    return msg


@lru_cache(maxsize=16)
def _covariance(rms_error_m: float) -> tuple[float, ...]:
    """:func:`~em_tracker.core.pose.pose_covariance` flattened (row-major), per RMS error (a
    tracker reports a handful of values: computed once each)."""
    return tuple(_floats(pose_covariance(rms_error_m).ravel()))


def tip_pose_to_cov_msg(pose: TipPose, stamp: Time, frame_id: str,
                        out: PoseWithCovarianceStamped | None = None
                        ) -> PoseWithCovarianceStamped:
    """A :class:`TipPose` as ``geometry_msgs/PoseWithCovarianceStamped``, its covariance from
    the RMS error (:func:`~em_tracker.core.pose.pose_covariance`); ``out``: a message to refill
    (:func:`tip_pose_to_msg`)."""
    msg = PoseWithCovarianceStamped() if out is None else out
    _fill(msg.header, msg.pose.pose, pose, stamp, frame_id)
    # a float64 array of 36 is stored as given (a list is checked value by value and
    # converted, ~10 us per message at 40 Hz): a copy of the cached one, each message its own
    msg.pose.covariance = _covariance_array(pose.rms_error_m).copy()
    return msg


@lru_cache(maxsize=16)
def _covariance_array(rms_error_m: float) -> np.ndarray:
    """:func:`_covariance` as the float64 array the message field holds (read-only)."""
    arr = np.array(_covariance(rms_error_m), dtype=np.float64)
    arr.setflags(write=False)
    return arr


def transform_msg(stamp: Time, parent: str, child: str, translation_m: np.ndarray,
                  quat_xyzw: np.ndarray, out: TransformStamped | None = None
                  ) -> TransformStamped:
    """``geometry_msgs/TransformStamped``: the pose of ``child`` in ``parent`` (tf2's
    convention: ``header.frame_id`` the parent, ``child_frame_id`` the child); ``out``: a
    message to refill (:func:`tip_pose_to_msg`)."""
    msg = TransformStamped() if out is None else out
    msg.header.stamp = stamp
    msg.header.frame_id = parent
    msg.child_frame_id = child
    t, q = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = _floats(translation_m)
    q.x, q.y, q.z, q.w = _floats(quat_xyzw)
    return msg


def registration_tf(registration: Registration, stamp: Time, tracker_frame: str,
                    phantom_frame: str) -> TFMessage:
    """The ``/tf_static`` message ``tracker_frame -> phantom_frame``: the phantom's pose in the
    field generator's frame, i.e. the inverse of the registration (``T_phantom_aurora``)."""
    flat = registration.inverse().to_flat()
    return TFMessage(transforms=[transform_msg(stamp, tracker_frame, phantom_frame,
                                               np.array(flat[:3]), np.array(flat[3:]))])


def tip_tf(pose: TipPose, stamp: Time, phantom_frame: str, tip_frame: str,
           out: TFMessage | None = None) -> TFMessage:
    """The ``/tf`` message ``phantom_frame -> tip_frame``: the tip pose (as ``tip_pose``);
    ``out``: a message of one transform to refill (:func:`tip_pose_to_msg`)."""
    if out is not None and len(out.transforms) == 1:
        transform_msg(stamp, phantom_frame, tip_frame, pose.position_m, pose.quat_xyzw,
                      out=out.transforms[0])
        return out
    return TFMessage(transforms=[transform_msg(stamp, phantom_frame, tip_frame,
                                               pose.position_m, pose.quat_xyzw)])


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

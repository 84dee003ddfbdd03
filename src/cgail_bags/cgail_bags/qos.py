"""QoS profiles of the interface contract as rosbags ``Qos``, and rclpy <-> rosbags conversions.

The bag's ``metadata.yaml`` stores each topic's offered QoS profiles the way rosbag2 does
(``offered_qos_profiles``, rosbag2 version 9 layout); the player rebuilds publishers from them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

if TYPE_CHECKING:
    from rclpy.qos import QoSProfile

_ZERO = QosTime(0, 0)
_INFINITE = QosTime(0x7FFFFFFF, 0xFFFFFFFF)  # rosbag2's "infinite" duration


def make_qos(reliable: bool, transient_local: bool, depth: int) -> Qos:
    """A keep-last QoS profile (automatic liveliness, infinite deadline/lifespan)."""
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        deadline=_INFINITE,
        lifespan=_INFINITE,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=_INFINITE,
        avoid_ros_namespace_conventions=False,
    )


#: docs/interfaces.md profiles.
SENSOR = make_qos(reliable=False, transient_local=False, depth=5)
COMMAND = make_qos(reliable=True, transient_local=False, depth=10)
LATCHED = make_qos(reliable=True, transient_local=True, depth=1)


def _duration(value: object) -> QosTime:
    nanoseconds = int(getattr(value, 'nanoseconds', 0))
    if nanoseconds <= 0 or nanoseconds >= 0x7FFFFFFF * 10**9:
        return _INFINITE
    return QosTime(nanoseconds // 10**9, nanoseconds % 10**9)


def from_rclpy(profile: QoSProfile) -> Qos:
    """Convert an rclpy QoSProfile (e.g. an endpoint's offered QoS) to a rosbags Qos."""

    def member(enum: type, value: object, default: object) -> object:
        name = getattr(value, 'name', str(value)).upper()
        return enum.__members__.get(name, default)  # type: ignore[attr-defined]

    return Qos(
        history=member(QosHistory, profile.history, QosHistory.KEEP_LAST),  # type: ignore[arg-type]
        depth=int(profile.depth),
        reliability=member(QosReliability, profile.reliability,  # type: ignore[arg-type]
                           QosReliability.RELIABLE),
        durability=member(QosDurability, profile.durability,  # type: ignore[arg-type]
                          QosDurability.VOLATILE),
        deadline=_duration(profile.deadline),
        lifespan=_duration(profile.lifespan),
        liveliness=member(QosLiveliness, profile.liveliness,  # type: ignore[arg-type]
                          QosLiveliness.AUTOMATIC),
        liveliness_lease_duration=_duration(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def to_rclpy(offered: Sequence[Qos]) -> QoSProfile:
    """The publisher QoS to replay a topic recorded with these offered profiles.

    Like ``ros2 bag play``: reliable only if every recorded publisher was reliable, transient
    local only if every one was (so latched topics such as ``planner/path`` stay latched),
    keep-last with the largest recorded depth (at least 1). No profile: reliable, volatile, 10.
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if not offered:
        return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
    reliable = all(q.reliability == QosReliability.RELIABLE for q in offered)
    latched = all(q.durability == QosDurability.TRANSIENT_LOCAL for q in offered)
    depth = max([max(1, int(q.depth)) for q in offered])
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def subscription_qos(offered: Sequence[Qos]) -> QoSProfile:
    """The recorder's subscription QoS, compatible with every offered profile.

    Best effort if any publisher is best effort (a reliable reader would not match it),
    transient local only if all publishers are (to receive latched samples), keep-last
    :data:`RECORD_DEPTH` (or the largest offered depth, if larger): the reader's queue must hold
    a burst the recorder's executor has not taken yet. With depth 100, a fresh-clone CI run
    recorded 100 of a 150-message burst (keep-last dropped the oldest 50).
    """
    profile = to_rclpy(offered)
    profile.depth = max(RECORD_DEPTH, profile.depth)
    return profile


RECORD_DEPTH = 5000
"""Keep-last depth of the recorder's subscriptions (:func:`subscription_qos`)."""

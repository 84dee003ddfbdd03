"""A synthetic guidance scene along an anatomy's centreline (tests, benchmark, screenshots).

Pure numpy: :func:`centerline_scene` gives the planned path (the centreline to one coronary
ostium), the target (its end), and for a tip index along it the tip pose (heading along the
centreline, offset from it), the next waypoint and the bend that turns the heading towards that
waypoint - the values a planner and a tracker would publish.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from cgail_planner.core.rotations import matrix_to_quaternion
from cgail_sim.ftl_model import frame_from_heading


@dataclass(frozen=True)
class ScenePose:
    """One tip sample of the scene."""

    position: np.ndarray
    """(3,) tip position, m."""
    quaternion: np.ndarray
    """(4,) tip orientation (x, y, z, w)."""
    waypoint: np.ndarray
    """(3,) next waypoint, m."""
    bend: tuple[float, float]
    """(alpha, gamma) turning the heading towards the waypoint, rad."""


def centerline_scene(path: np.ndarray, index: float, lookahead: int = 6,
                     offset: float = 0.002) -> ScenePose:
    """The tip at fractional centreline ``index``, heading slightly off the path.

    Args:
        path: (P, 3) centreline, m.
        index: position along it in waypoint units, 0..P-1.
        lookahead: the next waypoint is this many waypoints ahead.
        offset: lateral offset of the tip from the centreline, m.
    """
    p = np.asarray(path, dtype=float)
    i0 = int(np.clip(math.floor(index), 0, len(p) - 2))
    u = float(np.clip(index - i0, 0.0, 1.0))
    centre = (1 - u) * p[i0] + u * p[i0 + 1]
    tangent = p[min(i0 + 2, len(p) - 1)] - p[max(i0 - 1, 0)]
    tangent /= np.linalg.norm(tangent)
    side = np.cross(tangent, [0.0, 0.0, 1.0])
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-9 else np.array([1.0, 0, 0])
    tip = centre + offset * side
    heading = tangent + 0.15 * side
    rot = frame_from_heading(heading)
    waypoint = p[min(i0 + lookahead, len(p) - 1)]
    d = rot.T @ (waypoint - tip)
    alpha = math.atan2(d[2], d[1])
    gamma = math.atan2(-d[0], math.hypot(d[1], d[2]))
    return ScenePose(tip, matrix_to_quaternion(rot), waypoint, (alpha, gamma))

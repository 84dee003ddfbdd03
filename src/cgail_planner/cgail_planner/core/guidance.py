"""Guidance along a planned path: next waypoint and the suggested bend (the paper's internal view).

Pure numpy, no rclpy. Conventions follow :mod:`cgail_sim.ftl_model`: the tip pose is
``[R | p]`` with the heading ``y_A = R[:, 1]``; a bend ``(alpha, gamma)`` of the steerable
segment turns the heading about ``x_A`` (alpha, ``y_A`` towards ``z_A``) and about ``z_A``
(gamma, ``y_A`` towards ``-x_A``) by ``bend * dl / L`` per inserted length ``dl``
(constant-curvature follow-the-leader, segment length ``L``).

**Next waypoint.** The path is a polyline resampled at a uniform arc length. The tip is projected
on it (closest point of the polyline, searched in a window around the last projection so a path
that folds back on itself is followed in order); the next waypoint is the path point
``lookahead`` m of arc further on (the path's end when less is left).

**Suggested bend.** With ``d = R^T (w - p)`` the waypoint in the tip frame and ``theta`` the
angle between the heading and ``d``, the circular arc that leaves ``p`` along the heading and
passes through ``w`` turns by ``2 theta`` over the arc length ``s = |d| theta / sin(theta)``
(tangent-chord angle), so its curvature is ``kappa = 2 sin(theta) / |d|``. The bend that
produces that curvature is ``|bend| = kappa * L``, capped at ``max_bend``; it points in the
``(alpha, gamma)`` direction ``(d_z, -d_x) / hypot(d_x, d_z)``. A waypoint behind the tip
(``theta > 90 deg``) asks for the full bend towards it.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from numpy.typing import NDArray

from cgail_sim.ftl_model import CatheterConfig

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class GuidanceConfig:
    """How guidance is computed from the tip pose and the planned path."""

    lookahead: float = 0.025
    """Arc length from the tip's projection on the path to the next waypoint, m; (0, 0.2]."""
    segment_length: float = CatheterConfig().segment_length
    """Steerable segment length L, m (the catheter model's); the bend per curvature;
    [1 mm, 0.5 m]."""
    max_bend: float = CatheterConfig().theta_max
    """Cap of the suggested bend magnitude hypot(alpha, gamma), rad; (0, pi/2]."""
    search_window: float = 0.030
    """Half-width of the arc window searched around the last projection, m; (0, 1]."""

    def __post_init__(self) -> None:
        _check_open_closed("lookahead", self.lookahead, 0.0, 0.2)
        _check_open_closed("segment_length", self.segment_length, 1e-3, 0.5, closed_low=True)
        _check_open_closed("max_bend", self.max_bend, 0.0, math.pi / 2.0)
        _check_open_closed("search_window", self.search_window, 0.0, 1.0)


def _check_open_closed(name: str, value: float, low: float, high: float,
                       closed_low: bool = False) -> None:
    """Raise ValueError unless ``low < value <= high`` (``low <= value`` when ``closed_low``)."""
    ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
          and math.isfinite(value) and (value >= low if closed_low else value > low)
          and value <= high + 1e-12)
    if not ok:
        bracket = "[" if closed_low else "("
        raise ValueError(f"{name} must be in {bracket}{low}, {high}], found {value!r}")


@dataclass(frozen=True)
class Guidance:
    """Guidance for one tip pose."""

    next_waypoint: FloatArray
    """(3,) the path point ``lookahead`` ahead of the tip's projection, m."""
    bend: tuple[float, float]
    """Suggested ``(alpha, gamma)``, rad (magnitude <= ``max_bend``)."""
    heading_error: float
    """Angle between the heading and the direction to the next waypoint, rad, in [0, pi]."""
    cross_track: float
    """Distance from the tip to its projection on the path, m."""
    arc_position: float
    """Arc length of the projection from the path's start, m."""
    remaining: float
    """Arc length from the projection to the path's end, m."""
    distance_to_waypoint: float
    """Straight distance from the tip to the next waypoint, m."""


def suggested_bend(position: FloatArray, rotation: FloatArray, waypoint: FloatArray,
                   segment_length: float, max_bend: float) -> tuple[float, float, float]:
    """Bend that curves the tip from its pose onto ``waypoint`` (module docstring).

    Args:
        position: (3,) tip position, m.
        rotation: (3, 3) tip rotation (columns x_A, y_A, z_A).
        waypoint: (3,) point to reach, m.
        segment_length: steerable segment length L, m.
        max_bend: cap of ``hypot(alpha, gamma)``, rad.

    Returns:
        ``(alpha, gamma, theta)``: the bend (rad) and the heading error ``theta`` (rad).
    """
    d = rotation.T @ (waypoint - position)
    dist = math.sqrt(float(d @ d))
    if dist < 1e-12:
        return 0.0, 0.0, 0.0
    lateral = math.hypot(float(d[0]), float(d[2]))
    theta = math.atan2(lateral, float(d[1]))
    if lateral < 1e-12:
        return 0.0, 0.0, theta
    if theta >= math.pi / 2.0:
        magnitude = max_bend
    else:
        magnitude = min(2.0 * math.sin(theta) / dist * segment_length, max_bend)
    return magnitude * float(d[2]) / lateral, -magnitude * float(d[0]) / lateral, theta


class PathFollower:
    """Projects tip poses on a fixed path and computes :class:`Guidance` (allocation-light).

    Args:
        path: (N, 3) path points (N >= 2), uniformly resampled, m.
        config: guidance parameters.

    Raises:
        ValueError: a path with fewer than 2 points, non-finite values, or zero length.
    """

    def __init__(self, path: FloatArray, config: GuidanceConfig | None = None) -> None:
        pts = np.asarray(path, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 2:
            raise ValueError(f"path must have shape (N >= 2, 3), found {pts.shape}")
        if not np.isfinite(pts).all():
            raise ValueError("path must be finite, found NaN or inf")
        self.config = config or GuidanceConfig()
        self.points = np.ascontiguousarray(pts)
        seg = np.diff(pts, axis=0)
        self._seg = seg
        self._seg_len2 = np.einsum("ij,ij->i", seg, seg)
        # (a zero-length segment divides by 1: its t is 0)
        self._seg_den = np.where(self._seg_len2 > 0.0, self._seg_len2, 1.0)
        lengths = np.sqrt(self._seg_len2)
        self.arc = np.concatenate([[0.0], np.cumsum(lengths)])
        if self.arc[-1] <= 0.0:
            raise ValueError("path must have a positive length, found 0")
        self.length = float(self.arc[-1])
        self._last_seg: int | None = None
        spacing = self.length / (len(pts) - 1)
        self._window = max(2, math.ceil(self.config.search_window / max(spacing, 1e-9)))

    def reset(self) -> None:
        """Forget the last projection (the next query searches the whole path)."""
        self._last_seg = None

    def project(self, position: FloatArray) -> tuple[int, float, FloatArray]:
        """Closest point of the path to ``position``.

        Returns:
            ``(segment index, arc length, closest point)``.
        """
        n_seg = len(self._seg)
        if self._last_seg is None:
            lo, hi = 0, n_seg
        else:
            lo = max(0, self._last_seg - self._window)
            hi = min(n_seg, self._last_seg + self._window + 1)
        a = self.points[lo:hi]
        seg = self._seg[lo:hi]
        # (ndarray methods rather than numpy's function wrappers: the same ufuncs, once per
        # tip pose in two nodes)
        t = np.einsum("ij,ij->i", position - a, seg) / self._seg_den[lo:hi]
        t.clip(0.0, 1.0, out=t)
        closest = a + t[:, None] * seg
        diff = closest - position
        k = int(np.einsum("ij,ij->i", diff, diff).argmin())
        i = lo + k
        self._last_seg = i
        arc = float(self.arc[i] + t[k] * math.sqrt(float(self._seg_len2[i])))
        return i, arc, closest[k]

    def point_at(self, arc: float) -> FloatArray:
        """Path point at arc length ``arc`` (clamped to the path), m."""
        s = min(max(arc, 0.0), self.length)
        i = int(self.arc.searchsorted(s, side="right")) - 1
        i = min(max(i, 0), len(self._seg) - 1)
        seg_len = self.arc[i + 1] - self.arc[i]
        t = 0.0 if seg_len <= 0.0 else (s - self.arc[i]) / seg_len
        return self.points[i] + t * self._seg[i]

    def guide(self, position: FloatArray, rotation: FloatArray) -> Guidance:
        """Guidance for the tip pose ``[rotation | position]``."""
        cfg = self.config
        _, arc, closest = self.project(position)
        waypoint = self.point_at(arc + cfg.lookahead)
        alpha, gamma, theta = suggested_bend(position, rotation, waypoint, cfg.segment_length,
                                             cfg.max_bend)
        to_closest, to_waypoint = closest - position, waypoint - position
        return Guidance(  # (norms as np.linalg.norm computes a vector's: sqrt of its dot)
            next_waypoint=waypoint, bend=(alpha, gamma), heading_error=theta,
            cross_track=math.sqrt(float(to_closest @ to_closest)), arc_position=arc,
            remaining=self.length - arc,
            distance_to_waypoint=math.sqrt(float(to_waypoint @ to_waypoint)))

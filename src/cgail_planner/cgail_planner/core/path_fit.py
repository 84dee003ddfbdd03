"""B-spline fitting, arc-length resampling and closest-point queries for planned paths.

The paper (section IV-C, "Tracking Error") compares the EM trajectory with "the desired path ...
obtained through path planning, followed by B-spline curve fitting and resampling". This module
is that step, in pure numpy/scipy (no rclpy): positions in metres, arrays of shape ``(N, 3)``.

* :func:`fit_path` fits an interpolating (``smoothing = 0``) or smoothing cubic B-spline through
  the planned waypoints with ``scipy.interpolate.splprep`` (chord-length parameter), evaluates it
  densely and resamples it at a uniform arc-length ``spacing``.
* :func:`closest_points` gives, for each query point, the closest point of the resampled
  polyline (exact point-to-segment projection on the segments around the nearest vertices).
* :func:`resample_by_arc_length` and :func:`discrete_curvature` serve the tip-trajectory
  curvature metric.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import splev, splprep
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]

#: Consecutive points closer than this (m) are treated as duplicates (splprep rejects them).
DUPLICATE_TOL = 1e-9


class PathFitError(ValueError):
    """A path or trajectory cannot be fitted/resampled (too few points, NaN, wrong shape)."""


@dataclass(frozen=True)
class PathFitConfig:
    """How a planned path is turned into the desired path of the tracking-error metric."""

    spacing: float = 0.5e-3
    """Arc-length spacing of the resampled path (m), > 0. The chord error of the polyline is
    about spacing^2 / (8 R) for a bend of radius R (0.5 mm, R = 20 mm: 1.6 um)."""

    smoothing: float = 0.0
    """splprep smoothing per waypoint (m^2): s = smoothing * N. 0 interpolates the waypoints."""

    degree: int = 3
    """B-spline degree, 1..5 (3: cubic, as in the paper). Lowered to N-1 for N <= degree
    waypoints."""

    oversample: int = 20
    """Spline evaluations per waypoint before the arc-length resampling, >= 2."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.spacing) and self.spacing > 0.0):
            raise ValueError(f'spacing must be a positive number of metres, found {self.spacing}')
        if not (np.isfinite(self.smoothing) and self.smoothing >= 0.0):
            raise ValueError(f'smoothing must be >= 0, found {self.smoothing}')
        if not 1 <= self.degree <= 5:
            raise ValueError(f'degree must be in 1..5, found {self.degree}')
        if self.oversample < 2:
            raise ValueError(f'oversample must be >= 2, found {self.oversample}')


def _as_points(points: NDArray[np.floating], name: str) -> FloatArray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise PathFitError(f'{name} must have shape (N, 3), found {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise PathFitError(f'{name} must be finite, found NaN or inf')
    return arr


def drop_duplicates(points: NDArray[np.floating], tol: float = DUPLICATE_TOL) -> FloatArray:
    """Remove points that repeat the previous kept point (within ``tol`` metres)."""
    arr = _as_points(points, 'points')
    if len(arr) < 2:
        return arr
    step = np.linalg.norm(np.diff(arr, axis=0), axis=1)
    keep = np.concatenate(([True], step > tol))
    return arr[keep]


def polyline_length(points: NDArray[np.floating]) -> float:
    """Total length (m) of the polyline through ``points``."""
    arr = np.asarray(points, dtype=np.float64)
    if len(arr) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(arr, axis=0), axis=1)))


def resample_by_arc_length(points: NDArray[np.floating], spacing: float) -> FloatArray:
    """Resample a polyline at uniform arc length (linear interpolation along the polyline).

    Args:
        points: ``(N, 3)`` polyline vertices (m), N >= 2 after removing duplicates.
        spacing: Target arc-length step (m); the actual step is ``length / ceil(length/spacing)``
            so both end points are kept.

    Returns:
        ``(M, 3)`` points, ``M >= 2``, first and last equal to the input's.

    Raises:
        PathFitError: Fewer than two distinct points or a bad spacing.
    """
    if not (np.isfinite(spacing) and spacing > 0.0):
        raise PathFitError(f'spacing must be a positive number of metres, found {spacing}')
    arr = drop_duplicates(points)
    if len(arr) < 2:
        raise PathFitError(f'expected at least 2 distinct points to resample, found {len(arr)}')
    seg = np.linalg.norm(np.diff(arr, axis=0), axis=1)
    s = np.concatenate(([0.0], np.cumsum(seg)))
    count = max(1, int(np.ceil(s[-1] / spacing - 1e-9)))
    s_new = np.linspace(0.0, s[-1], count + 1)
    return np.column_stack([np.interp(s_new, s, arr[:, k]) for k in range(3)])


def fit_path(
    waypoints: NDArray[np.floating], config: PathFitConfig | None = None
) -> FloatArray:
    """Fit a B-spline through planned waypoints and resample it at uniform arc length.

    Args:
        waypoints: ``(N, 3)`` planned path (m), N >= 2 distinct points.
        config: Fit settings; defaults to :class:`PathFitConfig`.

    Returns:
        ``(M, 3)`` desired path, points ``config.spacing`` apart along the spline.

    Raises:
        PathFitError: Fewer than two distinct waypoints, NaN, wrong shape.
    """
    cfg = config or PathFitConfig()
    pts = drop_duplicates(_as_points(waypoints, 'waypoints'))
    if len(pts) < 2:
        raise PathFitError(f'expected at least 2 distinct waypoints, found {len(pts)}')
    if len(pts) == 2:
        return resample_by_arc_length(pts, cfg.spacing)
    degree = min(cfg.degree, len(pts) - 1)
    chord = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    u = np.concatenate(([0.0], np.cumsum(chord)))
    u /= u[-1]
    tck, _ = splprep(pts.T, u=u, k=degree, s=cfg.smoothing * len(pts))
    dense_u = np.linspace(0.0, 1.0, cfg.oversample * len(pts))
    dense = np.column_stack(splev(dense_u, tck))
    return resample_by_arc_length(dense, cfg.spacing)


def closest_points(
    queries: NDArray[np.floating], polyline: NDArray[np.floating], neighbours: int = 4
) -> tuple[FloatArray, FloatArray]:
    """Closest point of a polyline to each query point.

    The ``neighbours`` nearest vertices of each query are found with a KD-tree and the query is
    projected onto the segments on both sides of each of them; the nearest projection wins.
    On a resampled path (uniform spacing) this is the exact closest point.

    Args:
        queries: ``(K, 3)`` points (m).
        polyline: ``(M, 3)`` vertices (m), M >= 1.
        neighbours: Nearest vertices whose adjacent segments are tested, >= 1.

    Returns:
        ``(distances (K,), closest (K, 3))``.
    """
    q = _as_points(queries, 'queries')
    line = _as_points(polyline, 'polyline')
    if len(line) == 0:
        raise PathFitError('polyline must have at least 1 point, found 0')
    if len(q) == 0:
        return np.zeros(0), np.zeros((0, 3))
    if len(line) == 1:
        diff = q - line[0]
        return np.linalg.norm(diff, axis=1), np.repeat(line[:1], len(q), axis=0)
    k = int(min(max(1, neighbours), len(line)))
    _, idx = cKDTree(line).query(q, k=k)
    idx = np.asarray(idx).reshape(len(q), k)
    # Segment start indices: the segment before and after each neighbour vertex.
    starts = np.concatenate((idx - 1, idx), axis=1).clip(0, len(line) - 2)
    a = line[starts]  # (K, 2k, 3)
    b = line[starts + 1]
    ab = b - a
    denom = np.einsum('ijk,ijk->ij', ab, ab)
    t = np.einsum('ijk,ijk->ij', q[:, None, :] - a, ab) / np.where(denom > 0.0, denom, 1.0)
    proj = a + t.clip(0.0, 1.0)[..., None] * ab
    d2 = np.einsum('ijk,ijk->ij', proj - q[:, None, :], proj - q[:, None, :])
    best = np.argmin(d2, axis=1)
    rows = np.arange(len(q))
    return np.sqrt(d2[rows, best]), proj[rows, best]


def discrete_curvature(points: NDArray[np.floating]) -> FloatArray:
    """Menger curvature (1/m) at each interior vertex of a polyline.

    kappa_i = 4 * area(p_{i-1}, p_i, p_{i+1}) / (|a| |b| |c|): exact for points on a circle.

    Args:
        points: ``(N, 3)`` points; N < 3 gives an empty array.

    Returns:
        ``(N - 2,)`` curvatures (1/m).
    """
    arr = _as_points(points, 'points')
    if len(arr) < 3:
        return np.zeros(0)
    a = arr[1:-1] - arr[:-2]
    b = arr[2:] - arr[1:-1]
    c = arr[2:] - arr[:-2]
    cross = np.linalg.norm(np.cross(a, b), axis=1)
    denom = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) * np.linalg.norm(c, axis=1)
    return np.where(denom > 0.0, 2.0 * cross / np.where(denom > 0.0, denom, 1.0), 0.0)

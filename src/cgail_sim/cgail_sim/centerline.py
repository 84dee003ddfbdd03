"""Lumen centrelines from the wall by the Voronoi (medial-axis) method.

The centreline is computed from the WALL surface only, not from the generator's spine, so it
works for user meshes too (VMTK-style, Antiga et al. 2003):

1. sample the wall faces densely (area-weighted, deterministic seed);
2. ``scipy.spatial.Voronoi`` of the samples; the Voronoi vertices inside the lumen approximate
   the medial axis, and the distance from each to the nearest wall sample is its maximal
   inscribed sphere radius;
3. a graph on the Voronoi edges between inside vertices, each edge weighted by
   ``length / r**2`` (r = mean inscribed radius of its ends), so paths keep to the middle of
   the lumen where the inscribed spheres are largest;
4. the shortest path (``scipy.sparse.csgraph.dijkstra``) from the well-centred Voronoi vertex
   nearest the descending-aorta start point to the one nearest each coronary ostium;
5. arc-length resampling, Gaussian smoothing and resampling to ``n_waypoints`` points; the
   radius at each point is re-measured as the distance to the nearest wall sample.

Results are cached in memory per mesh (keyed by :attr:`Anatomy.content_hash`) and on disk under
``~/.cache/cgail_planner/`` (set ``CGAIL_PLANNER_NO_DISK_CACHE=1`` to disable), keyed there also
by this module's source and numpy's SIMD level (:mod:`cgail_sim.disk_cache`): numpy's
SIMD paths change the last bits of the result even for the same mesh (1.5e-16 m between the
AVX-512 and AVX2 paths for the default aorta), so a centerline computed by another commit or
another CPU's numpy is never read back.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
import itertools
import os
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree, Voronoi

from cgail_sim import disk_cache
from cgail_sim.anatomy import Anatomy, AnatomyError

__all__ = ["Centerline", "CenterlineError", "compute_centerlines", "medial_paths", "sample_wall"]

_SAMPLE_SPACING = 0.0018
"""Mean spacing of the wall samples fed to the Voronoi diagram (m)."""
_MAX_SAMPLES = 20000
_SMOOTH_SIGMA = 0.003
"""Standard deviation of the Gaussian smoothing along the path (m of arc length)."""


class CenterlineError(AnatomyError):
    """Raised when no centreline can be found (e.g. an ostium unreachable from the exit)."""


@dataclass(frozen=True)
class Centerline:
    """A centreline from the descending aorta to one coronary ostium (or, from
    :func:`medial_paths`, to any goal in the lumen)."""

    branch: str
    """'left' or 'right': the coronary ostium the line leads to (:func:`medial_paths`: the
    goal's name)."""
    points: np.ndarray
    """(P, 3) waypoints in m, from the descending aorta to the ostium (goal), evenly spaced."""
    radii: np.ndarray
    """(P,) maximal inscribed sphere radius at each waypoint, m."""

    @property
    def length(self) -> float:
        """Arc length of the polyline, m."""
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


def sample_wall(anatomy: Anatomy, spacing: float = _SAMPLE_SPACING,
                max_samples: int = _MAX_SAMPLES, seed: int = 0) -> np.ndarray:
    """Area-weighted deterministic samples of the wall faces plus the wall vertices.

    Args:
        anatomy: the anatomy to sample.
        spacing: mean distance between samples, m.
        max_samples: upper bound on the number of random samples.
        seed: random seed (the result is deterministic for a given seed).

    Returns:
        (S, 3) points on the wall, m.
    """
    faces = anatomy.faces[anatomy.wall_face_mask]
    tri = anatomy.vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n = int(min(max_samples, max(1000, area.sum() / spacing**2)))
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(faces), size=n, p=area / area.sum())
    u = rng.random((n, 2))
    flip = u.sum(axis=1) > 1.0
    u[flip] = 1.0 - u[flip]
    t = tri[idx]
    pts = t[:, 0] + u[:, :1] * (t[:, 1] - t[:, 0]) + u[:, 1:] * (t[:, 2] - t[:, 0])
    wall_vertices = anatomy.vertices[np.unique(faces)]
    return np.vstack([wall_vertices, pts])


def _mesh_key(anatomy: Anatomy, n_waypoints: int) -> str:
    """Cache key: the mesh and landmarks (incl. the start point the path starts from), the
    waypoint count, this module's source and the numerical environment."""
    return disk_cache.cache_key(sources=(__file__, disk_cache.__file__),
                                inputs=f"{anatomy.content_hash}|{n_waypoints}")


def _resample(points: np.ndarray, n: int) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-12])
    points = points[keep]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    target = np.linspace(0.0, arc[-1], n)
    return np.stack([np.interp(target, arc, points[:, k]) for k in range(3)], axis=1)


def _smooth(points: np.ndarray, sigma: float) -> np.ndarray:
    step = 0.0005
    arc_len = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
    n = max(8, int(arc_len / step))
    dense = _resample(points, n)
    sm = gaussian_filter1d(dense, sigma=sigma / step, axis=0, mode="nearest")
    # Keep the ends where they are: blend from the raw to the smoothed path over ~2 sigma.
    w = np.ones(n)
    ramp = np.clip(np.arange(n) * step / (2.0 * sigma), 0.0, 1.0)
    w = np.minimum(ramp, ramp[::-1])[:, None]
    return (1.0 - w) * dense + w * sm


class _Medial:
    """The inside Voronoi graph of one anatomy (shared by both branches)."""

    def __init__(self, anatomy: Anatomy) -> None:
        samples = sample_wall(anatomy)
        self.tree = cKDTree(samples)
        vor = Voronoi(samples)
        verts = vor.vertices
        lo = anatomy.vertices.min(axis=0)
        hi = anatomy.vertices.max(axis=0)
        cand = np.flatnonzero(np.all((verts > lo) & (verts < hi), axis=1))
        inside = np.zeros(len(verts), dtype=bool)
        inside[cand] = anatomy.contains(verts[cand])
        radius = np.zeros(len(verts))
        radius[inside] = self.tree.query(verts[inside])[0]
        ridges = vor.ridge_vertices
        lens = np.fromiter((len(r) for r in ridges), dtype=np.int64, count=len(ridges))
        flat = np.fromiter(itertools.chain.from_iterable(ridges), dtype=np.int64,
                           count=int(lens.sum()))
        starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
        nxt = np.arange(len(flat)) + 1
        nxt[starts + lens - 1] = starts          # each ridge polygon closes on itself
        e = np.stack([flat, flat[nxt]], axis=1)
        e = e[(e >= 0).all(axis=1)]
        e = e[inside[e[:, 0]] & inside[e[:, 1]]]
        e = np.unique(np.sort(e, axis=1), axis=0)
        e = e[e[:, 0] != e[:, 1]]
        length = np.linalg.norm(verts[e[:, 0]] - verts[e[:, 1]], axis=1)
        r_mid = 0.5 * (radius[e[:, 0]] + radius[e[:, 1]])
        weight = length / np.maximum(r_mid, 1e-5) ** 2 + 1e-12
        n = len(verts)
        self.graph = coo_matrix((weight, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
        self.vertices = verts
        self.radius = radius
        self.nodes = np.unique(e)
        if len(self.nodes) == 0:
            raise CenterlineError("expected Voronoi vertices inside the lumen, found none")
        self.node_tree = cKDTree(verts[self.nodes])

    def nearest_node(self, point: np.ndarray) -> int:
        return int(self.nodes[self.node_tree.query(point)[1]])

    def start_node(self, anatomy: Anatomy) -> int:
        """Well-centred node near ``anatomy.start_point`` (large inscribed sphere, close)."""
        return self.centred_node(anatomy.start_point, self.nodes)

    def centred_node(self, point: np.ndarray, nodes: np.ndarray) -> int:
        """Well-centred node of ``nodes`` near ``point`` (large inscribed sphere, close)."""
        d = np.linalg.norm(self.vertices[nodes] - point, axis=1)
        score = d - 0.8 * self.radius[nodes]
        return int(nodes[np.argmin(score)])


_MEMORY: dict[str, dict[str, Centerline]] = {}


def _disk_path(key: str) -> Path | None:
    root = disk_cache.cache_dir()
    return None if root is None else root / f"centerline_{key}.npz"


def _load_disk(key: str) -> dict[str, Centerline] | None:
    path = _disk_path(key)
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path) as data:
            return {b: Centerline(b, data[f"{b}_points"], data[f"{b}_radii"])
                    for b in ("left", "right")}
    except (OSError, KeyError, ValueError):
        return None


def _save_disk(key: str, lines: dict[str, Centerline]) -> None:
    path = _disk_path(key)
    if path is None:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        arrays: dict[str, np.ndarray] = {}
        for b, c in lines.items():
            arrays[f"{b}_points"] = c.points
            arrays[f"{b}_radii"] = c.radii
        np.savez(tmp, **arrays)  # type: ignore[arg-type]  # numpy stubs mistype **kwds
        os.replace(tmp, path)
    except OSError:
        pass


def compute_centerlines(anatomy: Anatomy, n_waypoints: int = 100) -> dict[str, Centerline]:
    """Centrelines from the descending aorta to the left and right coronary ostia.

    Args:
        anatomy: the lumen (rest shape) and its landmarks.
        n_waypoints: number of evenly spaced waypoints per centreline (>= 10).

    Returns:
        ``{'left': Centerline, 'right': Centerline}``.

    Raises:
        ValueError: ``n_waypoints`` below 10.
        CenterlineError: an ostium cannot be reached through the lumen from the exit.
    """
    if n_waypoints < 10:
        raise ValueError(f"n_waypoints must be >= 10, found {n_waypoints}")
    key = _mesh_key(anatomy, n_waypoints)
    if key in _MEMORY:
        return dict(_MEMORY[key])
    cached = _load_disk(key)
    if cached is not None:
        _MEMORY[key] = cached
        return dict(cached)
    lines = _trace(anatomy, {branch: anatomy.ostia[branch] for branch in ("left", "right")},
                   lambda length: n_waypoints, "ostium", centred_goals=False)
    _MEMORY[key] = lines
    _save_disk(key, lines)
    return dict(lines)


def medial_paths(anatomy: Anatomy, goals: Mapping[str, np.ndarray],
                 spacing: float = 0.001) -> dict[str, Centerline]:
    """Centrelines from the descending aorta to any points of the lumen, traced exactly as
    :func:`compute_centerlines` traces those to the ostia (the same medial graph, start,
    shortest paths, smoothing and radii), resampled every ``spacing``. Not cached.

    Args:
        anatomy: the lumen (rest shape) and its landmarks.
        goals: name -> point (3,) in m, e.g. a point above ``anatomy.annulus_center`` for
            the aortic trunk, a point just inside a cap for a branch. Each path ends at the
            well-centred medial vertex near its point (as the start is chosen: the one that
            minimises its distance from the point less 0.8 times its inscribed radius, so that
            a path into a wide root ends in its middle), among those the start reaches (a real
            lumen's medial graph can hold small islands, e.g. in a narrow branch end).
        spacing: distance between the waypoints, m (> 0).

    Returns:
        ``{name: Centerline}``, each from the descending start to its goal, ``branch`` set to
        the goal's name.

    Raises:
        ValueError: ``spacing`` not positive.
        CenterlineError: no medial vertex the start reaches lies near a goal.
    """
    if not spacing > 0.0:
        raise ValueError(f"spacing must be > 0, found {spacing!r}")
    return _trace(anatomy, {k: np.asarray(v, dtype=float) for k, v in goals.items()},
                  lambda length: max(10, round(length / spacing) + 1), "goal",
                  centred_goals=True)


_GOAL_REACH = 0.010
"""Farthest a :func:`medial_paths` goal may lie from every medial vertex the start reaches
(m)."""


def _trace(anatomy: Anatomy, goals: Mapping[str, np.ndarray], count: Callable[[float], int],
           what: str, *, centred_goals: bool) -> dict[str, Centerline]:
    """Shortest medial paths from the start to each goal point (its nearest medial vertex, or
    with ``centred_goals`` the well-centred vertex near it among those the start reaches),
    smoothed and resampled to ``count(length)`` points, with the inscribed radius re-measured
    at each."""
    medial = _Medial(anatomy)
    start = medial.start_node(anatomy)
    dist, pred = dijkstra(medial.graph, directed=False, indices=start, return_predecessors=True)
    lines: dict[str, Centerline] = {}
    reached = medial.nodes[np.isfinite(dist[medial.nodes])]
    for branch, point in goals.items():
        goal = medial.nearest_node(point)
        if centred_goals and len(reached):
            gap = np.linalg.norm(medial.vertices[reached] - point, axis=1)
            if gap.min() <= _GOAL_REACH:
                goal = medial.centred_node(point, reached)
        if not np.isfinite(dist[goal]):
            raise CenterlineError(
                f"expected the {branch} {what} to be reachable from the exit through the lumen, "
                f"found it cut off ({len(reached)} of {len(medial.nodes)} medial nodes "
                "reachable)")
        path = [goal]
        while path[-1] != start:
            path.append(int(pred[path[-1]]))
        pts = medial.vertices[path[::-1]]
        pts = _smooth(pts, _SMOOTH_SIGMA) if len(pts) > 3 else pts
        length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
        pts = _resample(pts, count(length))
        radii = medial.tree.query(pts)[0]
        lines[branch] = Centerline(branch=branch, points=pts, radii=radii)
    return lines

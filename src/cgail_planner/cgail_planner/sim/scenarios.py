"""Start configurations and targets of the navigation task (paper, section IV-A).

* **Starts** (3 by default): on the Voronoi centerline of the descending aorta, the first at the
  centerline point nearest ``Anatomy.start_point`` and the others evenly spaced cranially along the
  centerline, the last ``start_span`` = 53 mm (arc length) above the first. The tip heading is the
  local centerline tangent (central difference over +-5 mm) and the tip x axis is perpendicular to
  the world x axis (deterministic). Behind each start an introducer runs straight back along
  ``-y_A`` to 5 mm beyond the exit plane, so retraction can pull the tip out (``r_exit``).
* **Targets** (5 by default): seeded rejection sampling, uniform in the ``target_radius`` = 30 mm
  sphere centred at the midpoint of the two coronary ostia; a candidate is kept when it lies inside
  the lumen (``Anatomy.contains``), at least ``target_clearance`` = 4.5 mm (tip radius + 1 mm)
  from the wall (distance to the nearest wall vertex or wall-face centroid) and at least 5 mm
  from the targets already chosen. Each target is attached to its nearest wall vertex ``i`` with
  the rest offset ``o = p_g - v_i``; in dynamic mode ``p_g(t) = wall.vertex_position(i) + o``.
  Its ``branch`` (``left``/``right``) is the nearer ostium; its centerline pays ``r_centerline``.
* ``d_max``: the largest distance between any wall vertex (rest shape) and any target, i.e. the
  largest agent-target distance with the agent in the lumen (``u = ||p_g - p_t|| / d_max``).
* ``origin``: the centre of the anatomy's bounding box (observed positions are relative to it).

The set is a pure function of the anatomy, the centerlines and the seed; :func:`load_world`
caches it per ``(anatomy name, n_waypoints, seed)`` so many environments share one copy.
"""

from __future__ import annotations

from dataclasses import dataclass
import functools
import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cgail_planner.sim.anatomy import Anatomy, build_anatomy
from cgail_planner.sim.centerline import Centerline, compute_centerlines
from cgail_planner.sim.ftl_model import frame_from_heading
from cgail_planner.sim.ftl_model import introducer_tail as ftl_introducer_tail

FloatArray = NDArray[np.float64]

#: Branch names of the centerlines / coronary ostia.
BRANCHES = ("left", "right")


class ScenarioError(ValueError):
    """The anatomy does not admit the requested scenario set (e.g. no valid target found)."""


@dataclass(frozen=True)
class StartConfig:
    """A start configuration ``q_0`` in the descending aorta."""

    position: FloatArray
    """(3,) tip position, m."""
    rotation: FloatArray
    """(3, 3) tip rotation (columns x_A, y_A, z_A; y_A = heading)."""
    introducer_tail: FloatArray
    """(3,) proximal end of the introducer, 5 mm outside the exit plane."""
    arc_offset: float
    """Arc length along the centerline above the first start, m."""


@dataclass(frozen=True)
class TargetConfig:
    """A target ``p_g`` attached to a wall particle."""

    position: FloatArray
    """(3,) rest position, m."""
    vertex: int
    """Index of the wall vertex it is attached to."""
    offset: FloatArray
    """(3,) rest offset from that vertex, m."""
    branch: str
    """Coronary side (``left``/``right``): whose centerline pays r_centerline."""


@dataclass(frozen=True)
class ScenarioSet:
    """Starts, targets and the normalisers of one anatomy."""

    starts: tuple[StartConfig, ...]
    targets: tuple[TargetConfig, ...]
    waypoints: dict[str, FloatArray]
    """Centerline waypoints per branch, (W, 3) each, descending aorta first."""
    d_max: float
    """Largest agent-target distance in the lumen, m."""
    origin: FloatArray
    """(3,) origin of the observed positions, m."""


@dataclass(frozen=True)
class World:
    """An anatomy with its centerlines and scenario set (shared, read-only)."""

    anatomy: Anatomy
    centerlines: dict[str, Centerline]
    scenarios: ScenarioSet


def _arc(points: FloatArray) -> FloatArray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _interp(points: FloatArray, arc: FloatArray, s: float) -> FloatArray:
    return np.array([np.interp(s, arc, points[:, k]) for k in range(3)])


def build_starts(anatomy: Anatomy, centerline: Centerline, *, n_starts: int = 3,
                 start_span: float = 0.053) -> tuple[StartConfig, ...]:
    """Start configurations along the descending-aorta part of ``centerline`` (module doc)."""
    pts = np.asarray(centerline.points, dtype=np.float64)
    arc = _arc(pts)
    i0 = int(np.argmin(np.linalg.norm(pts - anatomy.start_point, axis=1)))
    s0 = float(arc[i0])
    if s0 + start_span + 0.005 > arc[-1]:
        raise ScenarioError(
            f"expected a centerline longer than start_span {start_span} m above the start point, "
            f"found {arc[-1] - s0:.3f} m")
    offsets = np.linspace(0.0, start_span, n_starts) if n_starts > 1 else np.zeros(1)
    starts = []
    for off in offsets:
        s = s0 + float(off)
        p = _interp(pts, arc, s)
        tangent = _interp(pts, arc, s + 0.005) - _interp(pts, arc, max(s - 0.005, 0.0))
        rot = frame_from_heading(tangent)
        starts.append(StartConfig(position=p, rotation=rot,
                                  introducer_tail=introducer_tail(anatomy, p, rot),
                                  arc_offset=float(off)))
    return tuple(starts)


def introducer_tail(anatomy: Anatomy, position: FloatArray, rotation: FloatArray) -> FloatArray:
    """(3,) proximal end of the introducer behind a start pose in ``anatomy``
    (:func:`cgail_planner.sim.ftl_model.introducer_tail` at the anatomy's exit plane)."""
    return ftl_introducer_tail(anatomy.exit_point, anatomy.exit_normal, position, rotation)


#: Margin of the region an episode (or a planner's rollout) may visit around the anatomy, m.
BOUNDS_MARGIN = 0.01


def episode_bounds(anatomy: Anatomy) -> tuple[FloatArray, FloatArray]:
    """``(low, high)`` corners of the region the tip may visit: the anatomy's bounding box grown
    by :data:`BOUNDS_MARGIN`; beyond it the tip has left through an open end."""
    verts = np.asarray(anatomy.vertices, dtype=np.float64)
    return verts.min(axis=0) - BOUNDS_MARGIN, verts.max(axis=0) + BOUNDS_MARGIN


def build_targets(anatomy: Anatomy, *, n_targets: int = 5, target_radius: float = 0.030,
                  target_clearance: float = 0.0045, min_separation: float = 0.005,
                  seed: int = 0, max_candidates: int = 20000) -> tuple[TargetConfig, ...]:
    """Seeded targets near the coronary ostia, inside the lumen (module doc)."""
    rng = np.random.default_rng(seed)
    wall_faces = anatomy.faces[anatomy.wall_face_mask]
    wall_vids = np.unique(wall_faces)
    verts = np.asarray(anatomy.vertices, dtype=np.float64)
    samples = np.vstack([verts[wall_vids], verts[wall_faces].mean(axis=1)])
    wall_tree = cKDTree(samples)
    vert_tree = cKDTree(verts[wall_vids])
    centre = 0.5 * (anatomy.ostia["left"] + anatomy.ostia["right"])
    chosen: list[TargetConfig] = []
    tried = 0
    while len(chosen) < n_targets and tried < max_candidates:
        batch = 256
        tried += batch
        d = rng.normal(size=(batch, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        r = target_radius * rng.uniform(size=batch) ** (1.0 / 3.0)
        cand = centre + d * r[:, None]
        clearance, _ = wall_tree.query(cand)
        ok = clearance >= target_clearance
        if ok.any():
            ok[ok] = anatomy.contains(cand[ok])
        for p in cand[ok]:
            if any(np.linalg.norm(p - t.position) < min_separation for t in chosen):
                continue
            _, j = vert_tree.query(p)
            vid = int(wall_vids[j])
            branch = min(BRANCHES, key=lambda b: float(np.linalg.norm(p - anatomy.ostia[b])))
            chosen.append(TargetConfig(position=p.copy(), vertex=vid, offset=p - verts[vid],
                                       branch=branch))
            if len(chosen) == n_targets:
                break
    if len(chosen) < n_targets:
        raise ScenarioError(
            f"expected {n_targets} targets inside the lumen within {target_radius} m of the "
            f"ostia with {target_clearance} m wall clearance, found {len(chosen)}")
    return tuple(chosen)


def build_scenarios(anatomy: Anatomy, centerlines: dict[str, Centerline], *, seed: int = 0,
                    n_starts: int = 3, start_span: float = 0.053, n_targets: int = 5,
                    target_radius: float = 0.030) -> ScenarioSet:
    """The scenario set of ``anatomy`` (see the module docstring)."""
    missing = [b for b in BRANCHES if b not in centerlines]
    if missing:
        raise ScenarioError(f"expected centerlines {BRANCHES}, found {sorted(centerlines)}")
    starts = build_starts(anatomy, centerlines["left"], n_starts=n_starts, start_span=start_span)
    targets = build_targets(anatomy, n_targets=n_targets, target_radius=target_radius,
                            seed=seed)
    verts = np.asarray(anatomy.vertices, dtype=np.float64)
    d_max = max(float(np.linalg.norm(verts - t.position, axis=1).max()) for t in targets)
    origin = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
    waypoints = {b: np.array(centerlines[b].points, dtype=np.float64) for b in BRANCHES}
    if len({w.shape for w in waypoints.values()}) != 1:
        raise ScenarioError(
            f"expected centerlines with equal waypoint counts, found "
            f"{ {b: w.shape for b, w in waypoints.items()} }")
    for arr in (origin, *waypoints.values()):
        arr.setflags(write=False)
    return ScenarioSet(starts=starts, targets=targets, waypoints=waypoints, d_max=d_max,
                       origin=origin)


@functools.lru_cache(maxsize=8)
def load_world(anatomy_name: str, n_waypoints: int = 100, seed: int = 0) -> World:
    """Build (once per process) the anatomy, its centerlines and scenarios."""
    anatomy = build_anatomy(anatomy_name)
    centerlines = compute_centerlines(anatomy, n_waypoints=n_waypoints)
    scenarios = build_scenarios(anatomy, centerlines, seed=seed)
    if not math.isfinite(scenarios.d_max) or scenarios.d_max <= 0.0:
        raise ScenarioError(f"expected a positive d_max, found {scenarios.d_max}")
    return World(anatomy=anatomy, centerlines=centerlines, scenarios=scenarios)

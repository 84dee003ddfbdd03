"""Start configurations and targets of the navigation task (paper, section IV-A).

* **Starts** (3 by default): on the Voronoi centerline of the descending aorta, the first at the
  centerline point nearest ``Anatomy.start_point`` and the others evenly spaced cranially along the
  centerline, the last ``start_span`` = 53 mm (arc length) above the first. The tip heading is the
  local centerline tangent (central difference over +-5 mm) and the tip x axis is perpendicular to
  the world x axis (deterministic). Behind each start an introducer runs back to 5 mm beyond the
  exit plane, so retraction can pull the tip out (``r_exit``): straight back along ``-y_A``
  when that tube (the catheter's radius, :data:`INTRODUCER_RADIUS`) lies inside the lumen, as
  in both built-in anatomies; otherwise bent along the centerline (a descending aorta that
  curves near its open end); a start where neither fits is refused with the reason
  (:func:`introducer_path`).
* **Targets** (5 by default): seeded rejection sampling, uniform in the ``target_radius`` = 30 mm
  sphere centred at the midpoint of the two coronary ostia; a candidate is kept when it lies inside
  the lumen (``Anatomy.contains``), at least ``target_clearance`` = 4.5 mm (tip radius + 1 mm)
  from the wall (distance to the nearest wall vertex or wall-face centroid) and at least 5 mm
  from the targets already chosen. Each target is attached to its nearest wall vertex ``i`` with
  the rest offset ``o = p_g - v_i``; in dynamic mode ``p_g(t) = wall.vertex_position(i) + o``.
  Its ``branch`` (``left``/``right``) is the nearer ostium; its centerline pays ``r_centerline``.
* ``d_max``: the largest distance between any wall vertex (rest shape) and any target, i.e. the
  largest agent-target distance with the agent in the lumen (``u = ||p_g - p_t|| / d_max``).
  With targets drawn anew per episode (``EnvConfig.targets == "sphere"``,
  :class:`TargetSampler`) there is no fixed set to take the maximum over, so ``d_max`` is the
  same bound over every target the sampler can draw: the largest distance from a wall vertex
  to the sphere's centre plus its radius (``ScenarioSet.sphere_d_max``). It is a function of
  the anatomy alone (not of the seed or of the episode), so ``u`` keeps one scale through a
  training run, and it lies above every fixed set's ``d_max`` (``u`` stays in [0, 1]): by 6 %
  on ``default`` and 22 % on ``elongated``, by 1-24 % (mean 6 %) over population seeds 0-39
  and 10000-10019 (target set 0).
* ``origin``: the centre of the anatomy's bounding box (observed positions are relative to it).

The set is a pure function of the anatomy, the centerlines and the seed;
:func:`cgail_sim.worlds.load_world` builds it, with the centerlines, once per anatomy, name,
waypoint count and seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import functools
import itertools
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cgail_sim.anatomy import Anatomy, AnatomyError
from cgail_sim.centerline import Centerline
from cgail_sim.ftl_model import CatheterConfig, frame_from_heading
from cgail_sim.ftl_model import introducer_tail as ftl_introducer_tail

FloatArray = NDArray[np.float64]

#: Branch names of the centerlines / coronary ostia.
BRANCHES = ("left", "right")
#: Where an episode's target comes from: ``fixed``, one of the scenario set's targets (the
#: paper's 5); ``sphere``, drawn anew per episode by the same sampler (module docstring).
TARGET_MODES = ("fixed", "sphere")


class ScenarioError(AnatomyError):
    """The anatomy does not admit the requested scenario set (e.g. no valid target found, no
    introducer inside the lumen behind a start); an :class:`AnatomyError`, so every entry
    point that reports a bad anatomy reports this too."""


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
    introducer: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    """(K, 3) nodes of the introducer, proximal end first, the start excluded: ``[tail]`` for
    a straight one (the default, when none is given), more along a bent one
    (:func:`introducer_path`)."""

    def __post_init__(self) -> None:
        intro = np.asarray(self.introducer, dtype=np.float64).reshape(-1, 3)
        if len(intro) == 0:
            intro = np.asarray(self.introducer_tail, dtype=np.float64)[None]
        object.__setattr__(self, "introducer", intro)

    @property
    def bent(self) -> bool:
        """True when the introducer follows the centerline rather than a straight line."""
        return len(self.introducer) > 1


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
    """Largest agent-target distance in the lumen, m (over the fixed targets)."""
    origin: FloatArray
    """(3,) origin of the observed positions, m."""
    sphere_d_max: float
    """Largest distance between a rest wall vertex and any point of the target sphere, m: the
    ``d_max`` of targets drawn per episode (:meth:`TargetSampler.max_distance`)."""

    def d_max_for(self, targets: str) -> float:
        """The observation's ``d_max`` when targets are ``fixed`` (this set's) or drawn per
        episode in the ``sphere`` (module docstring)."""
        if targets not in TARGET_MODES:
            raise ValueError(f"targets must be one of {TARGET_MODES}, found {targets!r}")
        return self.sphere_d_max if targets == "sphere" else self.d_max


@dataclass(frozen=True)
class World:
    """An anatomy with its centerlines and scenario set (shared, read-only)."""

    anatomy: Anatomy
    centerlines: dict[str, Centerline]
    scenarios: ScenarioSet

    def introducer(self, position: FloatArray, rotation: FloatArray) -> FloatArray:
        """(K, 3) the introducer behind the tip pose ``[rotation | position]``
        (:func:`introducer_path` on the left centerline, as behind the starts).

        Raises:
            ScenarioError: neither a straight introducer nor one along the centerline lies
                inside the lumen behind this pose.
        """
        return introducer_path(self.anatomy, self.centerlines["left"].points, position,
                               rotation)


#: Radius of the introducer tube that must lie inside the rest lumen, m: the catheter's.
INTRODUCER_RADIUS = CatheterConfig().radius
#: How far the proximal end of the introducer lies beyond the exit plane, m (as
#: :func:`cgail_sim.ftl_model.introducer_tail`).
INTRODUCER_OVERHANG = 0.005
#: Sampling step of :func:`tube_clearance` along an introducer, m.
_INTRODUCER_SAMPLE = 0.001
#: Smallest step of the introducer check (:func:`_tube_problem`), m.
_TRACE_STEP = 2.5e-4


def _arc(points: FloatArray) -> FloatArray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _interp(points: FloatArray, arc: FloatArray, s: float) -> FloatArray:
    return np.array([np.interp(s, arc, points[:, k]) for k in range(3)])


def build_starts(anatomy: Anatomy, centerline: Centerline, *, n_starts: int = 3,
                 start_span: float = 0.053, introducer_radius: float = INTRODUCER_RADIUS
                 ) -> tuple[StartConfig, ...]:
    """Start configurations along the descending-aorta part of ``centerline`` (module doc).

    Raises:
        ScenarioError: a centerline too short for ``start_span``, or a start with no
            introducer of ``introducer_radius`` inside the lumen (:func:`introducer_path`;
            the message names the anatomy and the start).
    """
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
    for k, off in enumerate(offsets):
        s = s0 + float(off)
        p = _interp(pts, arc, s)
        tangent = _interp(pts, arc, s + 0.005) - _interp(pts, arc, max(s - 0.005, 0.0))
        rot = frame_from_heading(tangent)
        try:
            intro = introducer_path(anatomy, pts, p, rot, radius=introducer_radius)
        except ScenarioError as exc:
            raise ScenarioError(f"anatomy {anatomy.name!r}, start {k} ({off * 1e3:.0f} mm above "
                                f"start 0): {exc}") from None
        starts.append(StartConfig(position=p, rotation=rot, introducer_tail=intro[0],
                                  arc_offset=float(off), introducer=intro))
    return tuple(starts)


def introducer_tail(anatomy: Anatomy, position: FloatArray, rotation: FloatArray) -> FloatArray:
    """(3,) proximal end of the straight introducer behind a tip pose in ``anatomy``
    (:func:`cgail_sim.ftl_model.introducer_tail` at the anatomy's exit plane)."""
    return ftl_introducer_tail(anatomy.exit_point, anatomy.exit_normal, position, rotation)


@functools.lru_cache(maxsize=16)
def _rest_wall(anatomy: Anatomy) -> Any:
    """The rest-shape wall BVH of ``anatomy`` (caps transparent), for clearance queries."""
    from cgail_sim.raycast import WallBVH

    return WallBVH(np.asarray(anatomy.vertices, dtype=np.float64), anatomy.faces,
                   anatomy.wall_face_mask)


def _clearance_fn(anatomy: Anatomy) -> Any:
    """``q -> clearance``: on the lumen side of the exit plane, the distance from ``q`` to the
    rest wall (negative beyond it); inf beyond the exit plane (outside the anatomy)."""
    bvh = _rest_wall(anatomy)
    n = np.asarray(anatomy.exit_normal, dtype=np.float64)
    e = np.asarray(anatomy.exit_point, dtype=np.float64)

    def clearance(q: FloatArray) -> float:
        return -bvh.closest_point(q)[0] if float((q - e) @ n) < 0.0 else math.inf

    return clearance


def tube_clearance(anatomy: Anatomy, nodes: FloatArray,
                   step: float = _INTRODUCER_SAMPLE) -> tuple[float, FloatArray]:
    """The smallest clearance of the polyline ``nodes`` (proximal end first) from the rest wall
    of ``anatomy``, sampled every ``step``, and where it occurs.

    Returns:
        ``(clearance, point)``: m, negative where the axis runs beyond the wall; points beyond
        the exit plane are not counted (inf when none is on the lumen side).
    """
    clearance = _clearance_fn(anatomy)
    pts = np.asarray(nodes, dtype=np.float64)
    worst, where = math.inf, pts[-1]
    for a, b in itertools.pairwise(pts):
        m = max(math.ceil(float(np.linalg.norm(b - a)) / step), 1)
        for t in np.linspace(0.0, 1.0, m + 1):
            q = a + t * (b - a)
            c = clearance(q)
            if c < worst:
                worst, where = c, q
    return worst, where


def _tube_problem(anatomy: Anatomy, nodes: FloatArray, radius: float) -> str | None:
    """Why the tube of ``radius`` around the polyline ``nodes`` (proximal end first) does not
    lie inside the rest lumen of ``anatomy``, or None when it does.

    Only the part on the lumen side of the exit plane is checked (the proximal end lies
    beyond it). The clearance is the exact distance to the wall faces (caps are open).
    """
    bvh = _rest_wall(anatomy)
    n = np.asarray(anatomy.exit_normal, dtype=np.float64)
    e = np.asarray(anatomy.exit_point, dtype=np.float64)
    # Cheap and conservative (sphere tracing): the clearance and the depth below the exit
    # plane are 1-Lipschitz along the axis, so after a sample with clearance c >= radius none
    # of the next c - radius can dip below radius, and a sample beyond the plane by d cannot
    # reach the plane within d. Steps are at least _TRACE_STEP, so a tube that passes clears
    # the wall by radius - _TRACE_STEP everywhere.
    ok = True
    for a, b in itertools.pairwise(nodes):
        length = float(np.linalg.norm(b - a))
        t = 0.0
        while ok:
            q = a + (t / length) * (b - a) if length > 0.0 else a
            depth = float((q - e) @ n)
            if depth >= 0.0:
                free = depth
            else:
                free = -bvh.closest_point(q)[0] - radius
                ok = free >= 0.0
            if t >= length:
                break
            t = min(t + max(free, _TRACE_STEP), length)
        if not ok:
            break
    if ok:
        return None
    worst, where = tube_clearance(anatomy, nodes)
    back = float(np.linalg.norm(where - nodes[-1])) * 1e3
    if worst < 0.0:
        return f"its axis runs {-worst * 1e3:.1f} mm outside the wall {back:.0f} mm behind the tip"
    return (f"its axis comes within {worst * 1e3:.1f} mm of the wall {back:.0f} mm behind the "
            f"tip (the tube needs {radius * 1e3:.1f} mm)")


def introducer_path(anatomy: Anatomy, centerline: FloatArray, position: FloatArray,
                    rotation: FloatArray, *, radius: float = INTRODUCER_RADIUS) -> FloatArray:
    """The introducer behind the tip pose ``[rotation | position]``: (K, 3) nodes from its
    proximal end (:data:`INTRODUCER_OVERHANG` beyond the exit plane) towards the tip, the tip
    excluded.

    1. **Straight** (K = 1, ``[tail]``): back along ``-y_A``
       (:func:`cgail_sim.ftl_model.introducer_tail`), when its tube of ``radius``
       lies inside the rest lumen; so the built-in anatomies' starts keep theirs.
    2. Else **along the centerline**: from the proximal end (the exit point moved
       :data:`INTRODUCER_OVERHANG` out along the exit normal) to the centerline's first
       waypoint, then along the waypoints up to the tip's projection on the centerline, when
       that tube lies inside the lumen.

    Args:
        anatomy: the anatomy (rest shape, exit plane).
        centerline: (W, 3) waypoints from the descending aorta (``Centerline.points``).
        position: (3,) tip position, m.
        rotation: (3, 3) tip rotation.
        radius: radius of the tube that must clear the wall, m (the catheter's).

    Raises:
        ScenarioError: neither introducer lies inside the lumen; the message gives both
            reasons ("expected ..., found ...").
    """
    p = np.asarray(position, dtype=np.float64)
    r = np.asarray(rotation, dtype=np.float64)
    tail = introducer_tail(anatomy, p, r)
    straight = _tube_problem(anatomy, np.stack([tail, p]), radius)
    if straight is None:
        return tail[None]
    pts = np.asarray(centerline, dtype=np.float64)
    seg = np.diff(pts, axis=0)
    l2 = np.einsum("ij,ij->i", seg, seg)
    t = np.clip(np.einsum("ij,ij->i", p - pts[:-1], seg) / np.where(l2 > 0.0, l2, 1.0), 0.0, 1.0)
    foot = pts[:-1] + t[:, None] * seg
    j = int(np.argmin(np.linalg.norm(foot - p, axis=1)))
    proximal = np.asarray(anatomy.exit_point, dtype=np.float64) \
        + INTRODUCER_OVERHANG * np.asarray(anatomy.exit_normal, dtype=np.float64)
    nodes = [proximal, *pts[:j + 1]]
    if t[j] > 0.0:
        nodes.append(foot[j])
    # drop nodes that coincide with the tip (a start on a waypoint)
    bent = np.array([q for q in nodes if float(np.linalg.norm(q - p)) > 1e-6])
    along = _tube_problem(anatomy, np.vstack([bent, p[None]]), radius)
    if along is None:
        return bent
    raise ScenarioError(
        f"expected an introducer inside the lumen (a {2 * radius * 1e3:.1f} mm tube from "
        f"{INTRODUCER_OVERHANG * 1e3:.0f} mm beyond the exit plane to the tip), found the "
        f"straight one: {straight}; the one along the centerline: {along}")


#: Radius of the sphere targets are drawn in, m (paper: 30 mm near the coronary ostia).
TARGET_RADIUS = 0.030
#: Smallest wall clearance of a target, m: the tip radius + 1 mm.
TARGET_CLEARANCE = 0.0045
#: Smallest distance between two targets of a fixed set, m.
TARGET_SEPARATION = 0.005

#: Margin of the region an episode (or a planner's rollout) may visit around the anatomy, m.
BOUNDS_MARGIN = 0.01


def episode_bounds(anatomy: Anatomy) -> tuple[FloatArray, FloatArray]:
    """``(low, high)`` corners of the region the tip may visit: the anatomy's bounding box grown
    by :data:`BOUNDS_MARGIN`; beyond it the tip has left through an open end."""
    verts = np.asarray(anatomy.vertices, dtype=np.float64)
    return verts.min(axis=0) - BOUNDS_MARGIN, verts.max(axis=0) + BOUNDS_MARGIN


#: How far the faces of the authors' exit box stand beyond their centreline, m, per axis of our
#: frame (x left, y posterior, z cranial), ``(low, high)``. Their six ``Plane``-tagged objects
#: bound x -133..115, y -573..-287, z -184..55 (scene units = mm,
#: ``shared/design/AUTHORS_SCENE.md``, "Exit"); their ``Assets/centerline.txt`` (read by
#: ``Planner.Start`` as x, z, y) spans x -37.27..21.88, y -511.79..-399.53,
#: z -117.25..-68.37. Their x, y and z are our x, z and y: the descending aorta lies at their
#: larger x and z (left and posterior of the ascending aorta) and the arch at their largest y
#: (cranial), and swapping two axes turns Unity's left-handed frame into our right-handed one.
PAPER_CODE_EXIT_MARGINS = (
    (0.09573, 0.06675, 0.06121),   # right, anterior, caudal of the centreline
    (0.09312, 0.12337, 0.11253),   # left, posterior, cranial
)


def paper_code_exit_box(waypoints: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
    """``(low, high)`` corners of the ``paper_code`` exit box in our frame: the bounding box
    of the centreline ``waypoints`` (every branch) grown by :data:`PAPER_CODE_EXIT_MARGINS`,
    so each face stands as far beyond our centreline as the authors' face beyond theirs
    (``docs/fidelity.md``, "Exit"). Their mesh is not in their repository, so their box cannot
    be carried over by a transform of the mesh; the centreline is what both scenes share."""
    pts = np.concatenate([np.asarray(w, dtype=np.float64) for w in waypoints.values()])
    low, high = np.asarray(PAPER_CODE_EXIT_MARGINS)
    return pts.min(axis=0) - low, pts.max(axis=0) + high


#: How a tip leaves the anatomy (:attr:`cgail_sim.config.EnvConfig.exit_rule`): ``discs``,
#: through the disc of an open cut or out of :func:`episode_bounds`; ``box``, only out of the
#: authors' exit box (:func:`paper_code_exit_box`, the ``paper_code`` option set).
EXIT_RULES = ("discs", "box")


def world_exits(anatomy: Anatomy, waypoints: dict[str, FloatArray],
                exit_rule: str = "discs") -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(exit_discs, low, high)`` of an anatomy under ``exit_rule`` (:data:`EXIT_RULES`): the
    open cuts a tip leaves through (``(D, 7)``, :mod:`cgail_sim.exits`; none under ``box``)
    and the corners of the region it may visit. The one owner of the exit rule, for the
    environment and for the planner's rollouts alike.

    Raises:
        ValueError: an unknown exit rule.
    """
    if exit_rule == "discs":
        low, high = episode_bounds(anatomy)
        return np.asarray(anatomy.exit_discs, dtype=np.float64), low, high
    if exit_rule == "box":
        low, high = paper_code_exit_box(waypoints)
        return np.zeros((0, 7)), low, high
    raise ValueError(f"exit_rule must be one of {EXIT_RULES}, found {exit_rule!r}")


class TargetSampler:
    """The one sampler of targets of an anatomy (module docstring): uniform in the
    ``target_radius`` sphere centred at the midpoint of the two coronary ostia, kept when inside
    the lumen and at least ``target_clearance`` from the wall, attached to the nearest wall
    vertex, ``branch`` the nearer ostium. :func:`build_targets` draws a scenario set's fixed
    targets with it; an env with ``EnvConfig.targets == "sphere"`` draws one per episode.

    Args:
        anatomy: the anatomy (rest shape).
        target_radius: radius of the sphere, m.
        target_clearance: smallest distance of a target from the wall (nearest wall vertex or
            wall-face centroid), m.
    """

    def __init__(self, anatomy: Anatomy, *, target_radius: float = TARGET_RADIUS,
                 target_clearance: float = TARGET_CLEARANCE) -> None:
        self.anatomy = anatomy
        self.target_radius = float(target_radius)
        self.target_clearance = float(target_clearance)
        wall_faces = anatomy.faces[anatomy.wall_face_mask]
        self._wall_vids = np.unique(wall_faces)
        self._verts = np.asarray(anatomy.vertices, dtype=np.float64)
        samples = np.vstack([self._verts[self._wall_vids], self._verts[wall_faces].mean(axis=1)])
        self._wall_tree = cKDTree(samples)
        self._vert_tree = cKDTree(self._verts[self._wall_vids])
        self.centre = 0.5 * (anatomy.ostia["left"] + anatomy.ostia["right"])

    def max_distance(self) -> float:
        """The largest distance between a rest wall vertex and any point of the sphere, m: an
        upper bound of the agent-target distance for every target this sampler can draw (the
        ``d_max`` of per-episode targets)."""
        return float(np.linalg.norm(self._verts - self.centre, axis=1).max()) \
            + self.target_radius

    def sample(self, rng: np.random.Generator, n_targets: int = 1, *,
               min_separation: float = 0.0, max_candidates: int = 20000
               ) -> tuple[TargetConfig, ...]:
        """``n_targets`` targets drawn with ``rng``, each at least ``min_separation`` from the
        ones drawn before it.

        Raises:
            ScenarioError: fewer than ``n_targets`` accepted among ``max_candidates``.
        """
        anatomy, verts = self.anatomy, self._verts
        chosen: list[TargetConfig] = []
        tried = 0
        while len(chosen) < n_targets and tried < max_candidates:
            batch = 256
            tried += batch
            d = rng.normal(size=(batch, 3))
            d /= np.linalg.norm(d, axis=1)[:, None]
            r = self.target_radius * rng.uniform(size=batch) ** (1.0 / 3.0)
            cand = self.centre + d * r[:, None]
            clearance, _ = self._wall_tree.query(cand)
            ok = clearance >= self.target_clearance
            if ok.any():
                ok[ok] = anatomy.contains(cand[ok])
            for p in cand[ok]:
                if any(np.linalg.norm(p - t.position) < min_separation for t in chosen):
                    continue
                _, j = self._vert_tree.query(p)
                vid = int(self._wall_vids[j])
                branch = min(BRANCHES,
                             key=lambda b: float(np.linalg.norm(p - anatomy.ostia[b])))
                chosen.append(TargetConfig(position=p.copy(), vertex=vid,
                                           offset=p - verts[vid], branch=branch))
                if len(chosen) == n_targets:
                    break
        if len(chosen) < n_targets:
            raise ScenarioError(
                f"expected {n_targets} targets inside the lumen within {self.target_radius} m "
                f"of the ostia with {self.target_clearance} m wall clearance, found "
                f"{len(chosen)}")
        return tuple(chosen)


@functools.lru_cache(maxsize=64)
def target_sampler(anatomy: Anatomy, target_radius: float = TARGET_RADIUS) -> TargetSampler:
    """The (cached) :class:`TargetSampler` of ``anatomy``."""
    return TargetSampler(anatomy, target_radius=target_radius)


def build_targets(anatomy: Anatomy, *, n_targets: int = 5, target_radius: float = TARGET_RADIUS,
                  target_clearance: float = TARGET_CLEARANCE,
                  min_separation: float = TARGET_SEPARATION, seed: int = 0,
                  max_candidates: int = 20000) -> tuple[TargetConfig, ...]:
    """Seeded targets near the coronary ostia, inside the lumen (module doc)."""
    sampler = TargetSampler(anatomy, target_radius=target_radius,
                            target_clearance=target_clearance)
    return sampler.sample(np.random.default_rng(seed), n_targets,
                          min_separation=min_separation, max_candidates=max_candidates)


def build_scenarios(anatomy: Anatomy, centerlines: dict[str, Centerline], *, seed: int = 0,
                    n_starts: int = 3, start_span: float = 0.053, n_targets: int = 5,
                    target_radius: float = TARGET_RADIUS) -> ScenarioSet:
    """The scenario set of ``anatomy`` (see the module docstring)."""
    missing = [b for b in BRANCHES if b not in centerlines]
    if missing:
        raise ScenarioError(f"expected centerlines {BRANCHES}, found {sorted(centerlines)}")
    starts = build_starts(anatomy, centerlines["left"], n_starts=n_starts, start_span=start_span)
    sampler = target_sampler(anatomy, target_radius)
    targets = sampler.sample(np.random.default_rng(seed), n_targets,
                             min_separation=TARGET_SEPARATION)
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
    sphere_d_max = target_sampler(anatomy, target_radius).max_distance()
    return ScenarioSet(starts=starts, targets=targets, waypoints=waypoints, d_max=d_max,
                       origin=origin, sphere_d_max=sphere_d_max)

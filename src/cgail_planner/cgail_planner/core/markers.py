"""Marker geometry for RViz2, Foxglove and the guidance page: plain arrays, no rclpy.

Each concept is drawn from the module that owns it; this module only arranges their numbers
into :class:`MarkerGeometry` records (frame ``phantom``, metres), which
:func:`cgail_planner.nodes.conversions.marker_array_msg` turns into a
``visualization_msgs/MarkerArray``:

=================  ==============  ==============================================  ==========
namespace (id)     kind            source                                          node
=================  ==============  ==============================================  ==========
``lumen`` (0)      TRIANGLE_LIST   the wall's current vertices (``StaticWall`` /   phantom
                                   ``DeformableWall.vertices``: deformed in
                                   dynamic mode) on the anatomy's wall faces,
                                   decimated above ``max_triangles``
                                   (:class:`LumenMesh`)
``catheter_body``  LINE_STRIP      the follow-the-leader body                      phantom
(0)                                (``CatheterBatch.body_points``), as wide as
                                   the catheter
``target`` (0)     SPHERE          the planner's goal, as large as its goal        planner
                                   tolerance
``path`` (0)       LINE_STRIP      the planned path                                planner
``next_waypoint``  SPHERE          the guidance's next waypoint                    planner
(0)
``suggested_bend`` LINE_STRIP (0)  the arc the tip follows when it holds the       planner
                   + ARROW (1)     suggested bend while inserting to the waypoint
                                   (:func:`bend_arc`: the catheter model's
                                   ``segment_bend_step`` + ``advance_pose``), and
                                   the heading at its end
=================  ==============  ==============================================  ==========

Every published array is a full snapshot: a DELETEALL first, then one ADD per marker present
(a marker that is gone, e.g. the path after a failed plan, simply is not in the next array).
So a late subscriber of the transient-local topic gets the whole picture from one message.

:func:`index_triangles` is the inverse of a TRIANGLE_LIST: it recovers shared vertices and
faces from the 3-points-per-triangle list (the guidance page draws an indexed mesh).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cgail_sim.ftl_model import (
    advance_pose_steps,
    CatheterBatch,
    CatheterConfig,
    segment_bend_step,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Frame of every marker (the phantom's; REP-103 axes, metres).
FRAME_ID = "phantom"

#: Marker kinds (``visualization_msgs/Marker`` types of the same names).
TRIANGLE_LIST, LINE_STRIP, SPHERE, ARROW = "triangle_list", "line_strip", "sphere", "arrow"
KINDS = (TRIANGLE_LIST, LINE_STRIP, SPHERE, ARROW)

#: Namespaces (each marker has id 0 in its namespace, the bend's arrow id 1).
LUMEN_NS, BODY_NS = "lumen", "catheter_body"
TARGET_NS, PATH_NS, WAYPOINT_NS, BEND_NS = "target", "path", "next_waypoint", "suggested_bend"

#: RGBA colours (0..1).
LUMEN_COLOR = (0.86, 0.42, 0.40, 0.35)
BODY_COLOR = (0.20, 0.55, 1.00, 1.00)
TARGET_COLOR = (1.00, 0.15, 0.15, 0.60)
PATH_COLOR = (0.10, 0.85, 0.30, 1.00)
WAYPOINT_COLOR = (1.00, 0.85, 0.10, 1.00)
BEND_COLOR = (1.00, 0.50, 0.00, 1.00)

Color = tuple[float, float, float, float]
Scale = tuple[float, float, float]


@dataclass(frozen=True)
class MarkerConfig:
    """Sizes and resolutions of the markers."""

    max_triangles: int = 6000
    """Largest triangle count of the lumen marker; a wall with more faces is decimated
    (:func:`decimate_faces`). 6000 triangles are 18000 points, 432 kB of
    ``geometry_msgs/Point``: the built-in anatomies (4783 and 5469 wall faces) go out whole;
    [100, 100000]."""
    body_spacing: float = 0.001
    """Arc-length spacing of the catheter body's line strip, m; [1e-4, 0.01]."""
    line_width: float = 0.001
    """Width of the path and of the suggested-bend arc, m; (0, 0.01]."""
    waypoint_diameter: float = 0.003
    """Diameter of the next-waypoint sphere, m; (0, 0.05]."""
    bend_steps: int = 20
    """Points of the suggested-bend arc beyond the tip; [2, 500]."""

    def __post_init__(self) -> None:
        for name, low, high in (("max_triangles", 100, 100_000), ("bend_steps", 2, 500)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) \
                    or not low <= value <= high:
                raise ValueError(f"{name} must be an int in [{low}, {high}], found {value!r}")
        for field, lo, hi, closed in (("body_spacing", 1e-4, 0.01, True),
                                      ("line_width", 0.0, 0.01, False),
                                      ("waypoint_diameter", 0.0, 0.05, False)):
            _check_length(field, getattr(self, field), lo, hi, closed)


def _check_length(name: str, value: Any, low: float, high: float, closed_low: bool) -> float:
    ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
          and math.isfinite(value) and (value >= low if closed_low else value > low)
          and value <= high)
    if not ok:
        raise ValueError(f"{name} must be in {'[' if closed_low else '('}{low}, {high}], "
                         f"found {value!r}")
    return float(value)


_POINT_COUNTS = {SPHERE: (1, 1), ARROW: (2, 2), LINE_STRIP: (2, None), TRIANGLE_LIST: (3, None)}


@dataclass(frozen=True)
class MarkerGeometry:
    """One marker as plain data (frame :data:`FRAME_ID`, metres).

    ``points`` by kind: SPHERE its centre (1, 3); ARROW tail and head (2, 3); LINE_STRIP the
    vertices in order (N >= 2, 3); TRIANGLE_LIST three points per triangle (3M, 3).
    ``scale`` as ``visualization_msgs/Marker`` reads it: SPHERE the diameters; LINE_STRIP
    ``(width, 0, 0)``; ARROW ``(shaft diameter, head diameter, head length)``; TRIANGLE_LIST
    ``(1, 1, 1)`` (a scale factor of the points).
    """

    ns: str
    """Namespace (one per concept, module docstring)."""
    id: int
    """Id within the namespace (stable: 0, the bend's arrow 1)."""
    kind: str
    """One of :data:`KINDS`."""
    points: FloatArray
    """(N, 3) points, m (above)."""
    scale: Scale
    """Sizes, m (above)."""
    color: Color
    """RGBA, 0..1."""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, found {self.kind!r}")
        p = np.asarray(self.points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
            raise ValueError(f"points must be finite (N, 3), found shape {p.shape}")
        low, high = _POINT_COUNTS[self.kind]
        if len(p) < low or (high is not None and len(p) > high) \
                or (self.kind == TRIANGLE_LIST and len(p) % 3):
            raise ValueError(f"a {self.kind} marker needs {low}"
                             f"{'' if high == low else ' or more'} points"
                             f"{' (3 per triangle)' if self.kind == TRIANGLE_LIST else ''}, "
                             f"found {len(p)}")
        object.__setattr__(self, "points", p)


# ------------------------------------------------------------------------------ lumen
def decimate_faces(vertices: FloatArray, faces: IntArray, max_triangles: int) -> IntArray:
    """At most about ``max_triangles`` faces of a coarser mesh on a subset of ``vertices``.

    Quadric edge collapses (fast-simplification, as ``prepare_anatomy`` decimates), replayed
    as half-edge collapses: each removed vertex maps onto the vertex it collapsed into, so the
    coarse faces index the *original* vertices and a deformed wall (same vertex order) is drawn
    by indexing its current vertices with them. Deterministic for a given mesh.

    Args:
        vertices: (N, 3) vertex positions, m (the rest shape).
        faces: (M, 3) triangles.
        max_triangles: the face budget.

    Returns:
        (K, 3) faces, ``K <= M``, no degenerate ones (``faces`` itself, copied, when
        ``M <= max_triangles``).
    """
    f = np.asarray(faces, dtype=np.int64)
    if len(f) <= max_triangles:
        return f.copy()
    import fast_simplification

    v = np.array(vertices, dtype=np.float64)  # (a writeable, contiguous copy)
    _, _, collapses = fast_simplification.simplify(v, np.array(f), target_count=max_triangles,
                                                   return_collapses=True)
    # (keep, gone) pairs of original indices, in order; a removed vertex never comes back, so
    # walking them backwards gives each removed vertex the survivor it ends up in
    final = np.arange(len(v), dtype=np.int64)
    for keep, gone in np.asarray(collapses, dtype=np.int64)[::-1].tolist():
        final[gone] = final[keep]
    out = final[f]
    ok = (out[:, 0] != out[:, 1]) & (out[:, 1] != out[:, 2]) & (out[:, 0] != out[:, 2])
    return np.ascontiguousarray(out[ok])


class LumenMesh:
    """The triangles the lumen marker draws: the anatomy's wall faces (caps are open, as for
    the ray casts), decimated above ``max_triangles``. Built once; :meth:`marker` then takes
    the wall's current vertices (rest, or deformed in dynamic mode).

    Args:
        anatomy: the vessel (``vertices``, ``faces``, ``wall_face_mask``).
        max_triangles: face budget (:attr:`MarkerConfig.max_triangles`).
    """

    def __init__(self, anatomy: Any, max_triangles: int = MarkerConfig().max_triangles) -> None:
        wall_faces = np.asarray(anatomy.faces)[np.asarray(anatomy.wall_face_mask, dtype=bool)]
        self.n_vertices = len(anatomy.vertices)
        self.faces: IntArray = decimate_faces(anatomy.vertices, wall_faces, max_triangles)
        """(K, 3) faces into the wall's vertices."""
        self.decimated = len(self.faces) < len(wall_faces)
        """True when the wall had more than ``max_triangles`` faces."""
        self._index = self.faces.reshape(-1)

    def marker(self, vertices: FloatArray, color: Color = LUMEN_COLOR) -> MarkerGeometry:
        """The lumen TRIANGLE_LIST on ``vertices`` (N, 3), the wall's current positions."""
        v = np.asarray(vertices, dtype=np.float64)
        if v.shape != (self.n_vertices, 3):
            raise ValueError(f"vertices must have shape ({self.n_vertices}, 3), found "
                             f"{v.shape}")
        return MarkerGeometry(LUMEN_NS, 0, TRIANGLE_LIST, v[self._index], (1.0, 1.0, 1.0), color)


def index_triangles(points: FloatArray) -> tuple[FloatArray, IntArray, IntArray]:
    """Shared vertices and faces of a triangle list (the inverse of a TRIANGLE_LIST marker).

    Points that are exactly equal are one vertex (a marker built from a mesh repeats each
    vertex's coordinates bit for bit).

    Args:
        points: (3M, 3) three points per triangle.

    Returns:
        ``(vertices (V, 3), faces (M, 3), first (V,))``: ``first[k]`` is the index in
        ``points`` where vertex ``k`` first appears, so a later list of the same topology
        gives its vertices as ``points[first]``.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) % 3:
        raise ValueError(f"points must hold 3 per triangle, found {len(p)}")
    _, first, inverse = np.unique(p, axis=0, return_index=True, return_inverse=True)
    # number the vertices in order of first appearance (stable, not by coordinates)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    first = first[order]
    return p[first].copy(), rank[inverse.reshape(-1)].reshape(-1, 3), first


# ------------------------------------------------------------------------------ catheter
def body_marker(catheter: CatheterBatch, index: int = 0,
                spacing: float = MarkerConfig().body_spacing,
                color: Color = BODY_COLOR) -> MarkerGeometry | None:
    """The body of catheter ``index`` as a LINE_STRIP as wide as the catheter (its
    ``outer_diameter``), proximal end first; None when it has fewer than 2 points."""
    points = catheter.body_points(index, spacing)
    if len(points) < 2:
        return None
    width = float(catheter.config.outer_diameter)
    return MarkerGeometry(BODY_NS, 0, LINE_STRIP, points, (width, 0.0, 0.0), color)


def bend_arc(position: FloatArray, rotation: FloatArray, bend: tuple[float, float],
             length: float, catheter: CatheterConfig, steps: int
             ) -> tuple[FloatArray, FloatArray]:
    """Where the tip goes when it holds ``bend`` while inserting ``length``.

    The catheter model's segment bend (:func:`~cgail_sim.ftl_model.segment_bend_step`:
    per inserted ``dl`` the heading turns by ``bend * dl / L``) stepped with
    :func:`~cgail_sim.ftl_model.advance_pose` (:func:`~cgail_sim.ftl_model.advance_pose_steps`).

    Returns:
        ``(points (steps + 1, 3), rotation (3, 3))``: the arc from the tip, and the tip
        rotation at its end.
    """
    dl = float(length) / steps
    alpha, gamma = segment_bend_step(bend, dl, catheter.theta_max, catheter.segment_length)
    return advance_pose_steps(np.asarray(position, dtype=np.float64),
                              np.asarray(rotation, dtype=np.float64), alpha, gamma, dl, steps)


def bend_markers(position: FloatArray, rotation: FloatArray, bend: tuple[float, float],
                 length: float, catheter: CatheterConfig, config: MarkerConfig,
                 color: Color = BEND_COLOR) -> list[MarkerGeometry]:
    """The suggested bend: its arc over ``length`` (LINE_STRIP, id 0) and an arrow along the
    heading at the arc's end (ARROW, id 1; a fifth of the arc, at least 5 mm)."""
    length = max(float(length), 1e-3)
    arc, r_end = bend_arc(position, rotation, bend, length, catheter, config.bend_steps)
    w = config.line_width
    head = max(0.2 * length, 0.005)
    arrow = np.stack([arc[-1], arc[-1] + head * r_end[:, 1]])
    return [MarkerGeometry(BEND_NS, 0, LINE_STRIP, arc, (w, 0.0, 0.0), color),
            MarkerGeometry(BEND_NS, 1, ARROW, arrow, (w, 3.0 * w, 0.3 * head), color)]


# ------------------------------------------------------------------------------ planner
def target_marker(position: FloatArray, radius: float,
                  color: Color = TARGET_COLOR) -> MarkerGeometry:
    """The target as a SPHERE of ``radius`` (e.g. the goal tolerance)."""
    d = 2.0 * _check_length("radius", radius, 0.0, 1.0, False)
    return MarkerGeometry(TARGET_NS, 0, SPHERE, np.reshape(position, (1, 3)), (d, d, d), color)


def path_marker(points: FloatArray, width: float,
                color: Color = PATH_COLOR) -> MarkerGeometry | None:
    """The planned path as a LINE_STRIP; None for fewer than 2 points."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2:
        return None
    return MarkerGeometry(PATH_NS, 0, LINE_STRIP, p, (width, 0.0, 0.0), color)


def waypoint_marker(point: FloatArray, diameter: float,
                    color: Color = WAYPOINT_COLOR) -> MarkerGeometry:
    """The next waypoint as a small SPHERE."""
    return MarkerGeometry(WAYPOINT_NS, 0, SPHERE, np.reshape(point, (1, 3)),
                          (diameter, diameter, diameter), color)


@dataclass(frozen=True)
class TipGuidance:
    """What the planner last told the operator, for the markers."""

    position: FloatArray
    """(3,) tip position the guidance was computed for, m."""
    rotation: FloatArray
    """(3, 3) tip rotation."""
    next_waypoint: FloatArray
    """(3,) next waypoint, m."""
    bend: tuple[float, float]
    """Suggested ``(alpha, gamma)``, rad."""
    distance_to_waypoint: float
    """Straight distance from the tip to the waypoint, m: the length of the drawn arc."""


def planner_markers(config: MarkerConfig, catheter: CatheterConfig, *,
                    goal: FloatArray | None, goal_radius: float,
                    path: FloatArray | None, guidance: TipGuidance | None
                    ) -> list[MarkerGeometry]:
    """The planner's markers (module docstring) for what it has: a goal, a path, guidance."""
    out: list[MarkerGeometry | None] = []
    if goal is not None:
        out.append(target_marker(goal, goal_radius))
    if path is not None:
        out.append(path_marker(path, config.line_width))
    if guidance is not None:
        out.append(waypoint_marker(guidance.next_waypoint, config.waypoint_diameter))
        out += bend_markers(guidance.position, guidance.rotation, guidance.bend,
                            guidance.distance_to_waypoint, catheter, config)
    return [m for m in out if m is not None]


def phantom_markers(lumen: LumenMesh, wall_vertices: FloatArray,
                    catheter: CatheterBatch | None,
                    config: MarkerConfig) -> list[MarkerGeometry]:
    """The phantom's markers: the lumen on the wall's current vertices and the catheter
    body (catheter 0 of ``catheter``; None: no body)."""
    out = [lumen.marker(wall_vertices)]
    body = body_marker(catheter, 0, config.body_spacing) if catheter is not None else None
    return out if body is None else [*out, body]


def namespaces(markers: Sequence[MarkerGeometry]) -> list[tuple[str, int, str]]:
    """``(ns, id, kind)`` of each marker, in order (for logs and tests)."""
    return [(m.ns, m.id, m.kind) for m in markers]

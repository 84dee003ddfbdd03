"""Anatomy descriptors: shape figures measured the same way on any aorta, real or sampled.

:func:`anatomy_descriptors` measures an :class:`~cgail_sim.anatomy.Anatomy` (a prepared
patient lumen or a population sample) from its wall and landmarks only, never from the
generator's parameters, so that a real case and a population sample are measured by the same
method with the same biases. Pure numpy/scipy: no rclpy, no torch.

Frame and centreline
--------------------
The ``phantom`` frame (LPS axes, +z cranial, the annulus centre at the origin; every
anatomy is in it). The **trunk centreline** runs from the annulus centre to the descending
start (the medial graph's source, 20 mm of centreline above the descending cut in every
anatomy the generator and ``prepare_anatomy`` make): the Voronoi medial path of
:func:`cgail_sim.centerline.medial_paths` from the start to the point one annulus radius
above the annulus centre along the root axis (the centre of the largest sphere that touches
the valve plane), then straight down the root axis to the annulus centre. ``s`` is the arc
length from the annulus centre (m). Points every ``DescriptorConfig.spacing``.

Segments
--------
* **apex**: the most cranial trunk point (largest z).
* **arch level**: the horizontal plane ``DescriptorConfig.arch_depth`` (40 mm) below the apex.
  (A fixed depth, not a landmark's level: the real cases' annulus lies up to 33 mm off along
  the root axis without a left-ventricle label, and some of their descending aortas are cut
  less than 50 mm below the apex, above the annulus level.)
* **arch start** / **arch end**: where the trunk crosses the arch level last before and first
  after the apex (linearly interpolated).
* **ascending**: the trunk from the annulus centre (s = 0) to the arch start: root and
  ascending aorta.
* **arch**: from the arch start to the arch end, over the apex.
* **descending**: from the arch end to the descending start.

When the trunk does not reach the arch level on one side, the arch start or end, and every
descriptor that needs it, is NaN.

Descriptors (the fields of :class:`AnatomyDescriptors`, SI units)
------------------------------------------------------------------
* ``root_tilt`` (rad): angle between the root axis (``Anatomy.root_axis``, the valve-plane
  normal into the aorta) and the cranial axis +z: the clinical "aortic angle" of the annulus
  plane against the horizontal.
* ``arch_width`` (m): distance between the arch start and the arch end (both at the arch
  level, so a horizontal distance, in the vertical plane through them: the arch plane of a
  planar arch). ``arch_height`` (m): height of the apex above the annulus centre along +z.
* ``<segment>_length`` (m): arc length of the segment.
* ``<segment>_tortuosity`` (-): tortuosity index, arc length / chord - 1 (chord: the distance
  between the segment's ends); 0 for a straight segment, pi/2 - 1 = 0.571 for a half circle.
* ``<segment>_curvature_mean`` / ``_max`` (1/m): mean and largest of the centreline's
  curvature over the segment's points, each the inverse circumradius of the trunk points
  ``DescriptorConfig.curvature_window`` of arc length before and after it
  (:func:`cgail_sim.validate.bend_radii`, 1/R for a circular arc of radius R, 0 where
  straight), measured along the whole medial path (so that a segment's ends see their
  neighbours; not across its corner with the straight piece down to the annulus centre); the
  first and last window of the medial path have no curvature.
* ``<segment>_radius_p10`` / ``_p50`` / ``_p90`` (m): 10th, 50th and 90th percentiles of the
  lumen's inscribed-sphere radius (distance to the nearest wall sample) at the segment's
  medial points (the straight piece down to the annulus centre, which touches the valve
  plane, is left out).
* ``branch_count``: the supra-aortic branches, the caps other than the descending cut and the
  coronary stubs (a cap within ``DescriptorConfig.coronary_gap`` of an ostium).
* ``branch_positions`` (m): for each branch, in order along the trunk (a standard arch:
  brachiocephalic trunk, left common carotid, left subclavian), the take-off position: the arc
  length ``s`` of the trunk point nearest the branch's **mouth** (its ostium on the aorta, as
  a clinician projects it onto the aortic centreline). The branch centreline is the medial
  path from the descending start to just inside the branch's cap; its mouth is where, walking
  in from the cap, it first comes within the trunk's inscribed radius of the trunk centreline
  (the aortic wall). A branch leaving at an angle theta to the trunk from the centreline point
  s0 has its mouth about r cot(theta) downstream of s0 (r: the trunk's radius).
* ``branch_angles`` (rad): for each branch, the angle between the **branch axis** (the chord of
  its centreline from ``branch_probe_from`` = 5 mm to ``branch_probe_to`` = 15 mm beyond the
  mouth, past the corner the path cuts into the branch, pointing out of the aorta) and the
  trunk's downstream tangent at the take-off (towards the descending aorta, the direction of
  blood flow; the chord over +- ``curvature_window``): 90 deg for a branch at right angles to
  the trunk, under 90 deg for one leaning downstream, over 90 deg for one leaning back towards
  the root.

:data:`DESCRIPTORS` lists them flat (``branch1_position`` ... ``branch3_angle``) with the
label and display unit the reports use; :meth:`AnatomyDescriptors.values` gives them as a flat
dict in SI units (NaN where not measurable).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np

from cgail_sim.anatomy import Anatomy, AnatomyError
from cgail_sim.centerline import medial_paths
from cgail_sim.validate import bend_radii

__all__ = [
    "DESCRIPTORS",
    "AnatomyDescriptors",
    "ArchLimits",
    "Descriptor",
    "DescriptorConfig",
    "SegmentShape",
    "Trunk",
    "anatomy_descriptors",
    "arch_limits",
    "branch_takeoff",
    "root_tilt",
    "segment_shape",
    "trunk_and_branches",
    "trunk_curvature",
]

_Z = np.array([0.0, 0.0, 1.0])
_MAX_BRANCHES = 3


@dataclass(frozen=True)
class DescriptorConfig:
    """How the descriptors are measured (module docstring). Lengths in m."""

    arch_depth: float = 0.040
    """Depth of the arch level below the apex (40 mm: within the 48 mm that the shortest real
    descending aorta, D2's, reaches below its apex). In [10, 100] mm."""
    spacing: float = 0.001
    """Distance between the trunk and branch centreline points (1 mm). In [0.2, 5] mm."""
    curvature_window: float = 0.010
    """Arc length before and after a point over which its curvature (circumradius) and the
    trunk tangent are measured (10 mm: the scale of a catheter bend, well above the
    centreline's 3 mm smoothing). In [2, 30] mm."""
    branch_probe_from: float = 0.005
    """A branch's axis is the chord of its centreline from this far beyond its mouth on the
    trunk (5 mm: past the corner the path cuts into the branch) ... In [0, 20] mm."""
    branch_probe_to: float = 0.015
    """... to this far (15 mm). In [branch_probe_from + 3 mm, 40 mm]."""
    coronary_gap: float = 0.020
    """A cap whose centre lies within this distance of a coronary ostium is a coronary stub,
    not a supra-aortic branch (20 mm). In [5, 50] mm."""

    def __post_init__(self) -> None:
        ranges = {"arch_depth": (0.010, 0.100),
                  "spacing": (0.0002, 0.005), "curvature_window": (0.002, 0.030),
                  "branch_probe_from": (0.0, 0.020),
                  "branch_probe_to": (self.branch_probe_from + 0.003, 0.040),
                  "coronary_gap": (0.005, 0.050)}
        for name, (lo, hi) in ranges.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not lo <= value <= hi:
                raise ValueError(f"{name} must be in [{lo:g}, {hi:g}] m, found {value!r}")


class Descriptor(NamedTuple):
    """One flat descriptor as the reports show it."""

    key: str
    """Key in :meth:`AnatomyDescriptors.values`."""
    label: str
    """Readable name."""
    unit: str
    """Display unit."""
    scale: float
    """Display value = SI value * scale."""


_DEG = 180.0 / math.pi
_SEGMENTS = ("ascending", "arch", "descending")
DESCRIPTORS: tuple[Descriptor, ...] = (
    Descriptor("root_tilt", "root tilt (root axis from cranial)", "deg", _DEG),
    Descriptor("arch_width", "arch width (40 mm below the apex)", "mm", 1e3),
    Descriptor("arch_height", "arch height (apex above the annulus)", "mm", 1e3),
    *(d for seg in _SEGMENTS for d in (
        Descriptor(f"{seg}_length", f"{seg} centreline length", "mm", 1e3),
        Descriptor(f"{seg}_tortuosity", f"{seg} tortuosity index", "-", 1.0),
        Descriptor(f"{seg}_curvature_mean", f"{seg} mean curvature", "1/m", 1.0),
        Descriptor(f"{seg}_curvature_max", f"{seg} max curvature", "1/m", 1.0))),
    *(Descriptor(f"{seg}_radius_{p}", f"{seg} lumen radius, {name}", "mm", 1e3)
      for seg in _SEGMENTS
      for p, name in (("p10", "10th percentile"), ("p50", "median"),
                      ("p90", "90th percentile"))),
    Descriptor("branch_count", "supra-aortic branches", "-", 1.0),
    *(Descriptor(f"branch{k}_position", f"branch {k} ({name}) take-off from the annulus", "mm",
                 1e3) for k, name in ((1, "BCT"), (2, "LCCA"), (3, "LSA"))),
    *(Descriptor(f"branch{k}_angle", f"branch {k} ({name}) angle to the trunk tangent", "deg",
                 _DEG) for k, name in ((1, "BCT"), (2, "LCCA"), (3, "LSA"))),
)
"""Every flat descriptor, in report order (the arch width's label names the default depth)."""


class SegmentShape(NamedTuple):
    """Shape of one centreline segment (SI units, NaN where not measurable)."""

    length: float
    """Arc length, m."""
    tortuosity: float
    """Arc length / chord - 1."""
    curvature_mean: float
    """Mean curvature over the segment's points, 1/m."""
    curvature_max: float
    """Largest curvature over the segment's points, 1/m."""
    radius_p10: float
    """10th percentile of the inscribed radius, m."""
    radius_p50: float
    """Median inscribed radius, m."""
    radius_p90: float
    """90th percentile of the inscribed radius, m."""


@dataclass(frozen=True)
class Trunk:
    """The trunk centreline from the annulus centre to the descending start."""

    points: np.ndarray
    """(P, 3) m, ``points[0]`` the annulus centre."""
    radii: np.ndarray
    """(P,) inscribed radius, m; NaN on the straight piece down to the annulus centre."""

    @property
    def arc(self) -> np.ndarray:
        """(P,) arc length from the annulus centre, m."""
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(seg)])


@dataclass(frozen=True)
class AnatomyDescriptors:
    """The descriptors of one anatomy (module docstring; SI units, NaN where not
    measurable)."""

    root_tilt: float
    """Angle of the root axis from cranial, rad."""
    arch_width: float
    """Arch start to arch end, at the arch level, m."""
    arch_height: float
    """Apex above the annulus centre, m."""
    ascending: SegmentShape
    """Shape of the root and ascending aorta (annulus centre to arch start)."""
    arch: SegmentShape
    """Shape of the arch (arch start to arch end)."""
    descending: SegmentShape
    """Shape of the descending aorta (arch end to descending start)."""
    branch_positions: tuple[float, ...]
    """Take-off arc length of each supra-aortic branch from the annulus, in order, m."""
    branch_angles: tuple[float, ...]
    """Angle of each branch to the trunk's downstream tangent at its take-off, rad."""

    @property
    def branch_count(self) -> int:
        """Number of supra-aortic branches."""
        return len(self.branch_positions)

    def values(self) -> dict[str, float]:
        """Every flat descriptor of :data:`DESCRIPTORS`, in SI units (NaN where missing)."""
        out: dict[str, float] = {"root_tilt": self.root_tilt, "arch_width": self.arch_width,
                                 "arch_height": self.arch_height}
        for seg in _SEGMENTS:
            shape: SegmentShape = getattr(self, seg)
            for f in SegmentShape._fields:
                out[f"{seg}_{f}"] = float(getattr(shape, f))
        out["branch_count"] = float(self.branch_count)
        for k in range(_MAX_BRANCHES):
            out[f"branch{k + 1}_position"] = (self.branch_positions[k]
                                              if k < self.branch_count else math.nan)
            out[f"branch{k + 1}_angle"] = (self.branch_angles[k]
                                           if k < self.branch_count else math.nan)
        return {d.key: out[d.key] for d in DESCRIPTORS}


# ------------------------------------------------------------------------------------------
# Pure geometry (numpy in, numpy out)
# ------------------------------------------------------------------------------------------
def root_tilt(root_axis: np.ndarray) -> float:
    """Angle between a root axis and the cranial axis +z, rad, in [0, pi]."""
    axis = np.asarray(root_axis, dtype=float)
    norm = float(np.linalg.norm(axis))
    if axis.shape != (3,) or not norm > 0.0:
        raise ValueError(f"root_axis must be a non-zero 3-vector, found {axis!r}")
    return float(math.acos(float(np.clip(axis @ _Z / norm, -1.0, 1.0))))


def trunk_curvature(points: np.ndarray, window: float) -> tuple[np.ndarray, np.ndarray]:
    """``(s, curvature)``: the curvature (1/m) at each polyline point at least ``window`` of
    arc length from both ends, the inverse circumradius of the points ``window`` before and
    after it (:func:`cgail_sim.validate.bend_radii`; 0 where straight)."""
    s, bend = bend_radii(np.asarray(points, dtype=float), half=window)
    return s, np.where(np.isfinite(bend), 1.0 / bend, 0.0)


def _at(points: np.ndarray, arc: np.ndarray, s: float) -> np.ndarray:
    return np.array([np.interp(s, arc, points[:, k]) for k in range(3)])


def segment_shape(points: np.ndarray, radii: np.ndarray, s_from: float, s_to: float,
                  window: float, *, curved_from: int = 0) -> SegmentShape:
    """Shape of the piece ``[s_from, s_to]`` (arc length from ``points[0]``, m) of a polyline.

    Args:
        points: (P, 3) the whole centreline, m (the curvature sees beyond the piece's ends).
        radii: (P,) inscribed radius at each point, m (NaN: left out of the percentiles).
        s_from, s_to: the piece, m.
        window: curvature half-window, m (:func:`trunk_curvature`).
        curved_from: the curvature is measured on ``points[curved_from:]`` only (the trunk:
            1, not across the corner between the straight piece down to the annulus centre
            and the medial path).

    Returns:
        The piece's :class:`SegmentShape` (NaN fields where the piece is empty, has no
        curvature point or no radius).
    """
    pts = np.asarray(points, dtype=float)
    rad = np.asarray(radii, dtype=float)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    nan = math.nan
    if not (math.isfinite(s_from) and math.isfinite(s_to)) or s_to <= s_from:
        return SegmentShape(nan, nan, nan, nan, nan, nan, nan)
    length = s_to - s_from
    chord = float(np.linalg.norm(_at(pts, arc, s_to) - _at(pts, arc, s_from)))
    tortuosity = length / chord - 1.0 if chord > 0.0 else math.inf
    s_k, kappa = trunk_curvature(pts[curved_from:], window)
    s_k = s_k + arc[curved_from]
    k_in = kappa[(s_k >= s_from) & (s_k <= s_to)]
    r_in = rad[(arc >= s_from) & (arc <= s_to) & np.isfinite(rad)]
    p10, p50, p90 = (np.percentile(r_in, [10, 50, 90]) if len(r_in) else (nan, nan, nan))
    return SegmentShape(
        length=float(length), tortuosity=float(tortuosity),
        curvature_mean=float(k_in.mean()) if len(k_in) else nan,
        curvature_max=float(k_in.max()) if len(k_in) else nan,
        radius_p10=float(p10), radius_p50=float(p50), radius_p90=float(p90))


class ArchLimits(NamedTuple):
    """Where the arch of a trunk lies and how large it is (module docstring), m."""

    s_apex: float
    """Arc length of the apex (the most cranial point)."""
    s_start: float
    """Arc length of the arch start (NaN when the ascending side never reaches the level)."""
    s_end: float
    """Arc length of the arch end (NaN when the descending side never reaches the level)."""
    width: float
    """Distance from the arch start to the arch end (NaN without both)."""
    height: float
    """Height of the apex above the annulus centre."""


def arch_limits(points: np.ndarray, depth: float) -> ArchLimits:
    """The arch of a trunk from the annulus centre (``points[0]``; +z cranial): its apex, the
    last point before and the first point after it at ``depth`` below the apex (linearly
    interpolated), the width between them, and the apex height above ``points[0]``."""
    pts = np.asarray(points, dtype=float)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    i_apex = int(np.argmax(pts[:, 2]))
    h = pts[:, 2] - (pts[i_apex, 2] - depth)       # > 0 above the arch level

    def crossing(i: int, j: int) -> float:
        """Arc length where the level is crossed between points i (above) and j (at or
        below)."""
        t = h[i] / (h[i] - h[j])
        return float(arc[i] + t * (arc[j] - arc[i]))

    before = np.flatnonzero(h[:i_apex] <= 0.0)
    after = np.flatnonzero(h[i_apex:] <= 0.0)
    s_start = crossing(int(before[-1]) + 1, int(before[-1])) if len(before) else math.nan
    s_end = crossing(i_apex + int(after[0]) - 1, i_apex + int(after[0])) if len(after) \
        else math.nan
    width = (float(np.linalg.norm(_at(pts, arc, s_end) - _at(pts, arc, s_start)))
             if math.isfinite(s_start) and math.isfinite(s_end) else math.nan)
    return ArchLimits(float(arc[i_apex]), s_start, s_end, width,
                      float(pts[i_apex, 2] - pts[0, 2]))


def branch_takeoff(trunk: Trunk, branch: np.ndarray, *, probe: tuple[float, float],
                   window: float) -> tuple[float, float]:
    """``(position, angle)`` of one branch (module docstring): the arc length on the trunk of
    the branch's mouth (m) and the angle between the branch axis and the trunk's downstream
    tangent there (rad).

    Args:
        trunk: the trunk centreline (annulus centre first).
        branch: (B, 3) the branch's centreline from the descending start (up the trunk, then
            out into the branch) to its cap, m.
        probe: ``(from, to)``: the branch axis is the chord of the branch centreline between
            these lengths beyond its mouth, m (shortened to the branch's length beyond the
            mouth, from at most a third of it).
        window: half-length of the chord that gives the trunk tangent, m.

    Raises:
        AnatomyError: the branch centreline never enters the trunk, or ends inside it.
    """
    pts = np.asarray(branch, dtype=float)
    good = np.isfinite(trunk.radii)
    tp, tr, arc = trunk.points[good], trunk.radii[good], trunk.arc[good]
    d = np.linalg.norm(pts[:, None, :] - tp[None, :, :], axis=2)
    nearest = np.argmin(d, axis=1)
    inside = d[np.arange(len(pts)), nearest] < tr[nearest]
    if inside[-1] or not inside.any():
        raise AnatomyError("expected a branch centreline that leaves the trunk, found one "
                           + ("ending inside it" if inside[-1] else "never inside it"))
    j = int(np.flatnonzero(inside)[-1])     # the mouth: walking in from the cap, the
    #                                         first point inside the trunk
    beyond = pts[j:]
    s_b = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(beyond, axis=0), axis=1))])
    hi = min(probe[1], float(s_b[-1]))
    lo = min(probe[0], hi / 3.0)
    p0, p1 = _at(beyond, s_b, lo), _at(beyond, s_b, hi)
    axis = (p1 - p0) / float(np.linalg.norm(p1 - p0))
    s0 = float(arc[nearest[j]])
    full_arc = trunk.arc
    tangent = (_at(trunk.points, full_arc, min(s0 + window, float(full_arc[-1])))
               - _at(trunk.points, full_arc, max(s0 - window, 0.0)))
    cos = float(axis @ tangent / float(np.linalg.norm(tangent)))
    return s0, float(math.acos(float(np.clip(cos, -1.0, 1.0))))


# ------------------------------------------------------------------------------------------
# An anatomy
# ------------------------------------------------------------------------------------------
def _branch_caps(anatomy: Anatomy, coronary_gap: float) -> list[np.ndarray]:
    """Centre and outward normal (6,) of each supra-aortic branch cap."""
    caps = []
    ostia = np.array([anatomy.ostia[k] for k in sorted(anatomy.ostia)])
    for disc in anatomy.exit_discs[1:]:
        centre = disc[:3]
        if len(ostia) and float(np.linalg.norm(ostia - centre, axis=1).min()) < coronary_gap:
            continue
        caps.append(disc[:6])
    return caps


def _annulus_radius(anatomy: Anatomy) -> float:
    """Largest in-plane distance of the annulus vertices from the annulus centre, m."""
    rel = anatomy.vertices[anatomy.annulus_vertices] - anatomy.annulus_center
    axis = anatomy.root_axis / float(np.linalg.norm(anatomy.root_axis))
    in_plane = rel - np.outer(rel @ axis, axis)
    return float(np.linalg.norm(in_plane, axis=1).max())


def trunk_and_branches(anatomy: Anatomy, config: DescriptorConfig | None = None
                       ) -> tuple[Trunk, list[np.ndarray]]:
    """The trunk centreline (annulus centre first) and each supra-aortic branch's centreline
    (descending start to just inside its cap), as the module docstring defines them."""
    cfg = config or DescriptorConfig()
    axis = anatomy.root_axis / float(np.linalg.norm(anatomy.root_axis))
    goals: dict[str, np.ndarray] = {
        "trunk": anatomy.annulus_center + _annulus_radius(anatomy) * axis}
    for k, cap in enumerate(_branch_caps(anatomy, cfg.coronary_gap)):
        goals[f"branch{k}"] = cap[:3] - 0.002 * cap[3:6]
    lines = medial_paths(anatomy, goals, spacing=cfg.spacing)
    trunk_line = lines.pop("trunk")
    trunk = Trunk(points=np.vstack([anatomy.annulus_center[None], trunk_line.points[::-1]]),
                  radii=np.concatenate([[math.nan], trunk_line.radii[::-1]]))
    return trunk, [lines[f"branch{k}"].points for k in range(len(lines))]


def anatomy_descriptors(anatomy: Anatomy,
                        config: DescriptorConfig | None = None) -> AnatomyDescriptors:
    """Measure every descriptor of an anatomy (module docstring).

    Args:
        anatomy: a built-in, population or prepared patient anatomy.
        config: how to measure (default :class:`DescriptorConfig`).

    Returns:
        The descriptors, SI units; NaN where one cannot be measured (e.g. no arch end).

    Raises:
        CenterlineError: the annulus or a branch cap cannot be reached through the lumen.
        AnatomyError: a branch centreline that never leaves the trunk.
    """
    cfg = config or DescriptorConfig()
    trunk, branches = trunk_and_branches(anatomy, cfg)
    pts, arc = trunk.points, trunk.arc
    limits = arch_limits(pts, cfg.arch_depth)
    def shape(s_from: float, s_to: float) -> SegmentShape:
        return segment_shape(pts, trunk.radii, s_from, s_to, cfg.curvature_window,
                             curved_from=1)

    ascending = shape(0.0, limits.s_start)
    arch = shape(limits.s_start, limits.s_end)
    descending = shape(limits.s_end, float(arc[-1]))
    takeoffs = sorted(branch_takeoff(trunk, b, probe=(cfg.branch_probe_from,
                                                      cfg.branch_probe_to),
                                     window=cfg.curvature_window)
                      for b in branches)
    return AnatomyDescriptors(
        root_tilt=root_tilt(anatomy.root_axis), arch_width=limits.width,
        arch_height=limits.height,
        ascending=ascending, arch=arch, descending=descending,
        branch_positions=tuple(p for p, _ in takeoffs),
        branch_angles=tuple(a for _, a in takeoffs))


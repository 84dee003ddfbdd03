"""The ``prepare_anatomy`` pipeline: a lumen volume in, a simulator :class:`Anatomy` out.

All steps run without a manual step, in patient LPS millimetres, and end in the ``phantom``
frame (LPS axes, annulus centre at the origin, metres):

1. **Lumen.** The largest connected component of the label (others are refused when they are
   large, dropped with a note when they are small islands), a signed distance field from the
   Euclidean distance transform, smoothed by a Gaussian (``smoothing_mm``).
2. **Skeleton** (:mod:`~cgail_patient.skeleton`): trunk, its two ends, the branches.
3. **Which end is the root**: the end touching the left ventricle when an LV label map is given;
   otherwise the end nearer the supra-aortic branches along the trunk (annulus -> brachiocephalic
   ~90 mm, left subclavian -> diaphragm ~200 mm) when that is clear; otherwise the more
   anterior end (with a warning that the frame could not be checked).
4. **Frame check**: with the root known, the descending aorta must lie posterior (and left) of
   the ascending aorta and the branches must point cranially; a mesh given in LPS but declared
   RAS (or the reverse), or a flipped cranial axis, is refused with one line saying so.
5. **Cut planes**: the annulus plane (fitted to the contact with the LV label, or to the flat
   end of the root), the descending end (``descending_mm`` of centreline below the last
   supra-aortic branch, shortened until every start's straight introducer keeps clear of the
   wall) and each branch ``branch_mm`` beyond the aortic wall. Beyond each cut the lumen is
   removed (a tube stub of ``_BEYOND_MM`` is kept for a clean cut); below the annulus the root's
   cross-section is extruded so that the valve plane cuts a full circle.
6. **Surface**: marching cubes (scikit-image) on the field, the largest component, quadric
   decimation (fast-simplification), then isotropic remeshing onto the field
   (:class:`~cgail_sim.mesh_io.Remesher`, the built-in anatomies' method) with the
   edge length that gives ``target_vertices``; the cuts with
   :func:`~cgail_sim.mesh_io.clip_and_cap` (flat ring-meshed caps, the valve plane
   counted as wall), a light relaxation next to them.
7. **Landmarks**: annulus centre and root axis (valve plane), exit point and normal (descending
   cap), start point (20 mm above the exit on the centreline), coronary ostia from a coronary
   label map, from points given by the user, or estimated in the left and right coronary sinuses
   at the usual heights above the annulus (14.4 / 17.2 mm, Tops 2008) with a warning.

Every refusal is a :class:`~cgail_patient.PatientError` with one line that says what was
expected and what was found.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np

from cgail_patient import PatientError
from cgail_patient.skeleton import Branch, Skeleton, skeleton_tree, SkeletonTree
from cgail_patient.volume import LabelVolume
from cgail_sim import mesh_io
from cgail_sim.anatomy import Anatomy

__all__ = [
    "Cut",
    "LandmarkOverrides",
    "PrepareOptions",
    "PreparedAnatomy",
    "prepare_volume",
]

_BEYOND_MM = 8.0
"""Length of lumen kept beyond each cut plane so that the clip crosses a clean tube, mm."""
_OSTIUM_HEIGHT_MM = {"left": 14.4, "right": 17.2}
"""Usual ostium heights above the annulus (Tops 2008; ANATOMY.md)."""
_START_ABOVE_EXIT_MM = 20.0
"""Centreline distance of the first start above the exit cap (as the built-in anatomies)."""
_START_SPAN_MM = 53.0
"""Arc length spanned by the starts (:func:`cgail_sim.scenarios.build_starts`)."""
_EDGE_FACTOR = 0.93
"""Remeshing target edge / ideal edge for ``target_vertices`` (measured on the synthetic aortas:
the remesher ends ~13 % short of the ideal vertex count)."""
_ARCH_CLEARANCE_MM = 40.0
"""Centreline distance between the last supra-aortic branch and the farthest start, mm."""
_ARCH_DROP_MM = 15.0
"""Both limbs of the arch run at least this far caudal of its apex, mm."""
_ARCH_BRANCH_BELOW_MM = 35.0
"""A supra-aortic branch leaves the trunk at most this far caudal of the arch's apex, mm."""
_ARCH_BRANCH_ARC_MM = 70.0
"""... and at most this far along the centreline from it, mm."""
_SKELETON_MM = 1.0
"""Voxel size of the grid the centreline tree is computed on, mm (a coarse first look)."""
_CUT_SHIFTS_MM = (0.0, 1.5, 3.0, 4.5, 6.0, 8.0, -1.5, -3.0)
"""Shifts of a cut plane (inwards > 0) tried in turn until it crosses a clean tube, mm."""
_END_TILT_DEG = 20.0
"""A root end face tilted more than this from the root axis is an axial cut, not the valve."""
_ANNULUS_SPREAD_MM = 3.0
"""Least uncertainty of an annulus found from the root's shape, along the axis, mm."""
_STJ_HEIGHT_MM = (17.0, 22.0)
"""Usual height of the sinotubular junction above the annulus, mm (ANATOMY.md)."""
_CATHETER_RADIUS_MM = 3.5
"""Outer radius of the paper's catheter (7 mm diameter, :mod:`cgail_sim.ftl_model`)."""


@dataclass(frozen=True)
class PrepareOptions:
    """Options of the pipeline (validated in ``__post_init__``)."""

    target_vertices: int = 2500
    """Vertex count of the prepared lumen. 2,500 (the built-in anatomies have 2,450-2,800):
    the deformable wall runs at >= 500 steps/s at this size (``bench/bench_prepare.py``);
    in [500, 20000]."""
    branch_mm: float = 25.0
    """Length of each supra-aortic branch kept beyond the aortic wall, mm (as the built-in
    stubs); in [5, 80]."""
    descending_mm: float = 150.0
    """Centreline length kept below the last supra-aortic branch, mm; in [90, 400]. Shortened
    when the field of view ends earlier; when a straight introducer would touch the wall,
    shorter lengths are tried, then (where the label goes on) up to 100 mm longer ones."""
    smoothing_mm: float = 1.0
    """Standard deviation of the Gaussian smoothing of the lumen field, mm; in [0, 3]."""
    island_fraction: float = 0.05
    """Components of the label larger than this fraction of the largest are refused (two
    disconnected lumens); smaller ones are dropped with a note; in (0, 1]."""

    def __post_init__(self) -> None:
        checks: dict[str, tuple[float, float]] = {
            "target_vertices": (500, 20000), "branch_mm": (5.0, 80.0),
            "descending_mm": (90.0, 400.0), "smoothing_mm": (0.0, 3.0),
            "island_fraction": (1e-6, 1.0)}
        for name, (lo, hi) in checks.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not lo <= value <= hi:
                raise ValueError(f"{name} must be in [{lo:g}, {hi:g}], found {value!r}")


@dataclass(frozen=True)
class LandmarkOverrides:
    """Landmarks given by the user, in patient LPS mm (None: estimated)."""

    annulus_center: np.ndarray | None = None
    exit_point: np.ndarray | None = None
    left_ostium: np.ndarray | None = None
    right_ostium: np.ndarray | None = None


@dataclass(frozen=True)
class Cut:
    """A flat cut of the lumen (patient LPS mm)."""

    name: str
    """``annulus``, ``descending`` or ``branch <k>``."""
    point: np.ndarray
    """(3,) centre of the cut."""
    normal: np.ndarray
    """(3,) unit, out of the kept lumen."""
    radius: float
    """Inscribed radius of the lumen at the cut, mm."""


@dataclass
class PreparedAnatomy:
    """What :func:`prepare_volume` made, with everything the report needs."""

    anatomy: Anatomy
    """The lumen in the phantom frame (m)."""
    annulus_lps_mm: np.ndarray
    """(3,) patient LPS mm of the phantom origin: phantom = (LPS - this) / 1000."""
    cuts: list[Cut]
    skeleton: Skeleton
    """Trunk from the root end to the descending end (LPS mm)."""
    notes: list[str] = field(default_factory=list)
    """Facts worth a line in the report (what was decided and why)."""
    warnings: list[str] = field(default_factory=list)
    """Things the user must check (estimated ostia, an unchecked frame ...)."""
    sources: dict[str, str] = field(default_factory=dict)
    """Where each landmark came from (``estimated``, ``coronary label``, ``given`` ...)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per step."""
    annulus_uncertainty_mm: float = 0.0
    """How far the annulus may lie from the estimate along the root axis, mm (0: given; a
    voxel or two: fitted to the LV contact; more when found from the root's shape)."""
    figures: dict[str, float] = field(default_factory=dict)
    """What the anatomy measures, for tables: ``annulus_diameter_mm`` (equivalent diameter of
    the valve plane), ``arch_branches`` (supra-aortic branches found), ``exit_below_arch_mm``
    (centreline length from the last of them to the descending cut)."""

    def to_phantom(self, points_lps_mm: np.ndarray) -> np.ndarray:
        """Patient LPS mm -> phantom m."""
        return (np.asarray(points_lps_mm, dtype=float) - self.annulus_lps_mm) * 1e-3

    def to_lps(self, points_phantom_m: np.ndarray) -> np.ndarray:
        """Phantom m -> patient LPS mm."""
        return np.asarray(points_phantom_m, dtype=float) * 1e3 + self.annulus_lps_mm


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def _arc(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _at(points: np.ndarray, arc: np.ndarray, s: float) -> np.ndarray:
    return np.array([np.interp(s, arc, points[:, k]) for k in range(3)])


def _tangent(points: np.ndarray, arc: np.ndarray, s: float, half: float = 6.0) -> np.ndarray:
    return _unit(_at(points, arc, min(s + half, arc[-1])) - _at(points, arc, max(s - half, 0.0)))


# ------------------------------------------------------------------------------------------
# 1. Lumen and signed distance
# ------------------------------------------------------------------------------------------
def _largest_component(vol: LabelVolume, options: PrepareOptions,
                       notes: list[str]) -> np.ndarray:
    from scipy.ndimage import label as cc_label

    labels, n = cc_label(vol.mask, structure=np.ones((3, 3, 3)))
    if n == 0:
        raise PatientError(f"expected a lumen in {vol.source}, found no voxel")
    sizes = np.bincount(labels.ravel())[1:]
    order = np.argsort(-sizes)
    best = int(order[0]) + 1
    if n > 1:
        second = int(sizes[order[1]])
        frac = second / float(sizes[order[0]])
        if frac > options.island_fraction:
            raise PatientError(
                f"expected one connected lumen in {vol.source}, found {n} components (the "
                f"second has {frac:.0%} of the largest's volume): a gap in the segmentation? "
                "Join them or remove one")
        h3 = vol.spacing ** 3
        dropped = float(sizes.sum() - sizes[order[0]]) * h3
        notes.append(f"dropped {n - 1} small island(s) of the label ({dropped:.0f} mm^3 in all)")
    return np.asarray(labels == best)


def _signed_distance(mask: np.ndarray, spacing: float, sigma_mm: float) -> np.ndarray:
    """Signed distance to the lumen boundary (mm, < 0 inside), Gaussian-smoothed."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    d_in = distance_transform_edt(mask, sampling=spacing)
    d_out = distance_transform_edt(~mask, sampling=spacing)
    sdf = np.where(mask, -(d_in - 0.5 * spacing), d_out - 0.5 * spacing).astype(np.float32)
    if sigma_mm > 0:
        sdf = gaussian_filter(sdf, sigma_mm / spacing)
    return np.asarray(sdf)


class _Field:
    """Trilinear interpolation of the signed distance grid, in LPS mm."""

    def __init__(self, sdf: np.ndarray, origin: np.ndarray, spacing: float) -> None:
        self.sdf = sdf
        self.origin = np.asarray(origin, dtype=float)
        self.spacing = float(spacing)

    def __call__(self, points_mm: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        idx = (np.asarray(points_mm, dtype=float).reshape(-1, 3) - self.origin) / self.spacing
        return np.asarray(map_coordinates(self.sdf, idx.T, order=1, mode="nearest"))

    def grid_points(self, sel: np.ndarray) -> np.ndarray:
        return np.asarray(self.origin + self.spacing * np.argwhere(sel))


# ------------------------------------------------------------------------------------------
# 3-4. Orientation and frame
# ------------------------------------------------------------------------------------------
def _turns_at(z: np.ndarray, arc: np.ndarray, i: int, sign: float) -> bool:
    """True when the trunk turns back at point ``i``: both limbs leave it by at least
    ``_ARCH_DROP_MM`` along S (``sign`` 1: down from a maximum, -1: up from a minimum)."""
    if arc[i] < 10.0 or arc[-1] - arc[i] < 10.0:
        return False
    d = sign * (z[i] - z)
    return bool(d[:i + 1].max() >= _ARCH_DROP_MM and d[i:].max() >= _ARCH_DROP_MM)


def _arch_apex(skel: Skeleton, source: str, frame_hint: str) -> int:
    """Index of the arch's apex on the trunk: the most cranial trunk point, where the trunk
    turns back on itself (the ascending and descending limbs both run caudally from it).

    Raises:
        PatientError: the lumen turns back at its most CAUDAL point instead (a flipped S axis),
            or it does not turn back at all (no arch in the label).
    """
    z = skel.trunk[:, 2]
    arc = skel.trunk_arc
    top = int(np.argmax(z))
    if _turns_at(z, arc, top, 1.0):
        return top
    bottom = int(np.argmin(z))
    if _turns_at(z, arc, bottom, -1.0):
        raise PatientError(
            f"expected the aortic arch at the cranial (+S) end of the lumen in {source}, found "
            f"the lumen turning back at its most caudal point (S = {z[bottom]:.0f} mm, both "
            f"limbs rising from it): the S axis is flipped; {frame_hint}")
    raise PatientError(
        f"expected an aortic arch in {source} (the lumen turning back at its cranial end, both "
        f"limbs {_ARCH_DROP_MM:.0f} mm below it), found a lumen from S = {z[0]:.0f} to "
        f"{z[-1]:.0f} mm that does not turn back: a thoracic or whole-aorta label is needed")


def _identify(tree: SkeletonTree, lv_points: np.ndarray | None, source: str, frame_hint: str,
              notes: list[str], warnings: list[str]) -> tuple[Skeleton, int, list[Branch]]:
    """The trunk from the root end to the distal end, the arch apex's index on it and the
    supra-aortic (arch) branches, found from the shape alone.

    * Root end: the trunk end next to the left ventricle when an LV label is given; otherwise
      the widest end (the ascending aorta is the widest part of the aorta). The distal end is
      the end farthest from the root along the tree (the descending cut of a thoracic label,
      or an iliac or femoral artery of a whole-aorta label).
    * Arch: the trunk's most cranial point, where it turns back (:func:`_arch_apex`). Without an
      LV label, the ascending limb (root to apex) must be the shorter one: when it is longer,
      the widest end was the descending end of a thoracic label and the ends swap.
    * Arch branches: the branches that leave the top of the arch (junction within
      ``_ARCH_BRANCH_BELOW_MM`` below the apex and ``_ARCH_BRANCH_ARC_MM`` of centreline from
      it) and run cranially. Abdominal and iliac branches never qualify, whatever their size.
    """
    leaves = list(tree.leaves)
    widths = {leaf: tree.end_width(leaf) for leaf in leaves}
    if lv_points is not None and len(lv_points):
        from scipy.spatial import cKDTree

        lv_tree = cKDTree(lv_points)
        wide = sorted(leaves, key=lambda n: -widths[n])[:3]
        dist = {n: float(lv_tree.query(tree.pos[n])[0]) for n in wide}
        root = min(wide, key=lambda n: dist[n])
        notes.append(f"root end: the wide trunk end next to the left ventricle "
                     f"({dist[root]:.0f} mm from it)")
    else:
        root = max(leaves, key=lambda n: widths[n])
    # The widest end is the root's almost always; when its trunk has no arch (a bulge of a
    # real label wider than the root's end), the next widest ends are tried in turn.
    first_error: PatientError | None = None
    roots = [root] if lv_points is not None and len(lv_points) else \
        sorted(leaves, key=lambda n: -widths[n])[:3]
    for root in roots:
        dist_root = tree.distances(root)
        distal = max((n for n in leaves if n != root), key=lambda n: dist_root[n])
        skel = tree.skeleton(root, distal)
        try:
            apex = _arch_apex(skel, source, frame_hint)
            break
        except PatientError as err:
            first_error = first_error or err
    else:
        assert first_error is not None
        raise first_error
    arc = skel.trunk_arc
    asc, desc = float(arc[apex]), float(arc[-1] - arc[apex])
    if lv_points is None or not len(lv_points):
        if asc > desc:
            root = distal
            dist_root = tree.distances(root)
            distal = max((n for n in leaves if n != root), key=lambda n: dist_root[n])
            skel = tree.skeleton(root, distal)
            apex = _arch_apex(skel, source, frame_hint)
            arc = skel.trunk_arc
            asc, desc = float(arc[apex]), float(arc[-1] - arc[apex])
        how = ("the widest end" if widths[root] >= max(widths.values()) else
               "the end of the shorter limb from the arch")
        notes.append(f"root end: {how} (mean radius {widths[root]:.1f} mm; "
                     f"{asc:.0f} mm of centreline to the top of the arch, {desc:.0f} mm from it "
                     "to the distal end)")
        if desc < 1.25 * asc:
            warnings.append("the root end could not be told clearly from the descending end "
                            f"({asc:.0f} vs {desc:.0f} mm of centreline from the arch): check "
                            "the render, or pass --lv")
    z = skel.trunk[:, 2]
    arch_branches = []
    for br in skel.branches:
        j = br.junction_index
        chord = br.points[-1] - br.points[0]
        rises = chord[2] > 0.3 * max(float(np.linalg.norm(chord)), 1e-9)
        if (z[apex] - z[j] <= _ARCH_BRANCH_BELOW_MM and abs(arc[j] - arc[apex])
                <= _ARCH_BRANCH_ARC_MM and rises):
            arch_branches.append(br)
    others = len(skel.branches) - len(arch_branches)
    notes.append(f"arch: top at S = {z[apex]:.0f} mm, {len(arch_branches)} supra-aortic "
                 f"branch(es) leaving it; {others} other branch end(s) of the label (below the "
                 "arch: visceral, renal, iliac ...)")
    if not arch_branches:
        warnings.append("no supra-aortic branch found at the top of the arch: the descending "
                        "cut is measured from the top of the arch; check the render")
    return skel, apex, arch_branches


def _check_frame(skel: Skeleton, apex: int, arch_branches: list[Branch], source: str,
                 frame_hint: str, warnings: list[str]) -> None:
    """Refuse flipped x and y axes: the descending aorta lies posterior-left of the ascending
    aorta (patient LPS). A flipped S axis is refused by :func:`_arch_apex`."""
    arc = skel.trunk_arc
    pts = skel.trunk
    asc = _at(pts, arc, min(30.0, 0.5 * arc[apex]))
    s_last = max((arc[b.junction_index] for b in arch_branches), default=float(arc[apex]))
    desc = _at(pts, arc, min(s_last + 60.0, 0.5 * (s_last + arc[-1])))
    d = desc - asc
    if d[0] < -10.0 and d[1] < -10.0:
        raise PatientError(
            f"expected the descending aorta posterior-left of the ascending aorta in {source}, "
            f"found it anterior-right ({-d[1]:.0f} mm anterior, {-d[0]:.0f} mm right): the "
            f"x and y axes are flipped (LPS read as RAS, or RAS as LPS); {frame_hint}")
    if d[1] < -10.0:
        warnings.append(f"the descending aorta lies {-d[1]:.0f} mm ANTERIOR of the ascending "
                        "aorta: an anterior-posterior flip? Check the frame in the render")
    if d[0] < -10.0:
        warnings.append(f"the descending aorta lies {-d[0]:.0f} mm to the RIGHT of the ascending "
                        "aorta: a right-sided arch or a left-right flip? Check the render")


# ------------------------------------------------------------------------------------------
# 5. Cuts
# ------------------------------------------------------------------------------------------
def _fit_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[2]


def _annulus_plane(field_: _Field, mask: np.ndarray, skel: Skeleton,
                   lv_mask: np.ndarray | None, given: np.ndarray | None,
                   notes: list[str]) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(centre, root axis into the aorta, radius, uncertainty along the axis) of the annulus
    (LPS mm).

    Without a left-ventricle label the annulus comes from the root's shape: the plane of the
    label's flat proximal end when it is square to the root axis, else the lowest cross-section
    square to the axis above an oblique (axial) end face; the uncertainty along the axis is
    the end face's span, at least ``_ANNULUS_SPREAD_MM``, and the sinus / sinotubular profile
    above it is checked against the usual heights (:func:`_root_profile`).
    """
    from scipy.ndimage import binary_dilation

    uncertainty = _ANNULUS_SPREAD_MM

    arc = skel.trunk_arc
    root_end = skel.trunk[0]
    # Direction out of the aorta at the root end (along the trunk, towards the valve).
    out_dir = _unit(skel.trunk[0] - _at(skel.trunk, arc, min(20.0, arc[-1])))
    if lv_mask is not None:
        contact = mask & binary_dilation(lv_mask, iterations=1)
        pts = field_.grid_points(contact)
        if len(pts) < 20:
            raise PatientError(
                f"expected the left-ventricle label to touch the aorta at the root, found "
                f"{len(pts)} contact voxels: wrong LV label or map?")
        # Keep the contact next to the root end (not, e.g., along the ascending wall).
        near = np.linalg.norm(pts - root_end, axis=1) < 40.0
        if near.sum() < 20:
            raise PatientError(
                "expected the left-ventricle contact at the root end of the aorta, found it "
                f"{np.linalg.norm(pts - root_end, axis=1).min():.0f} mm away")
        q, n = _fit_plane(pts[near])
        how = f"fitted to {int(near.sum())} voxels of contact with the left ventricle"
    else:
        # The flat end of the root: boundary samples near the root end facing out of it.
        # The root axis is the ascending centreline 10-35 mm from the end (the skeleton bends
        # into an oblique end face over its last millimetres).
        if arc[-1] > 40.0:
            out_dir = _unit(_at(skel.trunk, arc, 10.0) - _at(skel.trunk, arc, 35.0))
        shell = field_.grid_points(mask & ~_erode(mask))
        rel = shell - root_end
        cand = shell[(np.linalg.norm(rel, axis=1) < 35.0) & (rel @ out_dir > -12.0)]
        if len(cand) < 20:
            raise PatientError("expected a closed root end (the valve plane), found an open "
                               "or empty root in the label")
        eps = 0.5
        grad = np.stack([(field_(cand + eps * e) - field_(cand - eps * e)) / (2 * eps)
                         for e in np.eye(3)], axis=1)
        grad /= np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-9)
        facing = cand[grad @ out_dir > 0.5]
        if len(facing) < 20:
            raise PatientError("expected the root to end in a flat valve plane, found no flat "
                               "end facing out of it: give the annulus (--annulus) or an LV "
                               "label (--lv)")
        q, n = _fit_plane(facing)
        n = n if n @ out_dir > 0 else -n
        tilt = math.degrees(math.acos(min(1.0, abs(float(n @ out_dir)))))
        if tilt <= _END_TILT_DEG:
            flat = cand[grad @ n > 0.9]  # the end face itself, without the bend into it
            if len(flat) >= 20:
                facing = flat
                q, n = _fit_plane(facing)
                n = n if n @ out_dir > 0 else -n
            how = f"fitted to the flat end of the root ({len(facing)} boundary voxels)"
        else:
            # An end cut by an axial slice, oblique to the root: the annulus is the lowest
            # cross-section square to the root axis that the end face does not truncate.
            n = out_dir
            heights = (facing - root_end) @ -out_dir
            top = float(np.percentile(heights, 95.0)) + 1.0
            span = top - float(heights.min())
            q = root_end - top * out_dir
            how = (f"the lowest complete cross-section square to the root axis: the label's "
                   f"end face is oblique to it ({tilt:.0f} deg, an axial cut) and spans "
                   f"{span:.0f} mm along the axis below the plane")
            uncertainty = max(uncertainty, span)
    axis = -_unit(n) if n @ out_dir > 0 else _unit(n)
    if given is not None:
        q = np.asarray(given, dtype=float)
        how += "; centre given by the user"
    # Centre: centroid of the cross-section 1 mm above the plane, near the axis.
    above = field_.grid_points(mask)
    rel = above - q
    h = rel @ axis
    rho = np.linalg.norm(rel - np.outer(h, axis), axis=1)
    section = above[(h > 0.5) & (h < 0.5 + 2 * field_.spacing) & (rho < 35.0)]
    if len(section) < 10:
        raise PatientError("expected lumen just above the annulus plane, found none: the "
                           "annulus estimate left the root")
    centre = section.mean(axis=0)
    centre = centre - ((centre - q) @ axis) * axis
    if given is not None:
        centre = q
    radius = float(np.sqrt(len(section) * field_.spacing ** 3 / (2 * field_.spacing) / math.pi))
    notes.append(f"annulus plane {how}")
    if lv_mask is not None:
        uncertainty = 2.0 * field_.spacing
    return centre, axis, radius, uncertainty


def _coarse(mask: np.ndarray, vol: LabelVolume, sigma_mm: float) -> LabelVolume:
    """The lumen smoothed by ``sigma_mm`` on a ``_SKELETON_MM`` grid (or the working grid
    when coarser), for the centreline tree: thinning a whole aorta on a 0.5 mm grid takes
    half a minute, and the tree is only a first look."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    h = max(_SKELETON_MM, vol.spacing)
    smooth = gaussian_filter(mask.astype(np.float32), max(sigma_mm, 0.5 * h) / vol.spacing)
    shape = np.floor((np.array(mask.shape) - 1) * vol.spacing / h).astype(int) + 1
    axes = [np.arange(n) * h / vol.spacing for n in shape]
    idx = np.stack(np.meshgrid(*axes, indexing="ij"), axis=0)
    coarse = map_coordinates(smooth, idx.reshape(3, -1), order=1, mode="nearest")
    return LabelVolume(coarse.reshape(tuple(shape)) > 0.5, vol.origin, h, vol.source)


def _kept_box(skel: Skeleton, arch_branches: list[Branch], options: PrepareOptions,
              given_exit: bool) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) LPS mm corners of the part of the label that can be kept: the trunk from
    the root to the longest possible descending cut, the branches joining it there, and a
    margin for the extruded root and the cut stubs."""
    arc = skel.trunk_arc
    s_last = max((float(arc[b.junction_index]) for b in arch_branches), default=0.0)
    reach = float(arc[-1]) if given_exit else s_last + options.descending_mm + 2 * _BEYOND_MM
    pts = [skel.trunk[arc <= reach]]
    pts += [b.points for b in skel.branches if arc[b.junction_index] <= reach]
    allp = np.concatenate(pts)
    margin = float(skel.trunk_radii.max()) + 45.0
    return allp.min(axis=0) - margin, allp.max(axis=0) + margin


def _crop(vol: LabelVolume, mask: np.ndarray, box: tuple[np.ndarray, np.ndarray]
          ) -> LabelVolume:
    """``mask`` (on ``vol``'s grid) cut to the LPS box."""
    lo = np.maximum(np.floor((box[0] - vol.origin) / vol.spacing).astype(int), 0)
    hi = np.minimum(np.ceil((box[1] - vol.origin) / vol.spacing).astype(int) + 1,
                    np.array(mask.shape))
    sl = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    return LabelVolume(np.ascontiguousarray(mask[sl]), vol.origin + vol.spacing * lo,
                       vol.spacing, vol.source)


def _keep_connected(sdf: np.ndarray, field_: _Field, inside: np.ndarray,
                    notes: list[str]) -> np.ndarray:
    """The field with every lumen piece not connected to ``inside`` (LPS mm) removed: what
    lies beyond the descending cut (the abdominal aorta, iliacs) once the cuts are carved."""
    from scipy.ndimage import label as cc_label

    labels, n = cc_label(sdf < 0.0)
    ijk = np.clip(np.rint((inside - field_.origin) / field_.spacing).astype(int), 0,
                  np.array(sdf.shape) - 1)
    keep = int(labels[tuple(ijk)])
    if keep == 0:
        raise PatientError("expected the top of the arch inside the carved lumen, found it "
                           "outside: the cuts removed the arch")
    if n > 1:
        out = sdf.copy()
        drop = (labels != keep) & (labels > 0)
        out[drop] = np.maximum(out[drop], field_.spacing)
        removed = float(drop.sum()) * field_.spacing ** 3 * 1e-3
        notes.append(f"removed {removed:.0f} mL of lumen beyond the cuts ({n - 1} piece(s))")
        return out
    return sdf


def _root_profile(field_: _Field, mask: np.ndarray, centre: np.ndarray, axis: np.ndarray,
                  radius: float) -> tuple[float, float, float]:
    """(sinus height, sinotubular-junction height, sinus bulge) above the annulus, mm: the
    widest equivalent radius 0-15 mm above it, the narrowest 10-35 mm above it and beyond the
    sinus, and their difference (a label that starts above the valve has no bulge)."""
    pts = field_.grid_points(mask)
    rel = pts - centre
    h = rel @ axis
    rho = np.linalg.norm(rel - np.outer(h, axis), axis=1)
    sel = (h >= 0.0) & (h < 36.0) & (rho < max(1.5 * radius, radius + 8.0))
    counts = np.bincount(np.floor(h[sel]).astype(int), minlength=36)[:36]
    r_eq = np.sqrt(counts * field_.spacing ** 3 / math.pi)
    h_sinus = int(np.argmax(r_eq[:16]))
    lo = max(10, h_sinus + 3)
    h_stj = lo + int(np.argmin(r_eq[lo:36]))
    return float(h_sinus), float(h_stj), float(r_eq[h_sinus] - r_eq[h_stj])


def _euler(sdf: np.ndarray) -> int:
    """Euler characteristic of the largest zero-level surface of ``sdf`` (2: no handle)."""
    from skimage.measure import marching_cubes

    v, f, _, _ = marching_cubes(np.pad(sdf, 1, constant_values=1.0), 0.0)
    v, f = mesh_io.largest_component(v, np.asarray(f, dtype=np.int64))
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]),
                              axis=1), axis=0)
    return int(len(v) - len(edges) + len(f))


def _break_handles(sdf: np.ndarray, field_: _Field, notes: list[str]) -> np.ndarray:
    """The field with every handle of the lumen cut at its narrowest point.

    Real labels have them where two vessels touch (a carotid against the brachiocephalic
    trunk, a thin bridge on 3 mm slices): a loop in the lumen's skeleton. Each loop is cut by
    removing a ball at the loop's narrowest skeleton point (its inscribed radius + a voxel),
    which is where the two vessels meet. Refused when a handle remains after a few rounds.
    """
    import networkx as nx
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import cKDTree
    from skimage.morphology import skeletonize

    h = field_.spacing
    out = sdf
    for _ in range(4):
        euler = _euler(out)
        if euler == 2:
            return out
        mask = out < 0.0
        ijk = np.argwhere(skeletonize(mask))
        edt = distance_transform_edt(mask, sampling=h)
        tree = cKDTree(ijk)
        pairs = tree.query_pairs(np.sqrt(3.0) + 1e-6, output_type="ndarray")
        g = nx.Graph()
        g.add_edges_from((int(a), int(b)) for a, b in pairs)
        cycles = [c for c in nx.cycle_basis(g) if len(c) >= 6]
        if not cycles:
            break
        out = out.copy()
        grid: tuple[np.ndarray, ...] = tuple(np.indices(out.shape, sparse=True))
        for cyc in cycles:
            node = min(cyc, key=lambda n: float(edt[tuple(ijk[n])]))
            r = float(edt[tuple(ijk[node])]) + h
            c = ijk[node]
            d2 = np.zeros((1, 1, 1))
            for k in range(3):
                d2 = d2 + (grid[k] - int(c[k])) ** 2
            ball = d2 <= (r / h) ** 2
            out[ball] = np.maximum(out[ball], h)
            notes.append(f"cut a handle of the lumen (a loop of {len(cyc) * h:.0f} mm) at its "
                         f"narrowest point {np.round(field_.origin + h * c).tolist()} mm "
                         f"(radius {r - h:.1f} mm): two vessels touching in the label?")
    if _euler(out) != 2:
        raise PatientError(f"expected a lumen without handles (Euler characteristic 2), found "
                           f"{_euler(out)} after cutting loops: vessels fused in the label?")
    return out


def _erode(mask: np.ndarray) -> np.ndarray:
    from scipy.ndimage import binary_erosion

    return np.asarray(binary_erosion(mask))


def _introducer_clearance(trunk: np.ndarray, radii: np.ndarray, arc: np.ndarray,
                          s_exit: float, exit_normal: np.ndarray, exit_point: np.ndarray
                          ) -> float:
    """Smallest (lumen radius - distance from the trunk) along the straight introducers of
    the three starts, mm (< catheter radius: the introducer would touch the wall)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(trunk)
    worst = math.inf
    for off in (0.0, 0.5 * _START_SPAN_MM, _START_SPAN_MM):
        s = s_exit - _START_ABOVE_EXIT_MM - off
        p = _at(trunk, arc, s)
        heading = -_tangent(trunk, arc, s)  # cranial: towards the root (decreasing s)
        depth = float((p - exit_point) @ exit_normal)
        cos = float(heading @ exit_normal)
        if cos >= -0.2:
            return -math.inf
        length = (depth - 0.0) / cos
        for t in np.linspace(0.0, length, 40):
            q = p - t * heading
            d, i = tree.query(q)
            worst = min(worst, float(radii[i]) - float(d))
    return worst


def _last_branch_arc(skel: Skeleton, apex: int, arch_branches: list[Branch]) -> float:
    """Arc length along the trunk of the last supra-aortic branch's junction, mm (the top of
    the arch + 20 mm when none was found)."""
    return max((float(skel.trunk_arc[b.junction_index]) for b in arch_branches),
               default=float(skel.trunk_arc[apex]) + 20.0)


def _plan_cuts(skel: Skeleton, apex: int, arch_branches: list[Branch],
               annulus: tuple[np.ndarray, np.ndarray, float], options: PrepareOptions,
               given_exit: np.ndarray | None, notes: list[str],
               warnings: list[str]) -> tuple[list[Cut], float]:
    """The cut planes and the arc length of the exit along the trunk (mm).

    The descending cut lies ``options.descending_mm`` of centreline below the last arch
    branch (the top of the arch + 20 mm when none was found), whatever the label holds below
    it (abdominal branches, iliacs); every branch that joins the trunk above the cut is cut
    ``branch_mm`` beyond the wall.
    """
    centre, axis, r_ann = annulus
    arc = skel.trunk_arc
    trunk = skel.trunk
    radii = skel.trunk_radii
    cuts = [Cut("annulus", centre, -axis, r_ann)]
    s_last = _last_branch_arc(skel, apex, arch_branches)
    end_room = float(arc[-1]) - _BEYOND_MM - 2.0
    # The farthest start must lie in the descending aorta, clear of the arch's bend.
    need = _START_ABOVE_EXIT_MM + _START_SPAN_MM + _ARCH_CLEARANCE_MM
    if given_exit is not None:
        s_exit = float(arc[int(np.argmin(np.linalg.norm(trunk - given_exit, axis=1)))])
        notes.append(f"descending cut at the exit point given by the user "
                     f"({s_exit - s_last:.0f} mm below the last branch)")
    else:
        if end_room - s_last < need:
            raise PatientError(
                f"expected at least {need:.0f} mm of descending aorta below the last "
                f"supra-aortic branch (room for the starts), found {end_room - s_last:.0f} mm: "
                "the segmentation ends too early")
        # The longest descending aorta (up to descending_mm) whose straight introducers keep
        # clear of the wall; shorter ones are tried in 10 mm steps.
        first = min(s_last + options.descending_mm, end_room)
        # Shorter first; then, where a whole-aorta label goes on, up to 100 mm longer (an
        # S-shaped real descending aorta may be straight only further down).
        longer = np.arange(first + 10.0, min(first + 100.0, end_room) + 1e-9, 10.0)
        candidates = np.concatenate([np.arange(first, s_last + need - 1e-9, -10.0), longer])
        best = (-math.inf, first)
        for cand in candidates:
            clear = _introducer_clearance(trunk, radii, arc, float(cand),
                                          _tangent(trunk, arc, float(cand)),
                                          _at(trunk, arc, float(cand)))
            if clear > best[0]:
                best = (clear, float(cand))
            if clear >= _CATHETER_RADIUS_MM + 1.0:
                best = (clear, float(cand))
                break
        clear, s_exit = best
        if clear < _CATHETER_RADIUS_MM + 1.0:
            warnings.append(
                f"the descending aorta bends: at best a straight introducer passes "
                f"{clear:.1f} mm inside the centreline's inscribed radius (catheter radius "
                f"{_CATHETER_RADIUS_MM} mm); see the introducer check")
        notes.append(f"descending cut {s_exit - s_last:.0f} mm of centreline below the last "
                     f"supra-aortic branch (asked {options.descending_mm:.0f} mm; the label "
                     f"continues {arc[-1] - s_exit:.0f} mm beyond)")
    exit_point = _at(trunk, arc, s_exit)
    exit_normal = _tangent(trunk, arc, s_exit)
    r_exit = float(np.interp(s_exit, arc, radii))
    cuts.append(Cut("descending", exit_point, exit_normal, r_exit))
    k = 0
    for br in skel.branches:
        s_j = float(arc[br.junction_index])
        if s_j > s_exit:
            continue  # removed with the descending end
        if s_j < 0.5 * float(arc[apex]):
            # No branch leaves the ascending aorta's proximal half (the coronaries are not in
            # the label): a lobe of the root's end face, removed with the root below the
            # annulus or left closed.
            notes.append(f"a {br.length:.0f} mm end {s_j:.0f} mm from the root end is a lobe "
                         "of the root, not a branch: not cut")
            continue
        barc = _arc(br.points)
        r_j = float(radii[br.junction_index])
        u = r_j + options.branch_mm
        if barc[-1] - _BEYOND_MM - 2.0 < u:
            u = float(barc[-1]) - _BEYOND_MM - 2.0
            if u < r_j + 3.0:
                notes.append(f"a {barc[-1]:.0f} mm side branch at {s_j:.0f} mm is too short to "
                             "cut; left closed")
                continue
        k += 1
        p = _at(br.points, barc, u)
        n = _tangent(br.points, barc, u, half=4.0)
        cuts.append(Cut(f"branch {k}", p, n, float(np.interp(u, barc, br.radii))))
    notes.append(f"{k} side branch(es) cut {options.branch_mm:.0f} mm beyond the aortic wall "
                 "(or 10 mm before their end when shorter)")
    return cuts, s_exit


def _carve(sdf: np.ndarray, field_: _Field, cuts: list[Cut]) -> np.ndarray:
    """The field with the lumen removed beyond each cut (but a _BEYOND_MM stub) and the root
    cross-section extruded below the annulus plane."""
    from scipy.ndimage import label as cc_label

    out = sdf.copy()
    h = field_.spacing
    pad = 10.0
    for cut in cuts:
        r = cut.radius + pad
        lo = np.floor((cut.point - field_.origin - (r + 60.0)) / h).astype(int)
        hi = np.ceil((cut.point - field_.origin + (r + 60.0)) / h).astype(int)
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, np.array(sdf.shape) - 1)
        sl = tuple(slice(int(a), int(b) + 1) for a, b in zip(lo, hi, strict=True))
        ii = np.stack(np.meshgrid(*(np.arange(s.start, s.stop) for s in sl), indexing="ij"),
                      axis=-1)
        pts = field_.origin + h * ii
        rel = pts - cut.point
        ax = rel @ cut.normal
        rho = np.linalg.norm(rel - ax[..., None] * cut.normal, axis=-1)
        sub = out[sl]
        if cut.name == "annulus":
            below = (ax > 0.0) & (rho < r) & (ax < _BEYOND_MM + 2.0)
            src = pts[below] - (ax[below] + 1.0)[:, None] * cut.normal
            sub[below] = field_(src)
            sub[(ax >= _BEYOND_MM + 2.0) & (rho < r) & (ax < _BEYOND_MM + 40.0)] = h
            sub[below & (ax > _BEYOND_MM)] = np.maximum(sub[below & (ax > _BEYOND_MM)], h)
        else:
            beyond = (ax > 0.0) & (rho < r) & (sub < 0.0)
            labels, _ = cc_label(beyond)
            # The tube beyond the plane: components crossing the cut disc.
            disc = beyond & (ax < 2 * h) & (rho < cut.radius + 2.0)
            keep = np.unique(labels[disc])
            tube = np.isin(labels, keep[keep > 0])
            sub[tube & (ax > _BEYOND_MM)] = h
        out[sl] = sub
    return out


# ------------------------------------------------------------------------------------------
# 6. Surface
# ------------------------------------------------------------------------------------------
def _surface(sdf: np.ndarray, field_: _Field, target_vertices: int,
             cuts: list[Cut], annulus_lps: np.ndarray, timings: dict[str, float],
             notes: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                        list[np.ndarray], np.ndarray, np.ndarray]:
    """(vertices m, faces, wall mask, cap vertex ids per cut, annulus vertex ids, valve-plane
    face mask)."""
    import time

    import fast_simplification
    from skimage.measure import marching_cubes
    import trimesh

    t0 = time.perf_counter()
    padded = np.pad(sdf, 1, constant_values=float(field_.spacing))
    v, f, _, _ = marching_cubes(padded, 0.0)
    v = (v - 1.0) * field_.spacing + field_.origin
    v, f = mesh_io.largest_component(v, np.asarray(f, dtype=np.int64))
    mesh = trimesh.Trimesh(v, f, process=False)
    if mesh.volume < 0:
        f = f[:, ::-1]
    area = float(mesh.area)
    timings["marching cubes"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # Vertex count of an isotropic mesh of this area; the remesher's edges come out ~7 % long.
    edge_mm = _EDGE_FACTOR * math.sqrt(2.0 * area / (math.sqrt(3.0) * target_vertices))
    n_faces = int(min(len(f), 6 * target_vertices * 2))
    if n_faces < len(f):
        v, f = fast_simplification.simplify(v, f, target_count=n_faces)
    v, f = mesh_io.largest_component(np.asarray(v, dtype=float), np.asarray(f, dtype=np.int64))
    timings["decimation"] = time.perf_counter() - t0
    t0 = time.perf_counter()

    def field_m(p: np.ndarray) -> np.ndarray:
        return field_(np.asarray(p) * 1e3 + annulus_lps) * 1e-3

    edge = edge_mm * 1e-3
    vm = (v - annulus_lps) * 1e-3
    remesher = mesh_io.Remesher(vm, f, field_m, lambda p: np.full(len(p), edge))
    vm, f = remesher.run(iterations=5)
    timings["remeshing"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cap_mask = np.zeros(len(f), dtype=bool)
    valve_mask = np.zeros(len(f), dtype=bool)
    cap_ids: list[np.ndarray] = []
    annulus_ids = np.zeros(0, dtype=np.int64)
    for cut in cuts:
        is_wall = cut.name == "annulus"
        point = (cut.point - annulus_lps) * 1e-3
        r = cut.radius * 1e-3
        # A plane through a pinch of the surface (a lobe of an oblique root end, a bump of
        # the segmentation) gives no simple loop: the cut moves by up to 8 mm (inwards first).
        closed = False
        for shift in _CUT_SHIFTS_MM:
            try:
                vm_new, new_f, kept, ids = mesh_io.clip_and_cap(
                    vm, f, point - shift * 1e-3 * cut.normal, cut.normal, r + 0.004,
                    _BEYOND_MM * 1e-3 + r + 0.004, edge, field_m)
                break
            except mesh_io.MeshError as err:
                if shift != _CUT_SHIFTS_MM[-1]:
                    continue
                if not cut.name.startswith("branch"):
                    raise PatientError(f"expected a clean tube to cut at the {cut.name} cut, "
                                       f"found: {err}") from err
                # A side branch is left closed (a blind stub) rather than refuse the lumen.
                notes.append(f"the {cut.name} stub could not be cut cleanly ({err}): left "
                             "closed")
                closed = True
        if closed:
            continue
        if shift:
            notes.append(f"the {cut.name} cut moved {shift:+.1f} mm inwards to cross a clean "
                         "tube")
        vm = vm_new
        n_new = len(new_f) - len(kept)
        cap_mask = np.concatenate([cap_mask[kept], np.full(n_new, not is_wall)])
        valve_mask = np.concatenate([valve_mask[kept], np.full(n_new, is_wall)])
        f = new_f
        if is_wall:
            annulus_ids = ids
        else:
            cap_ids.append(ids)
    vm, f, remap = mesh_io.compact_with_map(vm, f)
    cap_ids = [remap[c] for c in cap_ids]
    annulus_ids = remap[annulus_ids]
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]),
                              axis=1), axis=0)
    euler = len(vm) - len(edges) + len(f)
    if euler != 2:
        raise PatientError(f"expected a sphere-like lumen surface after the cuts (Euler "
                           f"characteristic 2), found {euler}: a handle or a hole in the lumen")
    hold = np.zeros(len(vm), dtype=bool)
    for c in cap_ids:
        hold[c] = True
    hold[annulus_ids] = True
    vm = mesh_io.relax(vm, f, field_m, hold, iterations=3)
    timings["cuts and caps"] = time.perf_counter() - t0
    return vm, f, ~cap_mask, cap_ids, annulus_ids, valve_mask


def _disc_centroid(v: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, float]:
    """(area-weighted centroid, area) of a set of (flat cap) triangles."""
    tri = v[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum(), float(area.sum())


# ------------------------------------------------------------------------------------------
# 7. Landmarks
# ------------------------------------------------------------------------------------------
def _wall_rays(mesh: Any, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance from ``origin`` to the first wall hit along each direction (inf: none)."""
    locs, idx, _ = mesh.ray.intersects_location(np.repeat(origin[None], len(dirs), axis=0),
                                                dirs, multiple_hits=False)
    out = np.full(len(dirs), np.inf)
    out[idx] = np.linalg.norm(locs - origin, axis=1)
    return out


def estimate_ostia(anatomy_mesh: Any, axis: np.ndarray,
                   warnings: list[str]) -> dict[str, np.ndarray]:
    """Ostia (phantom m) in the left and right coronary sinuses at the usual heights.

    The sinus lobes are the three peaks of the root's wall distance around the axis, 6-14 mm
    above the annulus; the right coronary sinus is the most anterior one, the left coronary
    sinus the more leftward of the other two. The ostium is the wall point in the middle of
    its sinus at 14.4 mm (left) / 17.2 mm (right) above the annulus (Tops 2008), at most
    2 mm below the sinotubular junction (the narrowest level 10-35 mm above the annulus).
    """
    ant = np.array([0.0, -1.0, 0.0])
    e1 = _unit(ant - (ant @ axis) * axis)
    e2 = np.cross(axis, e1)
    phi = np.linspace(0.0, 2 * np.pi, 144, endpoint=False)
    dirs = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2

    def radius_at(h_mm: float) -> np.ndarray:
        return _wall_rays(anatomy_mesh, h_mm * 1e-3 * axis, dirs) * 1e3

    heights = np.arange(10.0, 35.5, 1.0)
    mean_r = np.array([np.median(radius_at(float(h))) for h in heights])
    h_stj = float(heights[int(np.argmin(mean_r))])
    prof = np.mean([radius_at(h) for h in (6.0, 8.0, 10.0, 12.0, 14.0)], axis=0)
    prof = np.where(np.isfinite(prof), prof, np.nanmedian(prof[np.isfinite(prof)]))
    k = np.exp(-0.5 * (np.arange(-6, 7) / 3.0) ** 2)
    smooth = np.convolve(np.concatenate([prof[-6:], prof, prof[:6]]), k / k.sum(), "valid")
    peaks = [i for i in range(len(smooth))
             if smooth[i] >= smooth[i - 1] and smooth[i] > smooth[(i + 1) % len(smooth)]]
    peaks = sorted(peaks, key=lambda i: -smooth[i])
    lobes: list[int] = []
    for i in peaks:
        if all(min(abs(i - j), len(phi) - abs(i - j)) >= len(phi) // 6 for j in lobes):
            lobes.append(i)
    lobes = lobes[:3]
    depth = float(smooth.max() - smooth.min())
    if len(lobes) == 3 and depth > 1.0:
        right = min(lobes, key=lambda i: float(dirs[i] @ ant) * -1.0)
        rest = [i for i in lobes if i != right]
        left = max(rest, key=lambda i: float(dirs[i][0]))
        phis = {"left": phi[left], "right": phi[right]}
        how = "in the middle of the left and right coronary sinuses"
    else:
        phis = {"left": 123.0 * math.pi / 180.0, "right": 0.0}
        if (math.cos(phis["left"]) * e1 + math.sin(phis["left"]) * e2)[0] < 0:
            phis["left"] = -phis["left"]
        how = ("right anterior and left 123 deg around the root (no three sinus lobes found, "
               f"wall depth {depth:.1f} mm)")
    ostia = {}
    for side in ("left", "right"):
        h = min(_OSTIUM_HEIGHT_MM[side], h_stj - 2.0)
        d = math.cos(phis[side]) * e1 + math.sin(phis[side]) * e2
        dist = _wall_rays(anatomy_mesh, h * 1e-3 * axis, d[None])[0]
        if not np.isfinite(dist):
            raise PatientError(f"expected the {side} coronary sinus wall {h:.0f} mm above the "
                               "annulus, found no wall there")
        ostia[side] = h * 1e-3 * axis + dist * d
    warnings.append(
        f"coronary ostia ESTIMATED {how}, at {min(_OSTIUM_HEIGHT_MM['left'], h_stj - 2):.1f} / "
        f"{min(_OSTIUM_HEIGHT_MM['right'], h_stj - 2):.1f} mm above the annulus (left / right; "
        "Tops 2008): give --coronary or --left-ostium/--right-ostium for this patient's ostia")
    return ostia


def _ostia_from_labels(coronary: np.ndarray, mask: np.ndarray, field_: _Field
                       ) -> dict[str, np.ndarray]:
    """Ostia (LPS mm): the centres of the contacts of the two largest coronary components with
    the aorta; left is the one further to the patient's left (+x)."""
    from scipy.ndimage import binary_dilation
    from scipy.ndimage import label as cc_label

    labels, n = cc_label(coronary, structure=np.ones((3, 3, 3)))
    if n < 2:
        raise PatientError(f"expected two coronary arteries (left and right) in the coronary "
                           f"label map, found {n}")
    sizes = np.bincount(labels.ravel())[1:]
    centres = []
    for lab in np.argsort(-sizes)[:2] + 1:
        contact = binary_dilation(labels == lab, iterations=1) & mask
        if contact.sum() < 3:
            gap = float(np.min(np.abs(field_(field_.grid_points(labels == lab)))))
            raise PatientError("expected each coronary artery to touch the aorta, found one "
                               f"{gap:.0f} mm away")
        centres.append(field_.grid_points(contact).mean(axis=0))
    left, right = sorted(centres, key=lambda c: -float(c[0]))
    return {"left": left, "right": right}


# ------------------------------------------------------------------------------------------
# Pipeline
# ------------------------------------------------------------------------------------------
def prepare_volume(vol: LabelVolume, *, name: str, options: PrepareOptions | None = None,
                   lv: LabelVolume | None = None, coronary: LabelVolume | None = None,
                   overrides: LandmarkOverrides | None = None,
                   frame_hint: str = "check the input's axis convention") -> PreparedAnatomy:
    """Make a simulator anatomy from a lumen volume (see the module doc).

    Args:
        vol: the aortic lumen (patient LPS mm grid).
        name: anatomy name.
        options: pipeline options.
        lv: left-ventricle mask on the same grid, or None.
        coronary: coronary mask on the same grid, or None.
        overrides: landmarks given by the user (LPS mm).
        frame_hint: what to tell the user when the axes look flipped.

    Raises:
        PatientError: the input cannot be made into a usable anatomy (one line why).
    """
    import time

    import trimesh

    opts = options or PrepareOptions()
    ov = overrides or LandmarkOverrides()
    notes: list[str] = []
    warnings: list[str] = []
    timings: dict[str, float] = {}
    sources: dict[str, str] = {}
    t0 = time.perf_counter()
    mask = _largest_component(vol, opts, notes)
    timings["lumen"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    tree = skeleton_tree(_coarse(mask, vol, opts.smoothing_mm))
    lv_points = None
    if lv is not None:
        lv_only = lv.mask & ~mask
        if not lv_only.any():
            raise PatientError(f"expected left-ventricle voxels in {lv.source}, found none "
                               "outside the aorta")
        lv_points = vol.points(np.argwhere(lv_only & ~_erode(lv_only)))
    skel, apex, arch_branches = _identify(tree, lv_points, vol.source, frame_hint, notes,
                                          warnings)
    _check_frame(skel, apex, arch_branches, vol.source, frame_hint, warnings)
    timings["skeleton"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # Only the part of the label that is kept needs the fine field: the root, the arch with
    # its branches and the descending aorta down to the longest cut (plus a margin).
    box = _kept_box(skel, arch_branches, opts, ov.exit_point is not None)
    vol = _crop(vol, mask, box)
    mask = vol.mask
    sdf = _signed_distance(mask, vol.spacing, opts.smoothing_mm)
    field_ = _Field(sdf, vol.origin, vol.spacing)
    sdf = field_.sdf = _break_handles(sdf, field_, notes)
    mask = sdf < 0.0
    lv_mask = None if lv is None else _crop(lv, lv.mask, box).mask & ~mask
    if coronary is not None:
        coronary = _crop(coronary, coronary.mask, box)
    timings["lumen field"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    centre, axis, r_ann, uncertainty = _annulus_plane(field_, mask, skel, lv_mask,
                                                      ov.annulus_center, notes)
    h_sinus, h_stj, bulge = _root_profile(field_, mask, centre, axis, r_ann)
    if lv is None and ov.annulus_center is None:
        lo, hi = _STJ_HEIGHT_MM
        if bulge < 1.0:
            warnings.append(
                f"annulus from the root's shape: no sinus bulge above it (widest {bulge:.1f} mm "
                "over the sinotubular junction): the label may start above the valve, and the "
                "true annulus lie lower; give --annulus or an LV label (--lv)")
            uncertainty = max(uncertainty, hi)
        elif not lo - uncertainty <= h_stj <= hi + uncertainty:
            warnings.append(
                f"annulus from the root's shape: the sinotubular junction lies {h_stj:.0f} mm "
                f"above it (usually {lo:.0f}-{hi:.0f} mm): check the annulus in the render")
            uncertainty = max(uncertainty, abs(h_stj - 0.5 * (lo + hi)))
        notes.append(f"annulus uncertainty +- {uncertainty:.0f} mm along the root axis (no LV "
                     f"label): sinus widest {h_sinus:.0f} mm above the annulus, sinotubular "
                     f"junction {h_stj:.0f} mm (usually {lo:.0f}-{hi:.0f}), bulge {bulge:.1f} mm")
    else:
        uncertainty = 0.0 if ov.annulus_center is not None else uncertainty
    sources["annulus_center"] = "given" if ov.annulus_center is not None else (
        "LV contact" if lv is not None else "root end")
    cuts, s_exit = _plan_cuts(skel, apex, arch_branches, (centre, axis, r_ann), opts,
                              ov.exit_point, notes, warnings)
    sources["exit_point"] = "given" if ov.exit_point is not None else "descending cut"
    carved = _keep_connected(_carve(sdf, field_, cuts), field_, skel.trunk[apex], notes)
    carved_field = _Field(carved, vol.origin, vol.spacing)
    timings["cuts planned"] = time.perf_counter() - t0
    vm, faces, wall, cap_ids, annulus_ids, valve = _surface(
        carved, carved_field, opts.target_vertices, cuts, centre, timings, notes)
    t0 = time.perf_counter()
    # The phantom origin is the centroid of the valve plane (the annulus cross-section).
    shift, valve_area = _disc_centroid(vm, faces[valve])
    vm = vm - shift
    annulus_lps = centre + shift * 1e3
    notes.append(f"annulus: equivalent diameter {2e3 * math.sqrt(valve_area / math.pi):.1f} mm "
                 "(valve-plane area)")
    exit_ids = set(cap_ids[0].tolist())
    exit_faces = faces[~wall][np.all(np.isin(faces[~wall], list(exit_ids)), axis=1)]
    exit_point, _ = _disc_centroid(vm, exit_faces)
    arc = skel.trunk_arc
    start_lps = _at(skel.trunk, arc, s_exit - _START_ABOVE_EXIT_MM)
    start_dir = -_tangent(skel.trunk, arc, s_exit - _START_ABOVE_EXIT_MM)
    mesh = trimesh.Trimesh(vm, faces[wall], process=False)
    if coronary is not None:
        ostia_lps = _ostia_from_labels(coronary.mask & ~mask, mask, field_)
        ostia = {k: (p - annulus_lps) * 1e-3 for k, p in ostia_lps.items()}
        sources["left_ostium"] = sources["right_ostium"] = "coronary label"
    else:
        ostia = {}
    for side, given in (("left", ov.left_ostium), ("right", ov.right_ostium)):
        if given is not None:
            ostia[side] = (np.asarray(given, dtype=float) - annulus_lps) * 1e-3
            sources[f"{side}_ostium"] = "given"
    if len(ostia) < 2:
        estimated = estimate_ostia(mesh, axis, warnings)
        for side in ("left", "right"):
            if side not in ostia:
                ostia[side] = estimated[side]
                sources[f"{side}_ostium"] = "estimated"
    # Ostia lie on the wall: project them, refusing points far from it.
    for side in ("left", "right"):
        closest, dist, _ = trimesh.proximity.closest_point(mesh, ostia[side][None])
        if dist[0] > 0.005:
            raise PatientError(
                f"expected the {side} ostium on the aortic wall (within 5 mm), found it "
                f"{dist[0] * 1e3:.0f} mm away ({sources[f'{side}_ostium']})")
        ostia[side] = closest[0]
    from scipy.spatial import cKDTree

    wall_vertices = np.unique(faces[wall])
    tree = cKDTree(vm[wall_vertices])
    fixed = np.unique(np.concatenate(cap_ids))
    anatomy = Anatomy(
        name=name, vertices=vm, faces=faces, wall_face_mask=wall,
        exit_point=exit_point, exit_normal=cuts[1].normal,
        fixed_vertices=fixed, annulus_vertices=np.unique(annulus_ids),
        annulus_center=np.zeros(3), root_axis=axis, ostia=ostia,
        ostium_vertices={k: int(wall_vertices[tree.query(o)[1]]) for k, o in ostia.items()},
        start_point=(start_lps - annulus_lps) * 1e-3, start_direction=start_dir)
    timings["landmarks"] = time.perf_counter() - t0
    notes.append(f"lumen: {len(vm)} vertices, {int(wall.sum())} wall faces, "
                 f"{len(cap_ids)} caps and the valve plane")
    figures = {"annulus_diameter_mm": 2e3 * math.sqrt(valve_area / math.pi),
               "arch_branches": float(len(arch_branches)),
               "exit_below_arch_mm": s_exit - _last_branch_arc(skel, apex, arch_branches)}
    return PreparedAnatomy(anatomy=anatomy, annulus_lps_mm=annulus_lps, cuts=cuts,
                           skeleton=skel, notes=notes, warnings=warnings, sources=sources,
                           timings=timings, annulus_uncertainty_mm=uncertainty,
                           figures=figures)

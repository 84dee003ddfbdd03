"""Synthetic CT label maps (and surface meshes) of the built-in aortas, with their truth.

There is no patient data to download, so the tests of ``prepare_anatomy`` run on label maps the
project makes: a built-in parametric aorta (:class:`~cgail_sim.anatomy.AortaGeometry`)
voxelised as a CT segmentation would give it:

* at CT spacing (default 0.84 x 0.84 x 1.0 mm, anisotropic) in a scanner frame: the NIfTI affine
  maps voxels to scanner RAS millimetres, with the voxel axes running towards L, P, S
  (``voxel_order="LPS"``, the DICOM order) or R, A, S (``"RAS"``), and the annulus at an
  arbitrary scanner position;
* with partial-volume noise: each voxel is lumen when the implicit field at its centre is below
  a random fraction of a voxel (normal, ``noise`` voxels standard deviation), so the boundary is
  jagged by about a voxel as in a thresholded segmentation;
* with long supra-aortic branches (``branch_length_mm`` beyond the arch wall) and a long
  descending aorta (``descending_length_mm`` below the arch), both open at the field of view as
  a real segmentation ends;
* optionally the whole aorta as TotalSegmentator and the AVT dataset give it
  (``abdominal=True``): below the descending aorta an abdominal aorta with a coeliac stub,
  two renal stubs and the iliac bifurcation into two common iliac arteries, so the label's
  lowest ends are iliacs and branches leave it far below the arch;
* the root ends at the annulus plane; an optional left-ventricle blob (an ellipsoid below the
  annulus, touching it) goes to a separate label map, as do optional coronary stubs (label 1
  left, 2 right; 10 mm beyond the sinus wall) which never belong to the aortic label.

:class:`SyntheticTruth` holds what the segmentation was made from: the landmarks in scanner RAS
millimetres and the distance to the true lumen wall, for round-trip tests.
:func:`synthetic_surface` gives the same lumen as a triangle surface (marching cubes of the
field at a fine spacing, optional vertex noise), in RAS or LPS millimetres.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass, field, replace
import functools
from pathlib import Path

import numpy as np

from cgail_patient import PatientError
from cgail_sim.anatomy import anatomy_params, AortaGeometry
from cgail_sim.cli_help import tool_parser

__all__ = [
    "LPS_FROM_RAS",
    "SyntheticCT",
    "SyntheticCTConfig",
    "SyntheticTruth",
    "make_synthetic_ct",
    "synthetic_surface",
]

#: Flips RAS to LPS (and back): the phantom frame's axes are LPS.
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0])

_VOXEL_ORDERS = ("LPS", "RAS")


@dataclass(frozen=True)
class SyntheticCTConfig:
    """How to voxelise a built-in aorta as a CT label map (validated in ``__post_init__``)."""

    anatomy: str = "default"
    """Built-in anatomy to voxelise (``default`` or ``elongated``)."""
    spacing_mm: tuple[float, float, float] = (0.84, 0.84, 1.0)
    """Voxel size along i, j, k in mm (a thoracic CTA); each in [0.3, 3.5] (3 mm slices are
    common in whole-aorta CTA)."""
    voxel_order: str = "LPS"
    """Directions of increasing i, j (k runs superior): ``LPS`` (DICOM order) or ``RAS``."""
    annulus_ras_mm: tuple[float, float, float] = (-18.0, 26.0, -642.0)
    """Scanner RAS position of the annulus centre, mm (anywhere in the scanner)."""
    branch_length_mm: float = 50.0
    """Length of the supra-aortic branches beyond the arch wall, mm; in [10, 60]."""
    descending_length_mm: float = 200.0
    """Length of the descending aorta below the arch, mm; in [50, 300]."""
    noise: float = 0.3
    """Standard deviation of the partial-volume noise, voxels; in [0, 1]."""
    lv: bool = True
    """Also make a left-ventricle label map (an ellipsoid touching the annulus)."""
    coronaries: bool = False
    """Also make a coronary label map (1 left, 2 right stub, outside the aortic label)."""
    seed: int = 0
    """Seed of the partial-volume noise."""
    abdominal: bool = False
    """Continue the label into the abdominal aorta, its coeliac and renal stubs and the iliac
    arteries (a whole-aorta label, :data:`ABDOMEN_MM`)."""

    def __post_init__(self) -> None:
        if len(self.spacing_mm) != 3 or not all(0.3 <= s <= 3.5 for s in self.spacing_mm):
            raise ValueError(f"spacing_mm must be 3 values in [0.3, 3.5] mm, found "
                             f"{self.spacing_mm!r}")
        if self.voxel_order not in _VOXEL_ORDERS:
            raise ValueError(f"voxel_order must be one of {_VOXEL_ORDERS}, found "
                             f"{self.voxel_order!r}")
        if not 10.0 <= self.branch_length_mm <= 60.0:
            raise ValueError(f"branch_length_mm must be in [10, 60], found "
                             f"{self.branch_length_mm!r}")
        if not 50.0 <= self.descending_length_mm <= 300.0:
            raise ValueError(f"descending_length_mm must be in [50, 300], found "
                             f"{self.descending_length_mm!r}")
        if not 0.0 <= self.noise <= 1.0:
            raise ValueError(f"noise must be in [0, 1] voxels, found {self.noise!r}")


@dataclass(frozen=True)
class SyntheticTruth:
    """What a synthetic label map was made from (scanner RAS millimetres)."""

    geometry: AortaGeometry
    """The parametric aorta (phantom frame, m)."""
    annulus_ras_mm: np.ndarray
    """(3,) scanner RAS position of the phantom origin (the annulus centre), mm."""
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    """``annulus_center``, ``left_ostium``, ``right_ostium`` (points, RAS mm) and
    ``root_axis`` (unit, RAS)."""

    def to_phantom(self, points_ras_mm: np.ndarray) -> np.ndarray:
        """RAS millimetres to phantom metres (LPS axes, annulus at the origin)."""
        p = np.asarray(points_ras_mm, dtype=float).reshape(-1, 3)
        return ((p - self.annulus_ras_mm) @ LPS_FROM_RAS.T) * 1e-3

    def to_ras(self, points_phantom_m: np.ndarray) -> np.ndarray:
        """Phantom metres to RAS millimetres."""
        p = np.asarray(points_phantom_m, dtype=float).reshape(-1, 3)
        return (p * 1e3) @ LPS_FROM_RAS.T + self.annulus_ras_mm

    def wall_distance_mm(self, points_ras_mm: np.ndarray) -> np.ndarray:
        """(P,) unsigned distance to the true aortic wall (no coronary stubs, root closed at
        the annulus plane), mm; approximate: the implicit field is a distance near the wall."""
        return np.abs(_aortic_field(self.geometry, self.to_phantom(points_ras_mm))) * 1e3


@dataclass(frozen=True)
class SyntheticCT:
    """A synthetic segmentation: label maps on one voxel grid and the truth."""

    aorta: np.ndarray
    """(I, J, K) uint8, 1 in the aortic lumen."""
    affine: np.ndarray
    """(4, 4) voxel index -> scanner RAS mm (the NIfTI affine)."""
    truth: SyntheticTruth
    lv: np.ndarray | None = None
    """(I, J, K) uint8, 1 in the left ventricle, or None."""
    coronary: np.ndarray | None = None
    """(I, J, K) uint8, 1 left and 2 right coronary stub, or None."""

    def write(self, out_dir: str | Path, stem: str = "synthetic") -> dict[str, Path]:
        """Write the label maps as NIfTI (``<stem>_aorta.nii.gz``, ``_lv``, ``_coronary``).

        Returns:
            ``{"aorta": path, "lv": path, "coronary": path}`` for the maps that exist.
        """
        import nibabel as nib

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths: dict[str, Path] = {}
        for key, data in (("aorta", self.aorta), ("lv", self.lv), ("coronary", self.coronary)):
            if data is None:
                continue
            img = nib.Nifti1Image(np.asarray(data, dtype=np.uint8), self.affine)
            img.header.set_xyzt_units("mm")
            img.set_qform(self.affine, code=1)
            img.set_sform(self.affine, code=1)
            path = out / f"{stem}_{key}.nii.gz"
            nib.save(img, path)
            paths[key] = path
        return paths


def _geometry(config: SyntheticCTConfig) -> AortaGeometry:
    params = replace(anatomy_params(config.anatomy),
                     branch_stub_length=config.branch_length_mm * 1e-3,
                     descending_length=config.descending_length_mm * 1e-3)
    return AortaGeometry(params)


def _root_cylinder(g: AortaGeometry, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(height along the root axis, distance from it) of phantom points, m."""
    h = pts @ g.axis
    rho = np.linalg.norm(pts - h[:, None] * g.axis, axis=1)
    return h, rho


def _aortic_field(g: AortaGeometry, pts: np.ndarray) -> np.ndarray:
    """The lumen without the coronary stubs, closed flat at the annulus plane (m, < 0 inside).

    Points further than 0.2 m from the spine are reported as 1 (outside)."""
    pts = np.asarray(pts, dtype=float).reshape(-1, 3)
    out = np.ones(len(pts))
    tubes = g.tubes
    near = g.tree.query(pts, distance_upper_bound=0.06)[0] < np.inf
    for tube in tubes:
        if tube.name.endswith("coronary"):
            continue
        rel = pts - tube.start
        t = np.clip(rel @ tube.direction, 0.0, tube.length)
        near |= np.linalg.norm(rel - t[:, None] * tube.direction, axis=1) < tube.radius + 0.02
    if not near.any():
        return out
    g.tubes = [t for t in tubes if not t.name.endswith("coronary")]
    try:
        f = g.field(pts[near])
    finally:
        g.tubes = tubes
    h, rho = _root_cylinder(g, pts[near])
    below = (rho < 0.03) & (h > -0.04)
    f[below] = np.maximum(f[below], -h[below])
    out[near] = f
    return out


#: The abdominal part of a whole-aorta label, mm: abdominal aorta length below the
#: descending aorta and its end radius; coeliac and renal stubs (height below the abdominal
#: aorta's start, length, radius); common iliacs (length, radius, angle from caudal, deg).
ABDOMEN_MM = {"aorta": (170.0, 8.5), "coeliac": (30.0, 25.0, 3.5), "renal": (70.0, 30.0, 3.0),
              "iliac": (90.0, 5.0, 25.0)}


def _capsule(pts: np.ndarray, a: np.ndarray, b: np.ndarray, ra: float, rb: float) -> np.ndarray:
    """Signed distance (about) to a cone-capped segment from ``a`` (radius ``ra``) to ``b``."""
    d = b - a
    t = np.clip((pts - a) @ d / float(d @ d), 0.0, 1.0)
    return np.asarray(np.linalg.norm(pts - (a + t[:, None] * d), axis=1) - (ra + t * (rb - ra)))


def _abdominal_field(g: AortaGeometry, pts: np.ndarray) -> np.ndarray:
    """The abdominal aorta, its coeliac and renal stubs and the common iliacs below the
    descending aorta's end (phantom m, < 0 inside): straight tubes, the aorta caudal along
    -S, the renals to the left and right, the coeliac anterior, the iliacs diverging."""
    mm = 1e-3
    top = g.spine[-1]
    r0 = 0.5 * g.p.descending_diameter
    length, r_end = ABDOMEN_MM["aorta"]
    caudal = np.array([0.0, 0.0, -1.0])
    bottom = top + length * mm * caudal
    f = _capsule(pts, top - 0.01 * caudal, bottom, r0, r_end * mm)
    h, ln, r = ABDOMEN_MM["coeliac"]
    at = top + h * mm * caudal
    f = np.minimum(f, _capsule(pts, at, at + (r0 + ln * mm) * np.array([0.0, -1.0, 0.0]),
                               r * mm, r * mm))
    h, ln, r = ABDOMEN_MM["renal"]
    at = top + h * mm * caudal
    for side in (-1.0, 1.0):
        f = np.minimum(f, _capsule(pts, at, at + (r0 + ln * mm) * np.array([side, 0.0, 0.0]),
                                   r * mm, r * mm))
    ln, r, ang = ABDOMEN_MM["iliac"]
    a = np.radians(ang)
    for side in (-1.0, 1.0):
        d = np.array([side * np.sin(a), 0.0, -np.cos(a)])
        f = np.minimum(f, _capsule(pts, bottom, bottom + ln * mm * d, r_end * mm, r * mm))
    return f


def _coronary_field(g: AortaGeometry, pts: np.ndarray, side: str) -> np.ndarray:
    """Stub of ``side``: 10 mm beyond the sinus wall, radius the ostium's (m, < 0 inside)."""
    tube = next(t for t in g.tubes if t.name == f"{side}_coronary")
    wall = float(np.linalg.norm(g.ostia[side] - tube.start))
    rel = pts - tube.start
    t = np.clip(rel @ tube.direction, 0.0, wall + 0.010)
    return np.asarray(np.linalg.norm(rel - t[:, None] * tube.direction, axis=1) - tube.radius)


def _lv_field(g: AortaGeometry, pts: np.ndarray) -> np.ndarray:
    """Left ventricle: an ellipsoid below the annulus touching it over more than the annulus
    (centre 25 mm below, semi-axes 30 mm along the root axis and 24 mm across); < 0 inside."""
    h, rho = _root_cylinder(g, pts)
    q = np.sqrt(((h + 0.025) / 0.030) ** 2 + (rho / 0.024) ** 2)
    return np.asarray(np.maximum(q - 1.0, h))


def _truth_landmarks(g: AortaGeometry, to_ras: np.ndarray,
                     annulus_ras: np.ndarray) -> dict[str, np.ndarray]:
    return {
        "annulus_center": annulus_ras.copy(),
        "left_ostium": to_ras @ (g.ostia["left"] * 1e3) + annulus_ras,
        "right_ostium": to_ras @ (g.ostia["right"] * 1e3) + annulus_ras,
        "root_axis": to_ras @ g.axis,
    }


def _sample_field(fn: Callable[[np.ndarray], np.ndarray], shape: tuple[int, ...],
                  to_phantom: Callable[[np.ndarray], np.ndarray], step: float,
                  coarse: int = 4) -> np.ndarray:
    """Field values at every voxel centre, exact near the zero set (coarse to fine).

    The field (m, about a distance near its zero set, Lipschitz ~1) is evaluated on every
    ``coarse``-th voxel, interpolated linearly, and evaluated exactly where the interpolation is
    within ``2 * coarse`` voxels (``step`` m each) of zero; elsewhere the interpolation stands.
    """
    from scipy.ndimage import map_coordinates

    axes = [np.arange(0, n + coarse - 1, coarse) for n in shape]
    cijk = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    cvals = fn(to_phantom(cijk.astype(float))).reshape(tuple(len(a) for a in axes))
    ijk = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"),
                   axis=-1).reshape(-1, 3)
    values = map_coordinates(cvals, (ijk / coarse).T, order=1, mode="nearest")
    band = np.flatnonzero(np.abs(values) < 2.0 * coarse * step)
    values[band] = fn(to_phantom(ijk[band].astype(float)))
    return np.asarray(values.reshape(shape))


def make_synthetic_ct(config: SyntheticCTConfig | None = None) -> SyntheticCT:
    """Voxelise a built-in aorta as a CT label map in a scanner frame (see the module doc).

    Returns:
        The label maps, the NIfTI affine and the truth.
    """
    cfg = config or SyntheticCTConfig()
    g = _geometry(cfg)
    annulus_ras = np.asarray(cfg.annulus_ras_mm, dtype=float)
    # Bounding box of the lumen, the LV and the coronary stubs (phantom m), plus a margin.
    pts = [g.spine]
    for tube in g.tubes:
        pts.append(np.stack([tube.start, tube.start + (tube.length + 0.01) * tube.direction]))
    pts.append(np.stack([-0.06 * g.axis]))
    if cfg.abdominal:
        length, _ = ABDOMEN_MM["aorta"]
        ln, _, ang = ABDOMEN_MM["iliac"]
        bottom = g.spine[-1] - length * 1e-3 * np.array([0.0, 0.0, 1.0])
        reach = (ln * 1e-3) * np.array([np.sin(np.radians(ang)), 0.06, np.cos(np.radians(ang))])
        pts.append(np.stack([bottom - reach * np.array([1, 1, 1]),
                             bottom + reach * np.array([1, 1, -1]),
                             g.spine[-1] + np.array([0.06, -0.06, 0.0]),
                             g.spine[-1] + np.array([-0.06, 0.0, 0.0])]))
    box = np.vstack(pts)
    lo = box.min(axis=0) - 0.03
    hi = box.max(axis=0) + 0.03
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    ras = (corners * 1e3) @ LPS_FROM_RAS.T + annulus_ras
    ras_lo, ras_hi = ras.min(axis=0), ras.max(axis=0)
    spacing = np.asarray(cfg.spacing_mm, dtype=float)
    signs = np.array([-1.0, -1.0, 1.0]) if cfg.voxel_order == "LPS" else np.ones(3)
    shape = np.ceil((ras_hi - ras_lo) / spacing).astype(int) + 1
    origin = np.where(signs > 0, ras_lo, ras_hi)
    # Snap the origin to the spacing grid so that voxel centres do not depend on the box.
    origin = np.round(origin / spacing) * spacing
    affine = np.eye(4)
    affine[:3, :3] = np.diag(signs * spacing)
    affine[:3, 3] = origin
    truth = SyntheticTruth(geometry=g, annulus_ras_mm=annulus_ras,
                           landmarks=_truth_landmarks(g, LPS_FROM_RAS, annulus_ras))

    def to_phantom(ijk: np.ndarray) -> np.ndarray:
        return truth.to_phantom(ijk * (signs * spacing) + origin)

    grid = tuple(int(n) for n in shape)
    step = float(spacing.max()) * 1e-3
    rng = np.random.default_rng(cfg.seed)
    threshold = rng.normal(0.0, cfg.noise, size=grid) * float(spacing.mean()) * 1e-3
    def aortic(p: np.ndarray) -> np.ndarray:
        f = _aortic_field(g, p)
        return np.minimum(f, _abdominal_field(g, p)) if cfg.abdominal else f

    aorta = (_sample_field(aortic, grid, to_phantom, step) < threshold).astype(np.uint8)
    lv = None
    if cfg.lv:
        lv_vals = _sample_field(lambda p: _lv_field(g, p), grid, to_phantom, step)
        lv = ((lv_vals < threshold) & (aorta == 0)).astype(np.uint8)
    coronary = None
    if cfg.coronaries:
        coronary = np.zeros(grid, dtype=np.uint8)
        for value, side in ((1, "left"), (2, "right")):
            vals = _sample_field(functools.partial(_coronary_field, g, side=side), grid,
                                 to_phantom, step)
            coronary[(vals < threshold) & (aorta == 0)] = value
    if not aorta.any():
        raise PatientError("expected a non-empty synthetic aorta, found no lumen voxel")
    return SyntheticCT(aorta=aorta, affine=affine, truth=truth, lv=lv, coronary=coronary)


def synthetic_surface(anatomy: str = "default", *, frame: str = "RAS", spacing_mm: float = 0.7,
                      noise_mm: float = 0.0, branch_length_mm: float = 50.0,
                      descending_length_mm: float = 200.0, seed: int = 0,
                      annulus_mm: tuple[float, float, float] = (-18.0, 26.0, -642.0),
                      ) -> tuple[np.ndarray, np.ndarray, SyntheticTruth]:
    """The synthetic lumen as a closed triangle surface in scanner millimetres.

    Marching cubes of the field (no coronary stubs, closed at the annulus and at the ends) on
    a ``spacing_mm`` grid, optionally with Gaussian vertex noise of ``noise_mm``.

    Args:
        anatomy: built-in anatomy name.
        frame: ``RAS`` or ``LPS``: the axes of the returned vertices.
        spacing_mm: marching-cubes grid spacing, mm.
        noise_mm: standard deviation of the vertex noise, mm (each axis).
        branch_length_mm: supra-aortic branch length beyond the arch wall, mm.
        descending_length_mm: descending aorta below the arch, mm.
        seed: seed of the vertex noise.
        annulus_mm: scanner position of the annulus centre, in ``frame``, mm.

    Returns:
        (vertices (N, 3) mm, faces (M, 3), truth); the truth's coordinates are RAS.
    """
    from skimage.measure import marching_cubes

    if frame not in _VOXEL_ORDERS:
        raise ValueError(f"frame must be one of {_VOXEL_ORDERS}, found {frame!r}")
    cfg = SyntheticCTConfig(anatomy=anatomy, branch_length_mm=branch_length_mm,
                            descending_length_mm=descending_length_mm, lv=False)
    g = _geometry(cfg)
    annulus = np.asarray(annulus_mm, dtype=float)
    annulus_ras = annulus if frame == "RAS" else LPS_FROM_RAS @ annulus
    truth = SyntheticTruth(geometry=g, annulus_ras_mm=annulus_ras,
                           landmarks=_truth_landmarks(g, LPS_FROM_RAS, annulus_ras))
    h = spacing_mm * 1e-3
    pts = [g.spine] + [np.stack([t.start, t.end]) for t in g.tubes]
    lo = np.vstack(pts).min(axis=0) - 0.02
    hi = np.vstack(pts).max(axis=0) + 0.02
    shape = tuple(int(n) for n in np.ceil((hi - lo) / h).astype(int) + 1)
    values = _sample_field(lambda p: _aortic_field(g, p), shape, lambda ijk: lo + h * ijk, h)
    # Close the open ends: the field stops at the grid; pad with outside samples.
    values = np.pad(values, 1, constant_values=1.0)
    verts, faces, _, _ = marching_cubes(values.astype(np.float32), 0.0)
    verts = (verts - 1.0) * h + lo                       # phantom m
    faces = faces[:, ::-1]                                # outward normals (field < 0 inside)
    rng = np.random.default_rng(seed)
    if noise_mm > 0.0:
        verts = verts + rng.normal(0.0, noise_mm * 1e-3, size=verts.shape)
    ras = truth.to_ras(verts)
    out = ras if frame == "RAS" else ras @ LPS_FROM_RAS.T
    return out, np.asarray(faces, dtype=np.int64), truth


def build_parser() -> argparse.ArgumentParser:
    """Command line of ``cgail synthetic-ct``: a synthetic CT label map or lumen surface.

    ``cgail synthetic-ct --out data/`` writes ``synthetic_aorta.nii.gz`` and
    ``synthetic_lv.nii.gz`` (``--coronaries``: ``synthetic_coronary.nii.gz``); ``--mesh RAS|LPS``
    writes ``synthetic_lumen.stl`` instead (``--noise-mm`` vertex noise). ``truth.yaml`` holds
    the landmarks the data were made from (scanner RAS, mm). Then ``cgail prepare-anatomy``
    turns it into a prepared anatomy::

        cgail synthetic-ct --out runs/ct --coronaries
        cgail prepare-anatomy runs/ct/synthetic_aorta.nii.gz --lv runs/ct/synthetic_lv.nii.gz \\
            --out runs/patients/synthetic
    """
    p = tool_parser("synthetic-ct", build_parser.__doc__, details=True,
                    description="Write a synthetic CT label map (or lumen surface) of a "
                                "built-in aorta, with the truth it was made from: test data "
                                "for cgail prepare-anatomy.")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--anatomy", default="default", help="built-in anatomy to voxelise")
    p.add_argument("--voxel-order", choices=_VOXEL_ORDERS, default="LPS",
                   help="directions of the voxel axes: L, P, S (the DICOM order) or R, A, S")
    p.add_argument("--spacing-mm", type=float, nargs=3, default=(0.84, 0.84, 1.0),
                   metavar=("X", "Y", "Z"),
                   help="voxel size along the three voxel axes, mm, each in [0.3, 3.5] "
                        "(default: 0.84 0.84 1.0)")
    p.add_argument("--no-lv", action="store_true", help="no left-ventricle label map")
    p.add_argument("--coronaries", action="store_true", help="also a coronary label map")
    p.add_argument("--abdominal", action="store_true",
                   help="the whole aorta: abdominal aorta, coeliac and renal stubs, iliacs")
    p.add_argument("--mesh", choices=_VOXEL_ORDERS, default=None,
                   help="write a lumen surface (STL) in this frame instead of label maps")
    p.add_argument("--noise-mm", type=float, default=0.0, help="vertex noise of --mesh, mm")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the partial-volume noise (and of --noise-mm)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cgail synthetic-ct``; returns the exit status."""
    import sys

    import yaml

    args = build_parser().parse_args(argv)
    try:
        if args.mesh:
            import trimesh

            v, f, truth = synthetic_surface(args.anatomy, frame=args.mesh,
                                            noise_mm=args.noise_mm, seed=args.seed)
            args.out.mkdir(parents=True, exist_ok=True)
            path = args.out / "synthetic_lumen.stl"
            trimesh.Trimesh(v, f, process=False).export(path)
            written = {"lumen": path}
        else:
            ct = make_synthetic_ct(SyntheticCTConfig(
                anatomy=args.anatomy, voxel_order=args.voxel_order,
                spacing_mm=tuple(args.spacing_mm), lv=not args.no_lv,
                coronaries=args.coronaries, seed=args.seed, abdominal=args.abdominal))
            written = ct.write(args.out)
            truth = ct.truth
    except (ValueError, PatientError) as exc:
        print(f"cgail synthetic-ct: error: {exc}", file=sys.stderr)
        return 2
    landmarks = {k: [round(float(x), 4) for x in np.asarray(v).ravel()]
                 for k, v in truth.landmarks.items()}
    (args.out / "truth.yaml").write_text(yaml.safe_dump(
        {"frame": "RAS", "units": "mm (root_axis: unit vector)", **landmarks},
        sort_keys=False))
    for key, path in written.items():
        print(f"cgail synthetic-ct: {key}: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

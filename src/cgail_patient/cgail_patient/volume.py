"""Inputs of ``prepare_anatomy`` as one binary lumen volume in patient LPS millimetres.

* :func:`read_label_image` reads a label map: NIfTI (``.nii`` / ``.nii.gz``, nibabel; the
  affine maps voxels to scanner RAS mm), NRRD (``.nrrd``, detached ``.nhdr``) or a 3D Slicer
  segmentation (``.seg.nrrd``, also multi-layer), pynrrd; the NRRD ``space`` (LPS, RAS, ...),
  ``space directions`` (any, also oblique and anisotropic) and ``space origin`` give the
  geometry. :meth:`LabelImage.select` picks the lumen by label value, Slicer segment name,
  TotalSegmentator class (:data:`TOTALSEG_CLASSES`) or a union of these;
  :func:`resample_mask` resamples it onto an isotropic grid aligned with the patient LPS axes
  (the ``phantom`` frame's axes) by shape-based interpolation (thick slices do not staircase).
  :func:`read_label_map` does both.
* :func:`read_surface` reads a closed surface mesh (STL / OBJ / PLY with trimesh, VTP with a
  small reader of VTK's XML PolyData, :func:`read_vtp`) given in RAS or LPS and in mm (or
  metres / cm with ``units``), and :func:`voxelize_surface` turns it into the same kind of
  volume.

Every failure is a :class:`~cgail_patient.PatientError` whose message names the file and
reads "expected ..., found ...".
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
import re
import struct
from typing import Any
import xml.etree.ElementTree as ET
import zlib

import numpy as np

from cgail_patient import PatientError

__all__ = [
    "FRAMES",
    "LABEL_MAP_SUFFIXES",
    "LPS_FROM_RAS",
    "MESH_SUFFIXES",
    "TOTALSEG_CLASSES",
    "UNITS",
    "LabelImage",
    "LabelVolume",
    "Segment",
    "SurfaceMesh",
    "default_spacing",
    "parse_label",
    "read_label_image",
    "read_label_map",
    "read_nifti",
    "read_nrrd",
    "read_surface",
    "resample_mask",
    "voxelize_surface",
]

#: Axis conventions a surface mesh may be given in.
FRAMES = ("RAS", "LPS")
#: Length units a surface mesh may be given in, and their size in mm.
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: Flips RAS to LPS (and back).
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0])

#: File names a surface mesh may have.
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".vtp")
#: File names a label map may have (``.seg.nrrd`` ends with ``.nrrd``).
LABEL_MAP_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".seg.nrrd", ".nhdr")


@dataclass
class LabelVolume:
    """A binary volume on an isotropic grid aligned with the patient LPS axes.

    Voxel ``(i, j, k)`` has its centre at ``origin + spacing * (i, j, k)`` (LPS mm).
    """

    mask: np.ndarray
    """(I, J, K) bool."""
    origin: np.ndarray
    """(3,) LPS mm of voxel (0, 0, 0)."""
    spacing: float
    """Voxel size, mm."""
    source: str
    """Where it came from (file and label), for messages."""

    def points(self, ijk: np.ndarray) -> np.ndarray:
        """LPS mm of voxel indices (P, 3)."""
        return np.asarray(self.origin + self.spacing * np.asarray(ijk, dtype=float))

    def indices(self, points: np.ndarray) -> np.ndarray:
        """Continuous voxel indices of LPS mm points (P, 3)."""
        return np.asarray((np.asarray(points, dtype=float) - self.origin) / self.spacing)


@dataclass
class SurfaceMesh:
    """A closed triangle surface in patient LPS millimetres."""

    vertices: np.ndarray
    """(N, 3) LPS mm."""
    faces: np.ndarray
    """(M, 3) int64, outward normals."""
    source: str


def _check_file(path: Path, suffixes: tuple[str, ...], what: str) -> None:
    name = path.name.lower()
    if not any(name.endswith(s) for s in suffixes):
        raise PatientError(f"expected a {what} ({', '.join(suffixes)}), found {path.name!r}")
    if not path.is_file():
        raise PatientError(f"expected an existing {what}, found no file at {path}")


def _check_affine(p: Path, affine: np.ndarray) -> None:
    """Refuse a singular affine or voxel sizes outside 0.1-5 mm (wrong units)."""
    if not np.all(np.isfinite(affine)):
        raise PatientError(f"expected a finite voxel-to-world affine in {p}, found "
                           "non-finite entries")
    if np.linalg.det(affine[:3, :3]) == 0.0:
        raise PatientError(f"expected an invertible voxel-to-world affine in {p}, found "
                           "determinant 0")
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    if not np.all((spacing >= 0.1) & (spacing <= 5.0)):
        raise PatientError(f"expected voxel sizes of 0.1-5 mm in {p}, found "
                           f"{', '.join(f'{s:.3g}' for s in spacing)} mm: wrong units?")


def _integer(data: np.ndarray) -> np.ndarray:
    if np.issubdtype(data.dtype, np.integer) or data.dtype == bool:
        return np.asarray(data)
    return np.rint(np.asarray(data, dtype=np.float64)).astype(np.int64)


def read_nifti(path: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(integer data (I, J, K), affine voxel -> RAS mm, notes) of a NIfTI file.

    Raises:
        PatientError: unreadable file, not 3-D, or an unusable affine.
    """
    import nibabel as nib

    p = Path(path)
    _check_file(p, (".nii", ".nii.gz"), "NIfTI label map")
    try:
        img: Any = nib.load(p)
        data = np.asanyarray(img.dataobj)
    except (OSError, ValueError, EOFError, zlib.error,
            nib.filebasedimages.ImageFileError) as err:
        raise PatientError(f"expected a readable NIfTI label map in {p}, found: {err}") from err
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise PatientError(f"expected a 3-D label map in {p}, found shape {data.shape}")
    notes: list[str] = []
    affine = np.asarray(img.affine, dtype=float)
    header = img.header
    qcode = int(header["qform_code"])
    scode = int(header["sform_code"])
    if qcode == 0 and scode == 0:
        notes.append(f"{p.name}: the NIfTI header has no orientation (qform and sform codes 0); "
                     "its voxel axes were taken as RAS: check the frame in the render")
    unit = header.get_xyzt_units()[0]
    scale = {"meter": 1000.0, "mm": 1.0, "micron": 1e-3, "unknown": 1.0}.get(unit, 1.0)
    if scale != 1.0:
        affine = affine.copy()
        affine[:3, :] *= scale
        notes.append(f"{p.name}: spatial units {unit}: converted to mm")
    _check_affine(p, affine)
    return _integer(data), affine, notes


# ------------------------------------------------------------------------------------------
# NRRD and 3D Slicer segmentations
# ------------------------------------------------------------------------------------------
#: NRRD ``space`` values this reader knows: the frame name of the world axes and the matrix
#: from them to patient LPS. ``scanner-xyz`` and ``3D-right-handed`` carry no anatomical
#: meaning; they are read as LPS (DICOM patient coordinates), with a note.
_NRRD_SPACES: dict[str, tuple[str, tuple[float, float, float]]] = {
    "left-posterior-superior": ("LPS", (1.0, 1.0, 1.0)),
    "right-anterior-superior": ("RAS", (-1.0, -1.0, 1.0)),
    "left-anterior-superior": ("LAS", (1.0, -1.0, 1.0)),
    "scanner-xyz": ("LPS", (1.0, 1.0, 1.0)),
    "3d-right-handed": ("LPS", (1.0, 1.0, 1.0)),
}
_NRRD_SPACE_ALIASES = {"lps": "left-posterior-superior", "ras": "right-anterior-superior",
                       "las": "left-anterior-superior"}
_NRRD_UNITS = {"mm": 1.0, "millimeter": 1.0, "millimetre": 1.0, "cm": 10.0, "m": 1000.0,
               "meter": 1000.0, "um": 1e-3, "micron": 1e-3}


@dataclass(frozen=True)
class Segment:
    """One segment of a 3D Slicer segmentation (``.seg.nrrd`` header ``SegmentN_*`` fields)."""

    name: str
    layer: int
    """Index along the list axis (0 for a 3-D file)."""
    value: int
    """Label value in its layer."""
    id: str


@dataclass
class LabelImage:
    """A label map as read from its file: integer labels on the file's own voxel grid."""

    data: np.ndarray
    """(L, I, J, K) integer labels, L layers (1 but for a multi-layer ``.seg.nrrd``)."""
    affine: np.ndarray
    """(4, 4) voxel (i, j, k) -> RAS mm."""
    frame: str
    """The file's world axes (``RAS`` for NIfTI, the NRRD ``space``), in which a user's point
    coordinates for this file are given."""
    to_lps: np.ndarray
    """(3, 3) from :attr:`frame` to patient LPS."""
    segments: list[Segment]
    """Named segments (3D Slicer); empty for a plain label map."""
    notes: list[str]
    path: Path
    kind: str
    """``NIfTI``, ``NRRD`` or ``3D Slicer segmentation``."""

    def select(self, label: str | int | None) -> tuple[np.ndarray, str]:
        """(bool (I, J, K) voxels of ``label``, its description for messages).

        ``label`` (see :func:`parse_label`): None (every non-zero voxel, or the only segment of
        a segmentation); a label value; a segment name; a TotalSegmentator class
        (``total:aorta``); several of these joined by commas (their union).

        Raises:
            PatientError: an unknown name or class, or no voxel of the label (the message
                lists what the file holds).
        """
        if label is None or (isinstance(label, str) and not label.strip()):
            if len(self.segments) > 1:
                raise PatientError(
                    f"expected --label to choose one of the {len(self.segments)} segments of "
                    f"{self.path.name}, found none: segments present: {self._segment_list()}")
            if self.segments:
                return self._select_one(self.segments[0].name)
            sel = np.any(self.data != 0, axis=0)
            if not sel.any():
                raise PatientError(f"expected non-zero voxels in {self.path}, found none "
                                   "(an empty label map)")
            return sel, "non-zero voxels"
        parts = [s.strip() for s in str(label).split(",")] if isinstance(label, str) \
            else [str(label)]
        sel = np.zeros(self.data.shape[1:], dtype=bool)
        names = []
        for part in parts:
            s, what = self._select_one(part)
            sel |= s
            names.append(what)
        return sel, " + ".join(names)

    def _segment_list(self) -> str:
        return ", ".join(f"{s.name!r} (layer {s.layer}, value {s.value})" if self.data.shape[0] > 1
                         else f"{s.name!r} (value {s.value})" for s in self.segments)

    def _values_present(self) -> str:
        present = np.unique(self.data)
        return ", ".join(str(int(v)) for v in present[:12]) + (" ..." if len(present) > 12
                                                                 else "")

    def _select_one(self, text: str) -> tuple[np.ndarray, str]:
        kind, layer, value, what = parse_label(text, self.segments, self.path.name)
        if layer is None and self.data.shape[0] > 1:
            raise PatientError(
                f"expected a segment name for the multi-layer segmentation {self.path.name} "
                f"({self.data.shape[0]} layers), found {kind} {text!r}: segments present: "
                f"{self._segment_list()}")
        sel = self.data[layer or 0] == value
        if not sel.any():
            listing = (f"segments present: {self._segment_list()}" if self.segments
                       else f"values present: {self._values_present()}")
            raise PatientError(f"expected voxels of {what} in {self.path}, found none "
                               f"({listing})")
        return sel, what

    def volume(self, label: str | int | None = None, *, spacing: float | None = None,
               margin_mm: float = 15.0,
               bbox_lps: tuple[np.ndarray, np.ndarray] | None = None) -> LabelVolume:
        """The voxels of ``label`` resampled by :func:`resample_mask`."""
        sel, what = self.select(label)
        source = self.path.name + ("" if label is None else f" ({what})")
        return resample_mask(sel, self.affine, spacing=spacing, margin_mm=margin_mm,
                             source=source, bbox_lps=bbox_lps)


#: The classes of TotalSegmentator's multi-label maps (``--ml``) that matter to
#: ``prepare_anatomy``, by task. From TotalSegmentator's own class map, ``class_map`` in
#: ``totalsegmentator/map_to_binary.py`` (github.com/wasserth/TotalSegmentator): the tasks
#: ``total`` (v2, the default), ``total_v1`` (v1) and ``heartchambers_highres``. The v2
#: ``total`` task has one ``heart`` class; its chambers are in ``heartchambers_highres``.
TOTALSEG_CLASSES: dict[str, dict[str, int]] = {
    "total": {"heart": 51, "aorta": 52, "brachiocephalic_trunk": 54,
              "subclavian_artery_right": 55, "subclavian_artery_left": 56,
              "common_carotid_artery_right": 57, "common_carotid_artery_left": 58,
              "iliac_artery_left": 65, "iliac_artery_right": 66},
    "total_v1": {"aorta": 7, "heart_myocardium": 44, "heart_atrium_left": 45,
                 "heart_ventricle_left": 46, "heart_atrium_right": 47,
                 "heart_ventricle_right": 48, "iliac_artery_left": 51,
                 "iliac_artery_right": 52},
    "heartchambers_highres": {"heart_myocardium": 1, "heart_atrium_left": 2,
                              "heart_ventricle_left": 3, "heart_atrium_right": 4,
                              "heart_ventricle_right": 5, "aorta": 6, "pulmonary_artery": 7},
}
_TOTALSEG_ALIASES = {"totalseg": "total"}


def parse_label(text: str, segments: Sequence[Segment] = (),
                where: str = "the label map") -> tuple[str, int | None, int, str]:
    """One ``--label`` choice as (kind, layer or None, value, description).

    ``text`` is a label value (``3``), a TotalSegmentator class ``TASK:CLASS`` (``total:aorta``,
    ``heartchambers_highres:heart_ventricle_left``; ``totalseg:`` is ``total:``) or the name
    (or ID) of one of ``segments`` (case-insensitive when unambiguous).

    Raises:
        PatientError: an unknown task, class or segment name (the message lists the choices).
    """
    t = text.strip()
    try:
        return "label value", None, int(t), f"label {int(t)}"
    except ValueError:
        pass
    if ":" in t:
        task, _, cls = t.partition(":")
        task = _TOTALSEG_ALIASES.get(task.strip().lower(), task.strip().lower())
        cls = cls.strip().lower()
        if task not in TOTALSEG_CLASSES:
            raise PatientError(f"expected a TotalSegmentator task ({', '.join(TOTALSEG_CLASSES)}"
                               f") before ':' in --label, found {t!r}")
        classes = TOTALSEG_CLASSES[task]
        if cls not in classes:
            hint = ""
            if cls in TOTALSEG_CLASSES["heartchambers_highres"] and task == "total":
                hint = (f": the v2 total task has only 'heart'; the chambers are in the "
                        f"heartchambers_highres task (heartchambers_highres:{cls})")
            raise PatientError(f"expected a {task} class ({', '.join(classes)}), found "
                               f"{cls!r}{hint}")
        return "TotalSegmentator class", None, classes[cls], f"{task}:{cls} = label {classes[cls]}"
    if not segments:
        raise PatientError(
            f"expected a label value, a TotalSegmentator class such as total:aorta, or a "
            f"segment name of a 3D Slicer .seg.nrrd, found {t!r} for {where}, which has no "
            "named segments")
    for match in (lambda s: s.name == t, lambda s: s.id == t,
                  lambda s: s.name.lower() == t.lower()):
        found = [s for s in segments if match(s)]
        if len(found) == 1:
            s = found[0]
            return "segment", s.layer, s.value, f"segment {s.name!r}"
    names = ", ".join(repr(s.name) for s in segments)
    raise PatientError(f"expected a segment name of {where} ({names}), found {t!r}")


def _nrrd_segments(header: dict[str, Any], n_layers: int, p: Path) -> list[Segment]:
    fields: dict[int, dict[str, str]] = {}
    for key, val in header.items():
        m = re.fullmatch(r"Segment(\d+)_(\w+)", str(key))
        if m:
            fields.setdefault(int(m.group(1)), {})[m.group(2)] = str(val)
    has_layers = any("Layer" in f for f in fields.values())
    segments = []
    for i in sorted(fields):
        f = fields[i]
        try:
            value = int(f.get("LabelValue", "1"))
            # Slicer < 4.11 stored one segment per layer with value 1 and no Layer field.
            layer = int(f["Layer"]) if has_layers else (i if n_layers == len(fields) else 0)
        except ValueError as err:
            raise PatientError(f"expected integer Segment{i}_LabelValue / _Layer in {p}, "
                               f"found: {err}") from err
        if not 0 <= layer < n_layers:
            raise PatientError(f"expected Segment{i}_Layer within the {n_layers} layer(s) of "
                               f"{p}, found {layer}")
        segments.append(Segment(name=f.get("Name", f"Segment_{i}"), layer=layer, value=value,
                                id=f.get("ID", f"Segment_{i}")))
    return segments


def read_nrrd(path: str | Path) -> LabelImage:
    """A NRRD label map (``.nrrd``, detached ``.nhdr``) or 3D Slicer segmentation (``.seg.nrrd``,
    also multi-layer: a leading list axis) with pynrrd.

    The world frame is the header's ``space`` (LPS, RAS or LAS; ``scanner-xyz`` is read as LPS),
    the voxel axes are the ``space directions`` (any, also oblique) from the ``space origin``
    (the first voxel's centre); ``space units`` other than mm are converted.

    Raises:
        PatientError: unreadable file, not 3-D (plus one list axis), an unknown space or an
            unusable geometry.
    """
    import nrrd

    p = Path(path)
    _check_file(p, (".nrrd", ".nhdr"), "NRRD label map")
    try:
        data, header = nrrd.read(str(p))
    except (nrrd.NRRDError, OSError, ValueError, EOFError, zlib.error, KeyError,
            IndexError) as err:
        raise PatientError(f"expected a readable NRRD label map in {p}, found: {err}") from err
    notes: list[str] = []
    data = np.asarray(data)
    dirs_raw = header.get("space directions")
    ndim = data.ndim
    if dirs_raw is not None:
        rows = [None if r is None or not np.all(np.isfinite(np.asarray(r, dtype=float)))
                else np.asarray(r, dtype=float) for r in dirs_raw]
    else:
        # No orientation: the domain axes step by their spacings along L, P, S in turn.
        spacings = np.asarray(header.get("spacings", [np.nan] * ndim), dtype=float)
        kinds = [str(k).lower() for k in header.get("kinds", ["domain"] * ndim)]
        rows = [None] * ndim
        domain = [k for k in range(ndim) if kinds[k] in ("domain", "space")]
        for n, k in enumerate(domain[:3]):
            rows[k] = np.eye(3)[n] * (spacings[k] if np.isfinite(spacings[k]) else 1.0)
        notes.append(f"{p.name}: the NRRD header has no space directions; its voxel axes were "
                     "taken as L, P, S with the header's spacings: check the frame in the render")
    spatial = [k for k in range(ndim) if rows[k] is not None]
    other = [k for k in range(ndim) if rows[k] is None]
    if len(spatial) != 3 or len(other) > 1 or (other and ndim != 4):
        raise PatientError(f"expected a 3-D label map (optionally with one list axis of "
                           f"segmentation layers) in {p}, found shape {data.shape} with "
                           f"{len(spatial)} space axes")
    data = np.moveaxis(data, other[0], 0) if other else data[None]
    space = str(header.get("space", "")).lower()
    space = _NRRD_SPACE_ALIASES.get(space, space).removesuffix("-time")
    if not space and dirs_raw is not None:
        space = "3d-right-handed"   # a bare "space dimension: 3"
        notes.append(f"{p.name}: the NRRD header names no space (only a space dimension)")
    if space not in _NRRD_SPACES and dirs_raw is not None:
        raise PatientError(f"expected a NRRD space of {', '.join(_NRRD_SPACES)} in {p}, found "
                           f"{header.get('space')!r}")
    frame, signs = _NRRD_SPACES.get(space, _NRRD_SPACES["left-posterior-superior"])
    if space in ("scanner-xyz", "3d-right-handed"):
        notes.append(f"{p.name}: NRRD space {space} has no anatomical axes; it was read as LPS "
                     "(DICOM patient coordinates): check the frame in the render")
    to_lps = np.diag(signs)
    # Columns: the steps of the voxel axes.
    dirs = np.stack([np.asarray(rows[k]) for k in spatial], axis=1)
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=float)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        origin = np.zeros(3)
    units = header.get("space units")
    if units is not None:
        scales = {_NRRD_UNITS.get(str(u).strip().lower()) for u in units}
        if None in scales or len(scales) != 1:
            raise PatientError(f"expected NRRD space units of {', '.join(_NRRD_UNITS)} in {p}, "
                               f"found {list(units)}")
        scale = scales.pop()
        if scale != 1.0:
            dirs, origin = dirs * scale, origin * scale
            notes.append(f"{p.name}: space units {units[0]}: converted to mm")
    affine_lps = np.eye(4)
    affine_lps[:3, :3] = to_lps @ dirs
    affine_lps[:3, 3] = to_lps @ origin
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ affine_lps
    _check_affine(p, affine)
    segments = _nrrd_segments(dict(header), data.shape[0], p)
    kind = "3D Slicer segmentation" if segments else "NRRD"
    return LabelImage(data=_integer(data), affine=affine, frame=frame,
                      to_lps=to_lps, segments=segments, notes=notes, path=p,
                      kind=kind)


def read_label_image(path: str | Path) -> LabelImage:
    """A NIfTI (``.nii``, ``.nii.gz``) or NRRD (``.nrrd``, ``.seg.nrrd``, ``.nhdr``) label map.

    Raises:
        PatientError: another suffix, or what :func:`read_nifti` / :func:`read_nrrd` refuse.
    """
    p = Path(path)
    _check_file(p, LABEL_MAP_SUFFIXES, "label map")
    if p.name.lower().endswith((".nrrd", ".nhdr")):
        return read_nrrd(p)
    data, affine, notes = read_nifti(p)
    return LabelImage(data=data[None], affine=affine, frame="RAS", to_lps=LPS_FROM_RAS.copy(),
                      segments=[], notes=notes, path=p, kind="NIfTI")


def read_label_map(path: str | Path, label: str | int | None = None, *,
                   spacing: float | None = None,
                   margin_mm: float = 15.0) -> tuple[LabelVolume, list[str]]:
    """The voxels of ``label`` as an isotropic LPS volume.

    Args:
        path: NIfTI or NRRD label map, or 3D Slicer segmentation.
        label: see :meth:`LabelImage.select`; None: every non-zero voxel (or the only segment).
        spacing: working voxel size, mm (default :func:`default_spacing`).
        margin_mm: empty margin kept around the lumen, mm.

    Returns:
        (the volume, notes for the report).

    Raises:
        PatientError: unreadable file, an unknown label, or no voxel of the label.
    """
    image = read_label_image(path)
    return image.volume(label, spacing=spacing, margin_mm=margin_mm), image.notes


def default_spacing(voxel_mm: np.ndarray) -> float:
    """Working voxel size for input voxels of these sides, mm: the smallest side, but not finer
    than a third of the largest (thick slices carry no detail finer than that across them),
    within [0.5, 1.0] mm."""
    v = np.asarray(voxel_mm, dtype=float)
    return float(np.clip(max(v.min(), v.max() / 3.0), 0.5, 1.0))


def _clipped_signed_distance(mask: np.ndarray, vox: np.ndarray, band: float,
                             chunk: int = 16) -> np.ndarray:
    """Signed distance (mm, negative inside) from each voxel centre of ``mask`` to the nearest
    voxel of the other kind, clipped to [-band, band].

    The Euclidean distance transforms run on chunks of ``chunk`` slices (axis 2), each cropped
    to its lumen's bounding box plus ``band``: a whole aorta fills a few per cent of its own
    bounding box.
    """
    from scipy.ndimage import distance_transform_edt

    out = np.full(mask.shape, band, dtype=np.float32)
    m = np.ceil(band / np.asarray(vox, dtype=float)).astype(int) + 1
    nk = mask.shape[2]
    for k0 in range(0, nk, chunk):
        k1 = min(k0 + chunk, nk)
        e0, e1 = max(k0 - m[2], 0), min(k1 + m[2], nk)
        sub = mask[:, :, e0:e1]
        rows = np.flatnonzero(sub.any(axis=(1, 2)))
        if not len(rows):
            continue
        cols = np.flatnonzero(sub.any(axis=(0, 2)))
        i0, i1 = max(rows[0] - m[0], 0), min(rows[-1] + m[0] + 1, mask.shape[0])
        j0, j1 = max(cols[0] - m[1], 0), min(cols[-1] + m[1] + 1, mask.shape[1])
        box = sub[i0:i1, j0:j1]
        d = distance_transform_edt(~box, sampling=vox)
        d -= distance_transform_edt(box, sampling=vox)
        # Exact within the band (every voxel within it lies in the box); beyond it the box
        # only overestimates the distance, which the clip removes.
        out[i0:i1, j0:j1, k0:k1] = np.clip(d[:, :, k0 - e0:k1 - e0], -band, band)
    return out


def resample_mask(sel: np.ndarray, affine_ras: np.ndarray, *, spacing: float | None = None,
                  margin_mm: float = 15.0, source: str = "label map",
                  bbox_lps: tuple[np.ndarray, np.ndarray] | None = None) -> LabelVolume:
    """Resample a binary voxel mask (affine to RAS mm) onto an isotropic LPS grid.

    Shape-based interpolation: the signed distance to the mask's boundary (in mm, on the input
    grid, so a 3 mm slice counts 3 mm), smoothed by half a voxel against the jagged boundary of
    a thresholded label, is interpolated linearly and the new mask is where it is negative.
    Between two thick slices the boundary then moves linearly from one slice's outline to the
    next, so an oblique vessel keeps its cross-section instead of a staircase, and the lumen
    ends about half a voxel beyond the last labelled voxel. Only the input's bounding box of
    the mask (plus 4 voxels) is transformed, and the interpolation runs only near the wall: a
    whole-aorta label of 512 x 666 x 190 voxels takes a few seconds.
    ``bbox_lps`` fixes the grid's extent (LPS mm corners); by default the mask's bounding box
    plus ``margin_mm``.
    """
    from scipy.ndimage import gaussian_filter, map_coordinates

    vox = np.linalg.norm(affine_ras[:3, :3], axis=0)
    h = default_spacing(vox) if spacing is None else float(spacing)
    affine_lps = np.diag([-1.0, -1.0, 1.0, 1.0]) @ affine_ras
    occupied = [np.flatnonzero(np.any(sel, axis=tuple(o for o in range(3) if o != ax)))
                for ax in range(3)]
    lo_i = np.array([o[0] for o in occupied])
    hi_i = np.array([o[-1] for o in occupied])
    if bbox_lps is None:
        corners = np.array([[a, b, c, 1.0] for a in (lo_i[0], hi_i[0])
                            for b in (lo_i[1], hi_i[1]) for c in (lo_i[2], hi_i[2])])
        world = (affine_lps @ corners.T).T[:, :3]
        lo = world.min(axis=0) - margin_mm
        hi = world.max(axis=0) + margin_mm
    else:
        lo, hi = (np.asarray(x, dtype=float) for x in bbox_lps)
    shape = tuple(int(n) for n in np.ceil((hi - lo) / h).astype(int) + 1)
    # The input's bounding box of the mask with 4 empty voxels around it (padded where the
    # mask touches the input's edge: the lumen ends there as at any other boundary).
    pad = 4
    crop = np.pad(sel[lo_i[0]:hi_i[0] + 1, lo_i[1]:hi_i[1] + 1, lo_i[2]:hi_i[2] + 1], pad)
    a = lo_i - pad
    # The field: the signed distance, clipped to 3 cell diagonals (no effect near the wall),
    # smoothed by half a voxel (as the partial-volume noise of a thresholded label).
    diag = float(np.linalg.norm(vox))
    sdf = gaussian_filter(_clipped_signed_distance(crop, vox, 3.0 * diag), 0.5, mode="nearest")
    # The field changes by at most 2 mm per mm between voxel centres (an inside and an outside
    # voxel are both within their distance of each other), so a point whose nearest input
    # voxel has a value beyond two cell diagonals has all 8 corners of its cell on that side:
    # it is decided from that voxel; only the points near the wall are interpolated (the same
    # result, faster).
    band = 2.002 * diag
    inv = np.linalg.inv(affine_lps)
    mask = np.zeros(shape, dtype=bool)
    # The input voxels that can make an output voxel lumen (inside or near the boundary), in
    # LPS mm sorted by z: each slab of output slices looks only at the rectangle they cover.
    near_ijk = np.argwhere(sdf <= band)
    world = (near_ijk + a) @ affine_lps[:3, :3].T + affine_lps[:3, 3]
    world = world[np.argsort(world[:, 2])]
    reach = 0.5 * float(vox.sum()) + h
    top = np.array(crop.shape) - 1
    slab = 2
    for k0 in range(0, shape[2], slab):
        k1 = min(k0 + slab, shape[2])
        s0, s1 = np.searchsorted(world[:, 2], [lo[2] + h * k0 - reach,
                                               lo[2] + h * (k1 - 1) + reach])
        if s0 == s1:
            continue
        w = world[s0:s1]
        i0, j0 = np.maximum(np.floor((w[:, :2].min(axis=0) - reach - lo[:2]) / h), 0)
        i1, j1 = np.minimum(np.ceil((w[:, :2].max(axis=0) + reach - lo[:2]) / h),
                            np.array(shape[:2]) - 1)
        sub = np.stack(np.meshgrid(np.arange(int(i0), int(i1) + 1),
                                   np.arange(int(j0), int(j1) + 1),
                                   np.arange(k0, k1), indexing="ij"), axis=-1)
        vidx = (lo + h * sub.reshape(-1, 3)) @ inv[:3, :3].T + inv[:3, 3] - a
        near = np.rint(vidx).astype(np.int64)
        cand = np.flatnonzero(np.all((near >= 0) & (near <= top), axis=1))
        n = near[cand]
        val = sdf[n[:, 0], n[:, 1], n[:, 2]]
        out = np.zeros(len(vidx), dtype=bool)
        out[cand[val < -band]] = True
        edge = cand[np.abs(val) <= band]
        if len(edge):
            out[edge] = map_coordinates(sdf, vidx[edge].T, order=1, mode="nearest") < 0.0
        mask[int(i0):int(i1) + 1, int(j0):int(j1) + 1, k0:k1] = out.reshape(sub.shape[:3])
    return LabelVolume(mask=mask, origin=np.asarray(lo, dtype=float), spacing=h, source=source)


# ------------------------------------------------------------------------------------------
# Surface meshes
# ------------------------------------------------------------------------------------------
def _vtp_array(node: ET.Element, appended: bytes | None, header_type: str,
               compressed: bool) -> np.ndarray:
    """One DataArray of a VTK XML file (ascii, base64 binary, or appended raw/base64)."""
    types = {"Float32": "<f4", "Float64": "<f8", "Int8": "<i1", "UInt8": "<u1",
             "Int16": "<i2", "UInt16": "<u2", "Int32": "<i4", "UInt32": "<u4",
             "Int64": "<i8", "UInt64": "<u8"}
    dtype = np.dtype(types[node.get("type", "Float32")])
    fmt = node.get("format", "ascii")
    if fmt == "ascii":
        return np.array((node.text or "").split(), dtype=dtype)
    hdr = np.dtype("<u8" if header_type == "UInt64" else "<u4")
    if fmt == "binary":
        raw = base64.b64decode("".join((node.text or "").split()))
    elif fmt == "appended" and appended is not None:
        raw = appended[int(node.get("offset", "0")):]
    else:
        raise ValueError(f"unsupported DataArray format {fmt!r}")
    if not compressed:
        n = int(np.frombuffer(raw[:hdr.itemsize], dtype=hdr)[0])
        return np.frombuffer(raw[hdr.itemsize:hdr.itemsize + n], dtype=dtype).copy()
    nblocks = int(np.frombuffer(raw[:hdr.itemsize], dtype=hdr)[0])
    head = np.frombuffer(raw[:hdr.itemsize * (3 + nblocks)], dtype=hdr)
    sizes = head[3:3 + nblocks]
    pos = hdr.itemsize * (3 + nblocks)
    chunks = []
    for size in sizes:
        chunks.append(zlib.decompress(raw[pos:pos + int(size)]))
        pos += int(size)
    return np.frombuffer(b"".join(chunks), dtype=dtype).copy()


def read_vtp(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of a VTK XML PolyData file (ascii, binary or appended data,
    optionally zlib-compressed, as 3D Slicer writes it); polygons with more than 3 corners are
    fanned.

    Ours, not a library's: meshio (5.3.5, the newest on PyPI) reads and writes VTK's legacy
    ``.vtk`` and XML ``.vtu`` (UnstructuredGrid) but not ``.vtp``: its XML reader refuses a
    PolyData file ("Expected type UnstructuredGrid, found PolyData", checked), and trimesh has
    no VTP reader either. The library that reads every VTP is VTK itself (``vtk``, or pyvista
    over it): the whole visualisation toolkit as a dependency for these 60 lines.

    Raises:
        ValueError: not a PolyData file or an encoding this reader does not know.
    """
    text = path.read_bytes()
    appended: bytes | None = None
    marker = text.find(b"<AppendedData")
    if marker >= 0:
        start = text.index(b"_", marker) + 1
        end = text.rindex(b"</AppendedData>")
        body = text[start:end].rstrip()
        root_el = ET.fromstring(text[:marker] + b"</VTKFile>")
        enc = None
        for el in ET.fromstring(text[marker:text.index(b">", marker) + 1] + b"</AppendedData>"
                                ).iter():
            enc = el.get("encoding")
        appended = base64.b64decode(body) if enc == "base64" else body
    else:
        root_el = ET.fromstring(text)
    if root_el.get("type") != "PolyData":
        raise ValueError(f"expected a VTKFile of type PolyData, found {root_el.get('type')!r}")
    header_type = root_el.get("header_type", "UInt32")
    compressed = root_el.get("compressor") is not None
    piece = root_el.find("PolyData/Piece")
    if piece is None:
        raise ValueError("expected PolyData/Piece, found none")
    pts_node = piece.find("Points/DataArray")
    polys = piece.find("Polys")
    if pts_node is None or polys is None:
        raise ValueError("expected Points and Polys, found "
                         f"{[c.tag for c in piece]}")
    verts = _vtp_array(pts_node, appended, header_type, compressed).reshape(-1, 3)
    arrays = {a.get("Name"): a for a in polys.findall("DataArray")}
    conn = _vtp_array(arrays["connectivity"], appended, header_type, compressed)
    offs = _vtp_array(arrays["offsets"], appended, header_type, compressed)
    tris: list[list[int]] = []
    start_i = 0
    for end_i in offs.tolist():
        poly = conn[start_i:end_i].tolist()
        tris.extend([poly[0], poly[k], poly[k + 1]] for k in range(1, len(poly) - 1))
        start_i = end_i
    return np.asarray(verts, dtype=float), np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def write_vtp(path: str | Path, vertices: np.ndarray, faces: np.ndarray,
              encoding: str = "binary") -> Path:
    """Write a triangle mesh as VTK XML PolyData (``ascii`` or base64 ``binary``), which 3D
    Slicer loads as a model (ours: see :func:`read_vtp` for why no library)."""
    p = Path(path)
    v = np.asarray(vertices, dtype="<f4").ravel()
    f = np.asarray(faces, dtype="<i8")
    conn = f.ravel()
    offs = 3 * np.arange(1, len(f) + 1, dtype="<i8")

    def arr(name: str, data: np.ndarray, vtype: str, comps: int = 1) -> str:
        extra = f' NumberOfComponents="{comps}"' if comps > 1 else ""
        if encoding == "ascii":
            body = " ".join(repr(x) for x in data.tolist())
        else:
            raw = data.tobytes()
            body = base64.b64encode(struct.pack("<Q", len(raw)) + raw).decode()
        return (f'<DataArray type="{vtype}" Name="{name}"{extra} format="{encoding}">'
                f"{body}</DataArray>")

    xml = ('<?xml version="1.0"?>\n<VTKFile type="PolyData" version="1.0" '
           'byte_order="LittleEndian" header_type="UInt64"><PolyData>'
           f'<Piece NumberOfPoints="{len(vertices)}" NumberOfPolys="{len(f)}">'
           f'<Points>{arr("Points", v, "Float32", 3)}</Points>'
           f'<Polys>{arr("connectivity", conn, "Int64")}{arr("offsets", offs, "Int64")}'
           "</Polys></Piece></PolyData></VTKFile>\n")
    p.write_text(xml)
    return p


def _open_edges(faces: np.ndarray) -> str:
    """What keeps a triangle surface from being closed, as text ("N open or non-manifold edges
    (H holes)"); "" when every edge is shared by exactly two faces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from cgail_sim.mesh_io import boundary_edges

    bad = boundary_edges(np.asarray(faces))
    if not len(bad):
        return ""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    border = uniq[cnt == 1]
    holes = 0
    if len(border):
        ids, inv = np.unique(border, return_inverse=True)
        inv = inv.reshape(-1, 2)
        graph = coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])),
                           shape=(len(ids), len(ids)))
        holes = connected_components(graph, directed=False)[0]
    return (f"{len(bad)} open or non-manifold edges ({holes} hole{'s' * (holes != 1)}, "
            f"{len(bad) - len(border)} non-manifold)")


def read_surface(path: str | Path, *, frame: str, units: str = "mm") -> SurfaceMesh:
    """A closed lumen surface in patient LPS mm.

    Args:
        path: STL, OBJ, PLY or VTP file.
        frame: the mesh's axes, ``RAS`` or ``LPS``.
        units: the mesh's length unit (``mm``, ``cm`` or ``m``).

    Raises:
        PatientError: unreadable file, not one closed surface, or a size that does not fit an
            adult aorta in the stated unit.
    """
    import trimesh

    p = Path(path)
    _check_file(p, MESH_SUFFIXES, "surface mesh")
    if frame not in FRAMES:
        raise PatientError(f"expected --frame {' or '.join(FRAMES)} for {p.name}, found "
                           f"{frame!r}")
    if units not in UNITS:
        raise PatientError(f"expected --units {', '.join(UNITS)}, found {units!r}")
    try:
        if p.suffix.lower() == ".vtp":
            v, f = read_vtp(p)
            mesh = trimesh.Trimesh(v, f, process=True)
        else:
            loaded = trimesh.load(p, force="mesh", process=True)
            if not isinstance(loaded, trimesh.Trimesh):
                raise ValueError(f"a {type(loaded).__name__}")
            mesh = loaded
    except (ValueError, OSError, KeyError, IndexError, ET.ParseError) as err:
        raise PatientError(f"expected a readable triangle mesh in {p}, found: {err}") from err
    if len(mesh.faces) == 0:
        raise PatientError(f"expected triangles in {p}, found none")
    mesh.merge_vertices()
    size = float(mesh.extents.max()) * UNITS[units]
    if not 60.0 <= size <= 600.0:
        guess = ("metres (try --units m)" if size < 1.0 else "centimetres (try --units cm)"
                 if size < 60.0 else "micrometres or a scanner scale")
        raise PatientError(
            f"expected an aorta 60-600 mm long in {p.name} ({units}), found a largest side of "
            f"{size:.4g} mm, which looks like {guess}")
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        areas = sorted((float(m.area) for m in parts), reverse=True)
        raise PatientError(
            f"expected one connected lumen surface in {p.name}, found {len(parts)} "
            f"(the two largest: {areas[0] / sum(areas):.0%} and {areas[1] / sum(areas):.0%} of "
            "the area): a gap in the segmentation or a stray island")
    if not mesh.is_watertight:
        raise PatientError(f"expected a closed (watertight) surface in {p.name}, found "
                           f"{_open_edges(np.asarray(mesh.faces))}: close the holes (e.g. with "
                           "pymeshfix) or export the segmentation as a closed surface")
    if mesh.volume < 0:
        mesh.invert()
    v = np.asarray(mesh.vertices, dtype=float) * UNITS[units]
    if frame == "RAS":
        v = v @ LPS_FROM_RAS.T
    return SurfaceMesh(vertices=v, faces=np.asarray(mesh.faces, dtype=np.int64),
                       source=f"{p.name} ({frame}, {units})")


def voxelize_surface(surface: SurfaceMesh, spacing: float = 0.75,
                     margin_mm: float = 15.0) -> LabelVolume:
    """Inside test of a closed surface at the voxel centres of an isotropic LPS grid.

    Rays along +z through every (i, j) column; a voxel is inside where an odd number of
    crossings lie below it (exact at the voxel centres, no staircase of the surface voxels).

    Raises:
        PatientError: the surface has holes (or non-manifold edges).
    """
    import trimesh

    open_edges = _open_edges(surface.faces)
    if open_edges:
        raise PatientError(f"expected a closed surface to voxelise from {surface.source}, found "
                           f"{open_edges}: the inside of an open surface is undefined")
    v = surface.vertices
    lo = v.min(axis=0) - margin_mm
    hi = v.max(axis=0) + margin_mm
    shape = tuple(int(n) for n in np.ceil((hi - lo) / spacing).astype(int) + 1)
    mesh = trimesh.Trimesh(v, surface.faces, process=False)
    ii, jj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    xy = lo[:2] + spacing * np.stack([ii.ravel(), jj.ravel()], axis=1)
    # Nudge the rays off the grid so that none runs exactly along an edge.
    origins = np.column_stack([xy + np.array([1.3e-4, 0.7e-4]), np.full(len(xy), lo[2] - 1.0)])
    keep = ((origins[:, 0] > v[:, 0].min()) & (origins[:, 0] < v[:, 0].max())
            & (origins[:, 1] > v[:, 1].min()) & (origins[:, 1] < v[:, 1].max()))
    rays = np.flatnonzero(keep)
    dirs = np.tile([0.0, 0.0, 1.0], (len(rays), 1))
    locs, ray_idx, _ = mesh.ray.intersects_location(origins[rays], dirs, multiple_hits=True)
    mask = np.zeros(shape, dtype=bool)
    z_axis = lo[2] + spacing * np.arange(shape[2])
    order = np.lexsort((locs[:, 2], ray_idx))
    ray_idx, zs = ray_idx[order], locs[order, 2]
    splits = np.flatnonzero(np.diff(ray_idx)) + 1
    for r, z in zip(np.split(ray_idx, splits), np.split(zs, splits), strict=True):
        if len(r) < 2:
            continue
        z = np.unique(np.round(z, 9))
        count = np.searchsorted(z, z_axis)
        col = rays[int(r[0])]
        mask[col // shape[1], col % shape[1]] = count % 2 == 1
    return LabelVolume(mask=mask, origin=lo, spacing=float(spacing), source=surface.source)

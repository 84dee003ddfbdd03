"""Inputs of ``prepare_anatomy`` as one binary lumen volume in patient LPS millimetres.

* :func:`read_label_map` reads a NIfTI label map (``.nii`` / ``.nii.gz``) with nibabel. The NIfTI
  affine maps voxels to scanner RAS millimetres (the NIfTI convention); the volume is resampled
  onto an isotropic grid aligned with the patient LPS axes (the ``phantom`` frame's axes).
* :func:`read_surface` reads a closed surface mesh (STL / OBJ / PLY with trimesh, VTP with a
  small reader of VTK's XML PolyData) given in RAS or LPS and in mm (or metres / cm with
  ``units``), and :func:`voxelize_surface` turns it into the same kind of volume.

Every failure is a :class:`~cgail_planner.patient.PatientError` whose message names the file and
reads "expected ..., found ...".
"""

from __future__ import annotations

import base64
from dataclasses import dataclass
from pathlib import Path
import struct
from typing import Any
import xml.etree.ElementTree as ET
import zlib

import numpy as np

from cgail_planner.patient import PatientError

__all__ = [
    "FRAMES",
    "LPS_FROM_RAS",
    "UNITS",
    "LabelVolume",
    "SurfaceMesh",
    "read_label_map",
    "read_surface",
    "voxelize_surface",
]

#: Axis conventions a surface mesh may be given in.
FRAMES = ("RAS", "LPS")
#: Length units a surface mesh may be given in, and their size in mm.
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: Flips RAS to LPS (and back).
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0])

_MESH_SUFFIXES = (".stl", ".obj", ".ply", ".vtp")


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
    except (OSError, ValueError, EOFError, nib.filebasedimages.ImageFileError) as err:
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
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    if not np.all(np.isfinite(affine)) or np.linalg.det(affine[:3, :3]) == 0.0:
        raise PatientError(f"expected an invertible voxel-to-world affine in {p}, found "
                           f"determinant 0")
    if not np.all((spacing >= 0.1) & (spacing <= 5.0)):
        raise PatientError(f"expected voxel sizes of 0.1-5 mm in {p}, found "
                           f"{', '.join(f'{s:.3g}' for s in spacing)} mm: wrong units?")
    if not np.issubdtype(data.dtype, np.integer):
        data = np.rint(np.asarray(data, dtype=np.float64))
    return np.asarray(data), affine, notes


def read_label_map(path: str | Path, label: int | None = None, *, spacing: float | None = None,
                   margin_mm: float = 15.0) -> tuple[LabelVolume, list[str]]:
    """The voxels of ``label`` (any non-zero value when None) as an isotropic LPS volume.

    Args:
        path: NIfTI file.
        label: label value of the aortic lumen; None: every non-zero voxel.
        spacing: working voxel size, mm (default: the smallest input voxel size, clamped to
            [0.5, 1.0] mm).
        margin_mm: empty margin kept around the lumen, mm.

    Returns:
        (the volume, notes for the report).

    Raises:
        PatientError: unreadable file, or no voxel of the label.
    """
    data, affine, notes = read_nifti(path)
    p = Path(path)
    sel = data != 0 if label is None else data == label
    what = "non-zero voxels" if label is None else f"voxels of label {label}"
    if not sel.any():
        present = np.unique(data)
        shown = ", ".join(str(int(v)) for v in present[:10]) + (" ..." if len(present) > 10
                                                                else "")
        raise PatientError(f"expected {what} in {p}, found none (values present: {shown})")
    vol = resample_mask(sel, affine, spacing=spacing, margin_mm=margin_mm,
                        source=f"{p.name}" + ("" if label is None else f" (label {label})"))
    return vol, notes


def resample_mask(sel: np.ndarray, affine_ras: np.ndarray, *, spacing: float | None = None,
                  margin_mm: float = 15.0, source: str = "label map",
                  bbox_lps: tuple[np.ndarray, np.ndarray] | None = None) -> LabelVolume:
    """Resample a binary voxel mask (affine to RAS mm) onto an isotropic LPS grid.

    The mask is smoothed by half a voxel (Gaussian) and interpolated linearly, so the
    resampled boundary follows the input's partial-volume boundary, not its staircase.
    ``bbox_lps`` fixes the grid's extent (LPS mm corners); by default the mask's bounding box
    plus ``margin_mm``.
    """
    from scipy.ndimage import gaussian_filter, map_coordinates

    vox = np.linalg.norm(affine_ras[:3, :3], axis=0)
    h = float(np.clip(vox.min(), 0.5, 1.0)) if spacing is None else float(spacing)
    affine_lps = np.diag([-1.0, -1.0, 1.0, 1.0]) @ affine_ras
    if bbox_lps is None:
        idx = np.argwhere(sel)
        lo_i, hi_i = idx.min(axis=0), idx.max(axis=0)
        corners = np.array([[a, b, c, 1.0] for a in (lo_i[0], hi_i[0])
                            for b in (lo_i[1], hi_i[1]) for c in (lo_i[2], hi_i[2])])
        world = (affine_lps @ corners.T).T[:, :3]
        lo = world.min(axis=0) - margin_mm
        hi = world.max(axis=0) + margin_mm
    else:
        lo, hi = bbox_lps
    shape = tuple(int(n) for n in np.ceil((hi - lo) / h).astype(int) + 1)
    # Work on the bounding box of the selection (plus a margin) of the input grid.
    idx = np.argwhere(sel)
    pad = int(np.ceil(3 + margin_mm / vox.min()))
    a = np.maximum(idx.min(axis=0) - pad, 0)
    b = np.minimum(idx.max(axis=0) + pad + 1, sel.shape)
    crop = gaussian_filter(sel[a[0]:b[0], a[1]:b[1], a[2]:b[2]].astype(np.float32), 0.5)
    inv = np.linalg.inv(affine_lps)
    mask = np.zeros(shape, dtype=bool)
    k_axis = lo[2] + h * np.arange(shape[2])
    ii, jj = np.meshgrid(lo[0] + h * np.arange(shape[0]), lo[1] + h * np.arange(shape[1]),
                         indexing="ij")
    for k0 in range(0, shape[2], 32):  # slabs keep the coordinate arrays small
        kk = k_axis[k0:k0 + 32]
        pts = np.stack([np.broadcast_to(ii[..., None], ii.shape + kk.shape),
                        np.broadcast_to(jj[..., None], jj.shape + kk.shape),
                        np.broadcast_to(kk, ii.shape + kk.shape)], axis=-1).reshape(-1, 3)
        vidx = pts @ inv[:3, :3].T + inv[:3, 3] - a
        val = map_coordinates(crop, vidx.T, order=1, mode="constant", cval=0.0)
        mask[:, :, k0:k0 + 32] = (val > 0.5).reshape(ii.shape + kk.shape)
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
    optionally zlib-compressed); polygons with more than 3 corners are fanned.

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
    """Write a triangle mesh as VTK XML PolyData (``ascii`` or base64 ``binary``)."""
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
    _check_file(p, _MESH_SUFFIXES, "surface mesh")
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
        from cgail_planner.sim.mesh_io import boundary_edges

        raise PatientError(
            f"expected a closed (watertight) surface in {p.name}, found "
            f"{len(boundary_edges(np.asarray(mesh.faces)))} open or non-manifold edges: close "
            "the holes (e.g. with pymeshfix) or export the segmentation as a closed surface")
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
    """
    import trimesh

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

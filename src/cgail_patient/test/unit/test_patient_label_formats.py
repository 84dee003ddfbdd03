"""prepare_anatomy's label-map readers: NRRD and 3D Slicer .seg.nrrd (any space, oblique and
anisotropic voxels, multi-layer), --label choices (values, segment names, TotalSegmentator
classes), thick-slice resampling, and their clear refusals."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import nibabel as nib
import nrrd
import numpy as np
import pytest
import trimesh

from cgail_patient import PatientError
from cgail_patient.volume import (
    default_spacing,
    read_label_image,
    read_label_map,
    resample_mask,
    SurfaceMesh,
    voxelize_surface,
)

_REPO = Path(__file__).resolve().parents[4]
_D18 = _REPO / "data" / "anatomies" / "avt" / "D18"


def _rotation(ax: float, az: float) -> np.ndarray:
    cx, sx, cz, sz = np.cos(ax), np.sin(ax), np.cos(az), np.sin(az)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return rz @ rx


def _ellipsoid_grid(dirs_lps: np.ndarray, origin_lps: np.ndarray, shape: tuple[int, int, int],
                    centre: np.ndarray, semi: np.ndarray, value: int = 1) -> np.ndarray:
    """Labels of the voxels (columns of ``dirs_lps``: the voxel steps in LPS mm) whose centre
    lies inside an LPS-axis-aligned ellipsoid."""
    ijk = np.indices(shape).reshape(3, -1).T
    p = origin_lps + ijk @ dirs_lps.T
    inside = (((p - centre) / semi) ** 2).sum(axis=1) < 1.0
    return (inside * value).reshape(shape).astype(np.uint8)


def _write_nrrd(path: Path, data: np.ndarray, dirs_lps: np.ndarray, origin_lps: np.ndarray, *,
                space: str = "left-posterior-superior", encoding: str = "gzip",
                extra: dict[str, Any] | None = None, detached: bool = False) -> Path:
    """Write ``data`` with its geometry given in LPS, expressed in ``space`` (LPS or RAS)."""
    flip = np.diag([-1.0, -1.0, 1.0]) if space == "right-anterior-superior" else np.eye(3)
    dirs = flip @ dirs_lps
    rows = dirs.T
    kinds = ["domain"] * 3
    if data.ndim == 4:
        rows = np.vstack([np.full((1, 3), np.nan), rows])
        kinds = ["list", *kinds]
    header = {"space": space, "space directions": rows, "space origin": flip @ origin_lps,
              "kinds": kinds, "encoding": encoding, **(extra or {})}
    nrrd.write(str(path), data, header, detached_header=detached)
    return path


_SHAPE = (60, 50, 14)
_VOX = np.diag([0.7, 0.7, 3.0])
_ORIGIN = np.array([-20.0, 15.0, -600.0])
_CENTRE = _ORIGIN + np.array([21.0, 17.0, 20.0])
_SEMI = np.array([14.0, 9.0, 13.0])


def _volume_mm3(vol: Any) -> float:
    return float(vol.mask.sum()) * vol.spacing ** 3


def _extent(vol: Any) -> tuple[np.ndarray, np.ndarray]:
    pts = vol.points(np.argwhere(vol.mask))
    return pts.min(axis=0), pts.max(axis=0)


# ------------------------------------------------------------------------------------------
# Geometry
# ------------------------------------------------------------------------------------------
def test_nrrd_lps_and_ras_space_give_the_same_lps_volume(tmp_path: Path) -> None:
    data = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE, _SEMI)
    lps, _ = read_label_map(_write_nrrd(tmp_path / "lps.nrrd", data, _VOX, _ORIGIN))
    ras, _ = read_label_map(_write_nrrd(tmp_path / "ras.nrrd", data, _VOX, _ORIGIN,
                                        space="right-anterior-superior"))
    assert lps.spacing == pytest.approx(1.0)      # 3 mm slices: a third of them
    assert np.allclose(lps.origin, ras.origin, atol=1e-6)
    assert np.array_equal(lps.mask, ras.mask)
    centre = lps.points(np.argwhere(lps.mask)).mean(axis=0)
    assert np.abs(centre - _CENTRE).max() < 0.5
    assert read_label_image(tmp_path / "ras.nrrd").frame == "RAS"
    assert read_label_image(tmp_path / "lps.nrrd").frame == "LPS"


def test_oblique_anisotropic_directions_keep_the_shape_in_lps(tmp_path: Path) -> None:
    dirs = _rotation(np.radians(25.0), np.radians(35.0)) @ np.diag([0.6, 0.8, 2.5])
    shape = (110, 90, 30)
    origin = _CENTRE - dirs @ (np.array(shape) / 2.0)
    data = _ellipsoid_grid(dirs, origin, shape, _CENTRE, _SEMI)
    vol, _ = read_label_map(_write_nrrd(tmp_path / "oblique.nrrd", data, dirs, origin))
    lo, hi = _extent(vol)
    # The ellipsoid's axes stay on L, P, S whatever the voxel axes (a transposed or ignored
    # direction matrix would swap or tilt them).
    assert hi - lo == pytest.approx(2.0 * _SEMI, abs=2.5)
    assert 0.5 * (lo + hi) == pytest.approx(_CENTRE, abs=1.0)
    assert _volume_mm3(vol) == pytest.approx(4.0 / 3.0 * np.pi * np.prod(_SEMI), rel=0.05)


def test_gzip_raw_and_detached_nrrd_read_the_same(tmp_path: Path) -> None:
    data = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE, _SEMI)
    gz = read_label_image(_write_nrrd(tmp_path / "a.nrrd", data, _VOX, _ORIGIN))
    raw = read_label_image(_write_nrrd(tmp_path / "b.nrrd", data, _VOX, _ORIGIN,
                                       encoding="raw"))
    nhdr = read_label_image(_write_nrrd(tmp_path / "c.nhdr", data, _VOX, _ORIGIN,
                                        encoding="raw", detached=True))
    for image in (raw, nhdr):
        assert np.array_equal(image.data, gz.data)
        assert np.allclose(image.affine, gz.affine)
    assert gz.kind == "NRRD" and gz.segments == []


def test_nrrd_space_units_in_metres_are_converted(tmp_path: Path) -> None:
    data = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE, _SEMI)
    mm = read_label_image(_write_nrrd(tmp_path / "mm.nrrd", data, _VOX, _ORIGIN))
    m = read_label_image(_write_nrrd(tmp_path / "m.nrrd", data, _VOX * 1e-3, _ORIGIN * 1e-3,
                                     extra={"space units": ["m", "m", "m"]}))
    assert np.allclose(m.affine, mm.affine)
    assert any("converted to mm" in n for n in m.notes)


def test_unknown_nrrd_space_refused_and_a_bare_space_read_as_lps(tmp_path: Path) -> None:
    data = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE, _SEMI)
    path = tmp_path / "odd.nrrd"
    nrrd.write(str(path), data, {"space": "3D-left-handed", "space directions": _VOX.T,
                                 "space origin": _ORIGIN, "kinds": ["domain"] * 3})
    with pytest.raises(PatientError, match=r"expected a NRRD space of left-posterior-superior"
                                           r".* in .*odd\.nrrd, found '3D-left-handed'"):
        read_label_image(path)
    nrrd.write(str(path), data, {"space dimension": 3, "space directions": _VOX.T,
                                 "space origin": _ORIGIN, "kinds": ["domain"] * 3})
    bare = read_label_image(path)
    lps = read_label_image(_write_nrrd(tmp_path / "lps.nrrd", data, _VOX, _ORIGIN))
    assert bare.frame == "LPS"
    assert np.allclose(bare.affine, lps.affine)
    assert any("no anatomical axes" in n for n in bare.notes)


def test_real_seg_nrrd_and_its_nifti_twin_give_the_same_volume() -> None:
    seg, seg_notes = read_label_map(_D18 / "D18.seg.nrrd", "aorta")
    nii, nii_notes = read_label_map(_D18 / "D18_aorta_label.nii.gz")
    assert seg.mask.shape == nii.mask.shape
    # The NIfTI affine is the NRRD's, stored in float32.
    assert np.abs(seg.origin - nii.origin).max() < 1e-3
    assert np.count_nonzero(seg.mask != nii.mask) <= 1e-5 * seg.mask.sum()
    assert seg.spacing == pytest.approx(2.98360492 / 3.0)
    # The AVT README gives 141 mL for this label.
    assert _volume_mm3(seg) / 1e3 == pytest.approx(141.0, rel=0.02)
    assert seg.source == "D18.seg.nrrd (segment 'aorta')"
    assert seg_notes == nii_notes == []


# ------------------------------------------------------------------------------------------
# 3D Slicer segmentations
# ------------------------------------------------------------------------------------------
def _two_segments() -> tuple[np.ndarray, dict[str, str]]:
    data = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE, _SEMI, value=1)
    lv = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE + np.array([0.0, 0.0, -20.0]),
                         np.array([8.0, 8.0, 9.0]), value=2)
    data = np.where(data > 0, data, lv)
    fields = {"Segment0_ID": "Segment_1", "Segment0_Name": "Aorta", "Segment0_LabelValue": "1",
              "Segment0_Layer": "0", "Segment1_ID": "Segment_2",
              "Segment1_Name": "left ventricle", "Segment1_LabelValue": "2",
              "Segment1_Layer": "0"}
    return data, fields


def test_seg_nrrd_segment_by_name_id_and_value(tmp_path: Path) -> None:
    data, fields = _two_segments()
    path = _write_nrrd(tmp_path / "two.seg.nrrd", data, _VOX, _ORIGIN, extra=fields)
    image = read_label_image(path)
    assert image.kind == "3D Slicer segmentation"
    assert [s.name for s in image.segments] == ["Aorta", "left ventricle"]
    by_name, what = image.select("Aorta")
    assert what == "segment 'Aorta'"
    assert np.array_equal(by_name, data == 1)
    assert np.array_equal(image.select("aorta")[0], by_name)       # case-insensitive
    assert np.array_equal(image.select("Segment_1")[0], by_name)   # segment ID
    assert np.array_equal(image.select("1")[0], by_name)           # label value
    assert np.array_equal(image.select(2)[0], data == 2)
    assert np.array_equal(image.select("Aorta, left ventricle")[0], data > 0)


def test_seg_nrrd_unknown_segment_lists_the_names(tmp_path: Path) -> None:
    data, fields = _two_segments()
    path = _write_nrrd(tmp_path / "two.seg.nrrd", data, _VOX, _ORIGIN, extra=fields)
    with pytest.raises(PatientError, match=r"expected a segment name of two\.seg\.nrrd "
                                           r"\('Aorta', 'left ventricle'\), found 'aortic'"):
        read_label_map(path, "aortic")
    with pytest.raises(PatientError, match=r"expected --label to choose one of the 2 segments "
                                           r"of two\.seg\.nrrd, found none: segments present: "
                                           r"'Aorta' \(value 1\), 'left ventricle' \(value 2\)"):
        read_label_map(path)


def test_multi_layer_seg_nrrd(tmp_path: Path) -> None:
    aorta = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE, _SEMI, value=1)
    # An overlapping segment in a second layer, with the same label value.
    lv = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE + np.array([0.0, 0.0, -8.0]),
                         np.array([8.0, 8.0, 9.0]), value=1)
    data = np.stack([aorta, lv])
    fields = {"Segment0_Name": "aorta", "Segment0_LabelValue": "1", "Segment0_Layer": "0",
              "Segment1_Name": "LV", "Segment1_LabelValue": "1", "Segment1_Layer": "1"}
    path = _write_nrrd(tmp_path / "layers.seg.nrrd", data, _VOX, _ORIGIN, extra=fields)
    image = read_label_image(path)
    assert image.data.shape == (2, *_SHAPE)
    assert np.array_equal(image.select("LV")[0], lv == 1)
    assert np.array_equal(image.select("aorta")[0], aorta == 1)
    assert (image.select("aorta")[0] & image.select("LV")[0]).any()
    with pytest.raises(PatientError, match=r"expected a segment name for the multi-layer "
                                           r"segmentation layers\.seg\.nrrd \(2 layers\), found "
                                           r"label value '1': segments present: 'aorta' "
                                           r"\(layer 0, value 1\), 'LV' \(layer 1, value 1\)"):
        image.select("1")
    vol, _ = read_label_map(path, "aorta")
    assert _volume_mm3(vol) == pytest.approx(4.0 / 3.0 * np.pi * np.prod(_SEMI), rel=0.05)


def test_old_slicer_layout_one_segment_per_layer(tmp_path: Path) -> None:
    """Slicer before 4.11: one layer per segment, value 1, no Layer / LabelValue fields."""
    a = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE, _SEMI)
    b = _ellipsoid_grid(_VOX, _ORIGIN, _SHAPE, _CENTRE, _SEMI * 0.5)
    path = _write_nrrd(tmp_path / "old.seg.nrrd", np.stack([a, b]), _VOX, _ORIGIN,
                       extra={"Segment0_Name": "aorta", "Segment1_Name": "core"})
    image = read_label_image(path)
    assert [(s.layer, s.value) for s in image.segments] == [(0, 1), (1, 1)]
    assert np.array_equal(image.select("core")[0], b == 1)


# ------------------------------------------------------------------------------------------
# Label choices: values and TotalSegmentator classes
# ------------------------------------------------------------------------------------------
def _multilabel_nifti(path: Path, values: dict[int, np.ndarray]) -> Path:
    data = np.zeros((20, 20, 20), dtype=np.uint8)
    for v, where in values.items():
        data[where] = v
    nib.save(nib.Nifti1Image(data, np.diag([-1.0, -1.0, 1.0, 1.0])), path)
    return path


def _box(i: int) -> np.ndarray:
    m = np.zeros((20, 20, 20), dtype=bool)
    m[2 + 4 * i:5 + 4 * i, 5:15, 5:15] = True
    return m


def test_totalsegmentator_classes_by_name(tmp_path: Path) -> None:
    # total (v2): heart 51, aorta 52; heartchambers_highres: heart_ventricle_left 3, aorta 6.
    total = read_label_image(_multilabel_nifti(tmp_path / "total.nii.gz",
                                               {51: _box(0), 52: _box(1), 7: _box(2)}))
    sel, what = total.select("total:aorta")
    assert what == "total:aorta = label 52"
    assert np.array_equal(sel, _box(1))
    assert np.array_equal(total.select("totalseg:aorta")[0], _box(1))
    assert np.array_equal(total.select("total:heart")[0], _box(0))
    assert np.array_equal(total.select("total_v1:aorta")[0], _box(2))
    assert np.array_equal(total.select("total:aorta,total:heart")[0], _box(0) | _box(1))
    chambers = read_label_image(_multilabel_nifti(tmp_path / "chambers.nii.gz",
                                                  {3: _box(0), 6: _box(1)}))
    assert np.array_equal(chambers.select("heartchambers_highres:heart_ventricle_left")[0],
                          _box(0))
    assert np.array_equal(chambers.select("heartchambers_highres:aorta")[0], _box(1))


def test_totalsegmentator_choice_refusals(tmp_path: Path) -> None:
    image = read_label_image(_multilabel_nifti(tmp_path / "total.nii.gz", {52: _box(1)}))
    with pytest.raises(PatientError, match=r"expected a total class .*, found "
                                           r"'heart_ventricle_left': the v2 total task has only "
                                           r"'heart'; the chambers are in the "
                                           r"heartchambers_highres task"):
        image.select("totalseg:heart_ventricle_left")
    with pytest.raises(PatientError, match=r"expected a TotalSegmentator task \(total, "
                                           r"total_v1, heartchambers_highres\) before ':'"):
        image.select("totalsegmentator:aorta")
    with pytest.raises(PatientError, match=r"expected voxels of heartchambers_highres:aorta = "
                                           r"label 6 in .*total\.nii\.gz, found none \(values "
                                           r"present: 0, 52\)"):
        image.select("heartchambers_highres:aorta")
    with pytest.raises(PatientError, match=r"expected a label value, a TotalSegmentator class "
                                           r"such as total:aorta, or a segment name of a 3D "
                                           r"Slicer \.seg\.nrrd, found 'aorta' for "
                                           r"total\.nii\.gz"):
        image.select("aorta")


def test_unknown_suffix_refused(tmp_path: Path) -> None:
    path = tmp_path / "aorta.mha"
    path.write_bytes(b"\0")
    with pytest.raises(PatientError, match=r"expected a label map \(\.nii, \.nii\.gz, \.nrrd, "
                                           r"\.seg\.nrrd, \.nhdr\), found 'aorta\.mha'"):
        read_label_image(path)


# ------------------------------------------------------------------------------------------
# Thick slices
# ------------------------------------------------------------------------------------------
def test_default_working_spacing() -> None:
    assert default_spacing(np.array([0.84, 0.84, 1.0])) == pytest.approx(0.84)
    assert default_spacing(np.array([0.55, 0.55, 3.0])) == pytest.approx(1.0)
    assert default_spacing(np.array([0.68, 0.68, 2.5])) == pytest.approx(2.5 / 3.0)
    assert default_spacing(np.array([0.3, 0.3, 0.3])) == pytest.approx(0.5)
    assert default_spacing(np.array([2.0, 2.0, 5.0])) == pytest.approx(1.0)


@pytest.mark.parametrize(("tilt", "limit_mm"), [((1.0, 0.0, 1.0), 0.15),
                                                ((1.0, 0.0, 0.27), 0.28)])
def test_oblique_tube_in_thick_slices_does_not_staircase(tilt: tuple[float, float, float],
                                                         limit_mm: float) -> None:
    """A tube at 45 and 75 degrees to 3 mm slices: the resampled lumen's mean distance from
    the true wall (the voxels that disagree with the true tube, per unit of wall area) is under
    0.15 / 0.28 mm at 1 mm voxels. Linearly interpolating the blurred label instead gives
    0.23 / 0.37 mm, nearest-neighbour 0.34 / 0.45 mm."""
    vox = np.array([0.6, 0.6, 3.0])
    radius = 10.0
    d = np.asarray(tilt) / np.linalg.norm(tilt)
    c0 = np.array([30.0, 12.0, 60.0])

    def inside(p: np.ndarray) -> np.ndarray:
        rel = p - c0
        return np.asarray(np.linalg.norm(rel - np.outer(rel @ d, d), axis=1) < radius)

    shape = (100, 40, 40)
    sel = inside(np.indices(shape).reshape(3, -1).T * vox).reshape(shape)
    # Voxel (i, j, k) at RAS (-0.6 i, -0.6 j, 3 k): LPS (0.6 i, 0.6 j, 3 k).
    vol = resample_mask(sel, np.diag([-vox[0], -vox[1], vox[2], 1.0]), spacing=1.0,
                        margin_mm=5.0)
    pts = vol.points(np.indices(vol.mask.shape).reshape(3, -1).T)
    keep = np.abs((pts - c0) @ d) < 15.0
    wrong = np.count_nonzero(vol.mask.ravel()[keep] != inside(pts[keep]))
    assert wrong * vol.spacing ** 3 / (2.0 * np.pi * radius * 30.0) < limit_mm


def test_lumen_ends_half_a_voxel_beyond_the_last_slice() -> None:
    """A label that reaches the edge of its grid ends there as anywhere else (no extrusion
    into the margin)."""
    sel = np.zeros((30, 30, 10), dtype=bool)
    sel[10:20, 10:20, :] = True     # through every slice
    vol = resample_mask(sel, np.diag([-1.0, -1.0, 3.0, 1.0]), spacing=1.0, margin_mm=10.0)
    lo, hi = _extent(vol)
    assert lo[2] == pytest.approx(-1.0, abs=0.6)
    assert hi[2] == pytest.approx(28.0, abs=0.6)


# ------------------------------------------------------------------------------------------
# Surfaces
# ------------------------------------------------------------------------------------------
def test_voxelize_refuses_a_surface_with_holes() -> None:
    tube = trimesh.creation.cylinder(radius=12.0, height=200.0, sections=48)
    keep = np.abs(tube.face_normals[:, 2]) < 0.5   # both end caps removed: two holes
    surface = SurfaceMesh(vertices=np.asarray(tube.vertices),
                          faces=np.asarray(tube.faces[keep]), source="open tube")
    with pytest.raises(PatientError, match=r"expected a closed surface to voxelise from open "
                                           r"tube, found 96 open or non-manifold edges \(2 "
                                           r"holes, 0 non-manifold\)"):
        voxelize_surface(surface)

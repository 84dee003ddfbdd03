"""prepare_anatomy's inputs: NIfTI label maps, surface meshes (STL/VTP), their clear refusals."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
import pytest
import trimesh

from cgail_patient import PatientError
from cgail_patient.prepare_cli import main
from cgail_patient.volume import (
    read_label_map,
    read_surface,
    read_vtp,
    voxelize_surface,
    write_vtp,
)


def _nifti(path: Path, data: np.ndarray, spacing: float = 1.0) -> Path:
    affine = np.diag([-spacing, -spacing, spacing, 1.0])
    nib.save(nib.Nifti1Image(data.astype(np.uint8), affine), path)
    return path


def _tube(length: float = 200.0, radius: float = 12.0) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=radius, height=length, sections=48)


def test_label_map_is_resampled_to_an_isotropic_lps_grid(tmp_path: Path) -> None:
    data = np.zeros((40, 40, 40), dtype=np.uint8)
    data[10:20, 15:25, 5:35] = 3
    path = _nifti(tmp_path / "box.nii.gz", data, spacing=1.0)
    vol, notes = read_label_map(path, label=3, margin_mm=5.0)
    assert vol.spacing == pytest.approx(1.0)
    # A 10 x 10 x 30 mm box: the resampled mask keeps its volume within a voxel layer.
    assert vol.mask.sum() == pytest.approx(3000, rel=0.15)
    # RAS voxel (10..19) along -x: LPS x = +10..+19.
    pts = vol.points(np.argwhere(vol.mask))
    assert pts[:, 0].min() == pytest.approx(10.0, abs=1.0)
    assert pts[:, 1].max() == pytest.approx(24.0, abs=1.0)
    assert notes == []


def test_empty_label_is_refused_with_the_values_present(tmp_path: Path) -> None:
    data = np.zeros((10, 10, 10), dtype=np.uint8)
    data[2:5, 2:5, 2:5] = 2
    path = _nifti(tmp_path / "seg.nii.gz", data)
    with pytest.raises(PatientError, match=r"expected voxels of label 1 in .*seg\.nii\.gz, "
                                           r"found none \(values present: 0, 2\)"):
        read_label_map(path, label=1)


def test_cli_empty_label_one_line_and_exit_2(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    path = _nifti(tmp_path / "empty.nii.gz", np.zeros((10, 10, 10), dtype=np.uint8))
    assert main([str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("cgail prepare-anatomy: error: expected non-zero voxels in ")
    assert not (tmp_path / "out").exists()


def test_cli_two_disconnected_components_refused(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    data = np.zeros((40, 40, 120), dtype=np.uint8)
    data[5:15, 5:15, 5:110] = 1
    data[25:35, 25:35, 5:110] = 1
    path = _nifti(tmp_path / "two.nii.gz", data)
    assert main([str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "expected one connected lumen in two.nii.gz, found 2 components" in err[0]
    assert not (tmp_path / "out").exists()


def test_cli_mesh_needs_a_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "tube.stl"
    _tube().export(path)
    assert main([str(path), "--out", str(tmp_path / "out")]) == 2
    assert "expected --frame RAS or --frame LPS for the surface mesh tube.stl" in \
        capsys.readouterr().err


def test_cli_open_mesh_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tube = _tube()
    keep = np.abs(tube.face_normals[:, 2]) < 0.5   # drop both end caps
    path = tmp_path / "open.stl"
    trimesh.Trimesh(tube.vertices, tube.faces[keep]).export(path)
    assert main([str(path), "--frame", "LPS", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert ("expected a closed (watertight) surface in open.stl, found 96 open or non-manifold "
            "edges (2 holes, 0 non-manifold)") in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["open.stl"]


def test_cli_mesh_in_metres_refused_with_the_hint(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "metres.stl"
    _tube(0.2, 0.012).export(path)
    assert main([str(path), "--frame", "RAS", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "found a largest side of 0.2 mm, which looks like metres (try --units m)" in err[0]


def test_two_surfaces_refused(tmp_path: Path) -> None:
    a = _tube()
    b = _tube().apply_translation([60.0, 0.0, 0.0])
    path = tmp_path / "two.stl"
    trimesh.util.concatenate([a, b]).export(path)
    with pytest.raises(PatientError, match=r"expected one connected lumen surface in two\.stl, "
                                           r"found 2 \(the two largest: 50% and 50%"):
        read_surface(path, frame="LPS")


def test_ras_surface_is_flipped_to_lps(tmp_path: Path) -> None:
    tube = _tube().apply_translation([30.0, -40.0, 0.0])
    path = tmp_path / "tube.ply"
    tube.export(path)
    ras = read_surface(path, frame="RAS")
    lps = read_surface(path, frame="LPS")
    assert ras.vertices.mean(axis=0)[:2] == pytest.approx([-30.0, 40.0], abs=0.5)
    assert lps.vertices.mean(axis=0)[:2] == pytest.approx([30.0, -40.0], abs=0.5)
    cm = read_surface(tmp_path / "tube.ply", frame="LPS", units="mm")
    assert cm.vertices.max() == pytest.approx(lps.vertices.max())


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_vtp_round_trip(tmp_path: Path, encoding: str) -> None:
    tube = _tube()
    path = write_vtp(tmp_path / f"tube_{encoding}.vtp", tube.vertices, tube.faces, encoding)
    v, f = read_vtp(path)
    assert np.array_equal(f, tube.faces)
    assert np.abs(v - tube.vertices).max() < 1e-4
    surf = read_surface(path, frame="LPS")
    assert surf.faces.shape == tube.faces.shape


def test_voxelised_surface_keeps_the_volume(tmp_path: Path) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    path = tmp_path / "sphere.stl"
    sphere.export(path)
    vol = voxelize_surface(read_surface(path, frame="LPS"), spacing=1.0, margin_mm=3.0)
    assert vol.mask.sum() == pytest.approx(sphere.volume, rel=0.01)
    centre = vol.points(np.argwhere(vol.mask)).mean(axis=0)
    assert np.abs(centre).max() < 0.2


@pytest.mark.slow
def test_synthetic_ct_console_script_writes_label_maps_and_meshes(tmp_path) -> None:
    import nibabel as nib
    import yaml

    from cgail_patient.synthetic import main

    assert main(['--out', str(tmp_path / 'ct'), '--coronaries']) == 0
    names = sorted(p.name for p in (tmp_path / 'ct').iterdir())
    assert names == ['synthetic_aorta.nii.gz', 'synthetic_coronary.nii.gz',
                     'synthetic_lv.nii.gz', 'truth.yaml']
    img: Any = nib.load(tmp_path / 'ct' / 'synthetic_aorta.nii.gz')
    assert img.header.get_zooms() == pytest.approx((0.84, 0.84, 1.0), abs=1e-6)
    truth = yaml.safe_load((tmp_path / 'ct' / 'truth.yaml').read_text())
    assert set(truth) >= {'annulus_center', 'left_ostium', 'right_ostium', 'root_axis'}
    assert main(['--out', str(tmp_path / 'mesh'), '--mesh', 'LPS', '--noise-mm', '0.3']) == 0
    assert (tmp_path / 'mesh' / 'synthetic_lumen.stl').stat().st_size > 1e6


def test_synthetic_ct_console_script_refuses_bad_options(tmp_path, capsys) -> None:
    from cgail_patient.synthetic import main

    assert main(['--out', str(tmp_path), '--spacing-mm', '0.1', '0.84', '1.0']) == 2
    assert 'spacing_mm must be 3 values in [0.3, 3.5] mm' in capsys.readouterr().err

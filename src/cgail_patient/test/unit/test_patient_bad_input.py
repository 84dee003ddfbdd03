"""prepare_anatomy on bad input, end to end through ``main``: one line on stderr, exit 2, and no
output directory (not even a half-written one), whatever step refuses.

(The empty label, two large components and a mesh with holes are in test_patient_inputs.py.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import nibabel as nib
import nrrd
import numpy as np
import pytest

from cgail_patient.prepare_cli import main
from cgail_patient.synthetic import make_synthetic_ct, SyntheticCTConfig

_REPO = Path(__file__).resolve().parents[4]
_D18 = _REPO / "data" / "anatomies" / "avt" / "D18"
_QUICK = ["--no-wall-check", "--no-expert-check"]


def refused(rc: int, capsys: pytest.CaptureFixture[str], out: Path) -> str:
    """The one stderr line of a refused input (exit 2, nothing written); returns it."""
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1, err
    assert err[0].startswith("cgail prepare-anatomy: error: expected ")
    assert not out.exists()
    assert not [p.name for p in out.parent.iterdir() if p.name.endswith(".partial")]
    return err[0]


def _nifti(path: Path, data: np.ndarray, affine: np.ndarray) -> Path:
    nib.save(nib.Nifti1Image(data.astype(np.uint8), affine), path)
    return path


def test_label_value_not_present_lists_the_values(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    data = np.zeros((12, 12, 12), dtype=np.uint8)
    data[2:5, 2:5, 2:5] = 52
    data[6:9, 6:9, 6:9] = 51
    path = _nifti(tmp_path / "total.nii.gz", data, np.diag([-1.0, -1.0, 1.0, 1.0]))
    out = tmp_path / "out"
    line = refused(main([str(path), "--label", "7", "--out", str(out), *_QUICK]), capsys, out)
    assert line.endswith("found none (values present: 0, 51, 52)")
    line = refused(main([str(path), "--label", "total:heart_ventricle_left", "--out", str(out),
                         *_QUICK]), capsys, out)
    assert "the chambers are in the heartchambers_highres task" in line


def test_unknown_segment_name_lists_the_segments(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    data = np.zeros((12, 12, 12), dtype=np.uint8)
    data[2:9, 2:9, 2:9] = 1
    path = tmp_path / "case.seg.nrrd"
    nrrd.write(str(path), data, {"space": "left-posterior-superior",
                                 "space directions": np.eye(3), "space origin": np.zeros(3),
                                 "kinds": ["domain"] * 3, "Segment0_Name": "aorta",
                                 "Segment0_LabelValue": "1", "Segment0_Layer": "0"})
    out = tmp_path / "out"
    line = refused(main([str(path), "--label", "LV", "--out", str(out), *_QUICK]), capsys, out)
    assert line.endswith("expected a segment name of case.seg.nrrd ('aorta'), found 'LV'")


def test_flipped_affine_of_a_real_case_refused(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """D18 with its S voxel axis reversed in the affine (the image mirrored head to foot)."""
    img: Any = nib.load(_D18 / "D18_aorta_label.nii.gz")
    affine = img.affine.copy()
    affine[:3, 2] *= -1.0
    path = _nifti(tmp_path / "D18_flipped.nii.gz", np.asanyarray(img.dataobj), affine)
    out = tmp_path / "out"
    line = refused(main([str(path), "--out", str(out), *_QUICK]), capsys, out)
    assert "the S axis is flipped" in line
    assert "D18_flipped.nii.gz" in line


@pytest.fixture(scope="module")
def coarse_ct(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    ct = make_synthetic_ct(SyntheticCTConfig(spacing_mm=(1.6, 1.6, 2.0),
                                             descending_length_mm=170.0))
    return ct.write(tmp_path_factory.mktemp("coarse_ct"))


def _moved(src: Path, dst: Path, shift_mm: tuple[float, float, float]) -> Path:
    img: Any = nib.load(src)
    affine = img.affine.copy()
    affine[:3, 3] += shift_mm
    return _nifti(dst, np.asanyarray(img.dataobj), affine)


def test_left_ventricle_not_touching_the_aorta_refused(
        coarse_ct: dict[str, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    lv = _moved(coarse_ct["lv"], tmp_path / "lv_low.nii.gz", (0.0, 0.0, -40.0))
    line = refused(main([str(coarse_ct["aorta"]), "--lv", str(lv), "--out", str(out),
                         "--voxel-mm", "1.2", *_QUICK]), capsys, out)
    assert "left-ventricle label to touch the aorta" in line
    far = _moved(coarse_ct["lv"], tmp_path / "lv_far.nii.gz", (0.0, 0.0, -400.0))
    line = refused(main([str(coarse_ct["aorta"]), "--lv", str(far), "--out", str(out),
                         "--voxel-mm", "1.2", *_QUICK]), capsys, out)
    assert line.endswith("expected left-ventricle voxels of lv_far.nii.gz within the aortic "
                         "label's bounding box (+15 mm), found none: not the same patient or "
                         "frame?")


def test_label_without_an_arch_refused(tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    """A straight tube, 190 mm long, in 3 mm slices."""
    vox = np.array([0.8, 0.8, 3.0])
    shape = (60, 60, 70)
    ijk = np.indices(shape).reshape(3, -1).T * vox
    r = np.linalg.norm(ijk[:, :2] - 24.0, axis=1)
    data = ((r < 12.0) & (ijk[:, 2] > 6.0) & (ijk[:, 2] < 200.0)).reshape(shape)
    path = _nifti(tmp_path / "tube.nii.gz", data, np.diag([-0.8, -0.8, 3.0, 1.0]))
    out = tmp_path / "out"
    line = refused(main([str(path), "--out", str(out), *_QUICK]), capsys, out)
    assert "expected an aortic arch in tube.nii.gz" in line


def test_bad_input_leaves_an_earlier_output_untouched(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "lumen.stl").write_text("earlier run")
    path = _nifti(tmp_path / "empty.nii.gz", np.zeros((8, 8, 8)), np.eye(4))
    assert main([str(path), "--out", str(out), *_QUICK]) == 2
    assert (out / "lumen.stl").read_text() == "earlier run"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.nii.gz", "out"]
    assert "expected non-zero voxels" in capsys.readouterr().err


def test_unknown_input_suffix_and_lv_label_for_a_mesh(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    out = tmp_path / "out"
    mha = tmp_path / "aorta.mha"
    mha.write_bytes(b"\0")
    line = refused(main([str(mha), "--out", str(out)]), capsys, out)
    assert line.endswith("expected a label map (.nii, .nii.gz, .nrrd, .seg.nrrd, .nhdr) or a "
                         "surface mesh (.stl, .obj, .ply, .vtp), found 'aorta.mha'")
    stl = tmp_path / "lumen.stl"
    stl.write_text("solid x\nendsolid x\n")
    line = refused(main([str(stl), "--frame", "LPS", "--lv-label", "3", "--out", str(out)]),
                   capsys, out)
    assert "expected --lv with --lv-label for the surface mesh lumen.stl" in line

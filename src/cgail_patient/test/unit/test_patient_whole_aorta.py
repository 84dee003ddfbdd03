"""``prepare_anatomy`` on whole-aorta labels: a real AVT case and a synthetic whole aorta.

Real labels break what the synthetic thoracic ones satisfy: they run down to the iliacs (whose
ends are narrower than the supra-aortic stubs and whose branches point caudally), their slices
are 3 mm thick, their root ends in an axial cut, and they have no left-ventricle label. The
anatomy must come from the shape: the arch is the trunk's cranial turn, its branches are the
ones leaving the top of it, and the descending cut lies a set length below them whatever the
label holds below.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
import re

import numpy as np
import pytest

from cgail_patient.prepare_cli import prepare_anatomy, PrepareResult
from cgail_patient.synthetic import make_synthetic_ct, SyntheticCT, SyntheticCTConfig

REPO = Path(__file__).resolve().parents[4]
D18 = REPO / "data" / "anatomies" / "avt" / "D18" / "D18.seg.nrrd"


def _note(result: PrepareResult, pattern: str) -> re.Match[str]:
    text = "\n".join(result.prepared.notes)
    m = re.search(pattern, text)
    assert m, f"no note matching {pattern!r} in:\n{text}"
    return m


@dataclass
class Whole:
    ct: SyntheticCT
    result: PrepareResult


@pytest.fixture(scope="module")
def synthetic_whole(tmp_path_factory: pytest.TempPathFactory) -> Whole:
    """A whole aorta (abdominal aorta, coeliac and renal stubs, iliacs) on 3 mm slices,
    without a left-ventricle label."""
    ct = make_synthetic_ct(SyntheticCTConfig(spacing_mm=(1.2, 1.2, 3.0), abdominal=True,
                                             lv=False, descending_length_mm=200.0))
    tmp = tmp_path_factory.mktemp("whole")
    paths = ct.write(tmp)
    result = prepare_anatomy([str(paths["aorta"]), "--out", str(tmp / "prepared"),
                              "--target-vertices", "1500", "--no-expert-check",
                              "--no-wall-check"])
    return Whole(ct, result)


def test_synthetic_whole_aorta_finds_the_arch_and_ignores_the_abdomen(
        synthetic_whole: Whole) -> None:
    r = synthetic_whole.result
    assert r.usable, [c.message for c in r.validation.errors]
    # The three supra-aortic stubs leave the arch; the coeliac, renal and iliac ends do not.
    assert _note(r, r"(\d+) supra-aortic branch\(es\) leaving it").group(1) == "3"
    assert int(_note(r, r"(\d+) other branch end\(s\)").group(1)) >= 3
    # The descending cut lies the asked 150 mm below the last arch branch, whatever follows.
    assert _note(r, r"descending cut (\d+) mm of centreline below").group(1) == "150"
    assert int(_note(r, r"the label continues (\d+) mm beyond").group(1)) > 200
    # the same figures, for tables (bench_real_patients)
    f = r.prepared.figures
    assert f["arch_branches"] == 3 and round(f["exit_below_arch_mm"]) == 150
    assert f["annulus_diameter_mm"] == pytest.approx(float(_note(
        r, r"equivalent diameter ([\d.]+) mm").group(1)), abs=0.06)


def test_synthetic_whole_aorta_landmarks_near_the_truth(synthetic_whole: Whole) -> None:
    r, truth = synthetic_whole.result, synthetic_whole.ct.truth.landmarks
    lps_from_ras = np.diag([-1.0, -1.0, 1.0])
    annulus = lps_from_ras @ r.prepared.annulus_lps_mm
    assert np.linalg.norm(annulus - truth["annulus_center"]) < 3.0
    axis_truth = lps_from_ras @ np.asarray(truth["root_axis"])
    cos = float(np.asarray(r.anatomy.root_axis) @ axis_truth)
    assert np.degrees(np.arccos(min(1.0, cos))) < 8.0
    # Square, flat root end: the annulus is the fitted end plane, a few mm uncertain.
    assert 0.0 < r.prepared.annulus_uncertainty_mm <= 5.0


@pytest.fixture(scope="module")
def real_d18(tmp_path_factory: pytest.TempPathFactory) -> PrepareResult:
    """AVT D18 (a real whole-aorta CTA label, 3 mm slices, no LV label) from its .seg.nrrd."""
    out = tmp_path_factory.mktemp("d18") / "prepared"
    return prepare_anatomy([str(D18), "--out", str(out), "--no-expert-check",
                            "--no-wall-check"])


def test_real_whole_aorta_is_prepared_from_its_shape(real_d18: PrepareResult) -> None:
    r = real_d18
    assert r.usable, [c.message for c in r.validation.errors]
    assert (r.out / "lumen.stl").is_file() and (r.out / "report.md").is_file()
    assert _note(r, r"(\d+) supra-aortic branch\(es\) leaving it").group(1) == "3"
    # The label runs on to the iliacs; the cut keeps 150 mm below the last arch branch, or
    # up to 100 mm more where D18's bending descending aorta leaves a straight introducer
    # against the wall at 150 mm.
    assert 150 <= int(_note(r, r"descending cut (\d+) mm of centreline below").group(1)) <= 250
    assert int(_note(r, r"the label continues (\d+) mm beyond").group(1)) > 100
    # The descending aorta lies posterior of the ascending aorta (phantom frame: LPS).
    a = r.anatomy
    assert float(a.start_point[1]) > 0.02
    # The end face is an axial cut oblique to the root: the annulus is found from the shape
    # and its uncertainty is said.
    assert r.prepared.annulus_uncertainty_mm >= 5.0
    assert "annulus uncertainty" in (r.out / "report.md").read_text() or any(
        "annulus uncertainty" in n for n in r.prepared.notes)
    for side in ("left", "right"):
        height = float(np.asarray(a.ostia[side]) @ np.asarray(a.root_axis)) * 1e3
        assert 5.0 <= height <= 30.0, (side, height)


def test_real_whole_aorta_descending_cut_at_root_level_no_exit_near_targets(
        real_d18: PrepareResult) -> None:
    """D18's descending cut lies below the annulus' level (a whole-aorta label cut 150 mm
    below the arch): the exit is the cut's disc, and no exit disc lies near a target."""
    a = real_d18.anatomy
    exit_height = float(np.asarray(a.exit_point) @ np.asarray(a.root_axis)) * 1e3
    assert exit_height < 25.0  # the cut's plane crosses the root's height
    scen = real_d18.validation.scenarios
    assert len(scen.targets) == 5
    discs = a.exit_discs
    for target in scen.targets:
        p = np.asarray(target.position)
        d = np.linalg.norm(discs[:, :3] - p[None], axis=1) - discs[:, 6]
        assert d.min() > 0.02, d

"""prepare_anatomy end to end: synthetic CT label maps and surface meshes in scanner frames in, a
prepared anatomy directory out that the simulator loads; landmarks and lumen against the truth.

The fast tests run on a coarse label map (1.6 mm voxels); the ``slow`` ones at CT spacing
(0.84 x 0.84 x 1.0 mm) and on 0.7 mm surface meshes, where the issue's tolerances apply:
landmarks within 2 mm, lumen within 1 mm (Hausdorff distance at the 95th percentile).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
import yaml

from cgail_patient.prepare_cli import main, prepare_anatomy, PrepareResult
from cgail_patient.synthetic import (
    LPS_FROM_RAS,
    make_synthetic_ct,
    synthetic_surface,
    SyntheticCTConfig,
    SyntheticTruth,
)
from cgail_sim.anatomy import load_anatomy_mesh
from cgail_sim.centerline import compute_centerlines
from cgail_sim.scenarios import build_scenarios, World


@dataclass
class Case:
    result: PrepareResult
    truth: SyntheticTruth
    branch_length_mm: float
    descending_length_mm: float
    anatomy: str = "default"


def _ras(result: PrepareResult, points_m: Any) -> np.ndarray:
    lps = np.asarray(points_m, dtype=float).reshape(-1, 3) * 1e3 + \
        result.prepared.annulus_lps_mm
    return lps @ LPS_FROM_RAS.T


def landmark_errors_mm(case: Case) -> dict[str, float]:
    """Distance of each recovered landmark from the truth, mm (root axis in degrees)."""
    a = case.result.anatomy
    t = case.truth.landmarks
    out = {key: float(np.linalg.norm(_ras(case.result, p)[0] - t[key]))
           for key, p in (("annulus_center", a.annulus_center),
                          ("left_ostium", a.ostia["left"]),
                          ("right_ostium", a.ostia["right"]))}
    cos = float((LPS_FROM_RAS @ a.root_axis) @ t["root_axis"])
    out["root_axis_deg"] = float(np.degrees(np.arccos(min(1.0, cos))))
    # The exit lies on the true descending centreline.
    out["exit_off_axis"] = float(case.truth.geometry.tree.query(
        case.truth.to_phantom(_ras(case.result, a.exit_point)))[0][0] * 1e3)
    return out


def hausdorff95_mm(case: Case) -> tuple[float, float]:
    """(prepared -> true wall, true wall -> prepared) 95th-percentile distances, mm; the true
    wall is sampled where the prepared lumen keeps it (not beyond the cuts)."""
    a = case.result.anatomy
    wall = trimesh.Trimesh(a.vertices, a.faces[a.wall_face_mask], process=False)
    pts = np.vstack([wall.sample(4000, seed=0), a.vertices])
    d_ab = case.truth.wall_distance_mm(_ras(case.result, pts))
    v, _, _ = synthetic_surface(case.anatomy, frame="RAS", spacing_mm=1.0,
                                    branch_length_mm=case.branch_length_mm,
                                    descending_length_mm=case.descending_length_mm,
                                    annulus_mm=tuple(case.truth.annulus_ras_mm))
    lps = v @ LPS_FROM_RAS.T
    keep = np.ones(len(lps), dtype=bool)
    for cut in case.result.prepared.cuts:
        rel = lps - cut.point
        ax = rel @ cut.normal
        rho = np.linalg.norm(rel - np.outer(ax, cut.normal), axis=1)
        keep &= ~((ax > -1.0) & (rho < cut.radius + 10.0))
    sample = lps[keep][:: max(1, int(keep.sum()) // 4000)]
    _, d_ba, _ = trimesh.proximity.closest_point(
        wall, case.result.prepared.to_phantom(sample))
    return float(np.percentile(d_ab, 95)), float(np.percentile(d_ba * 1e3, 95))


def _check_directory(case: Case) -> None:
    """The directory holds what the contract says, and the simulator loads it."""
    out = case.result.out
    for name in ("lumen.stl", "lumen.yaml", "report.md", "render.png", "prepare.yaml"):
        assert (out / name).is_file(), name
    anatomy = load_anatomy_mesh(out / "lumen.stl")
    record = yaml.safe_load((out / "prepare.yaml").read_text())
    assert record["anatomy"]["content_hash"] == anatomy.content_hash
    assert record["usable"] is True
    assert record["frame_conversion"]["R"] is not None
    lines = compute_centerlines(anatomy)
    scen = build_scenarios(anatomy, lines)
    assert len(scen.starts) == 3 and len(scen.targets) == 5
    report = (out / "report.md").read_text()
    assert "**Usable.**" in report
    assert "| check | result | value | limit |" in report
    assert "![render](render.png)" in report


# ------------------------------------------------------------------------------------------
# Fast: a coarse label map
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def coarse(tmp_path_factory: pytest.TempPathFactory) -> Case:
    ct = make_synthetic_ct(SyntheticCTConfig(spacing_mm=(1.6, 1.6, 2.0),
                                             descending_length_mm=170.0))
    tmp = tmp_path_factory.mktemp("coarse")
    paths = ct.write(tmp)
    # (the expert check's ~10 s run in test_patient_expert_check.py)
    result = prepare_anatomy([str(paths["aorta"]), "--lv", str(paths["lv"]), "--out",
                              str(tmp / "prepared"), "--voxel-mm", "1.2",
                              "--target-vertices", "1500", "--no-expert-check"])
    return Case(result, ct.truth, 50.0, 170.0)


def test_coarse_label_map_prepares_a_usable_directory(coarse: Case) -> None:
    assert coarse.result.usable, [c.message for c in coarse.result.validation.errors]
    _check_directory(coarse)
    assert 1200 <= len(coarse.result.anatomy.vertices) <= 1800


def test_coarse_label_map_landmarks_near_the_truth(coarse: Case) -> None:
    err = landmark_errors_mm(coarse)
    assert err["annulus_center"] < 2.0, err
    assert err["root_axis_deg"] < 5.0, err
    assert err["exit_off_axis"] < 2.0, err
    # Ostia estimated in the sinuses (no coronary map): said so in the report.
    assert err["left_ostium"] < 3.0 and err["right_ostium"] < 3.0, err
    assert coarse.result.prepared.sources["left_ostium"] == "estimated"
    assert "coronary ostia ESTIMATED" in (coarse.result.out / "report.md").read_text()


def test_prepared_anatomy_runs_in_the_static_env(coarse: Case,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from cgail_sim.config import EnvConfig
    import cgail_sim.env as env_mod

    anatomy = load_anatomy_mesh(coarse.result.out / "lumen.stl")
    lines = compute_centerlines(anatomy)
    world = World(anatomy, lines, build_scenarios(anatomy, lines))
    # Until EnvConfig takes a path (the name-or-path work), hand the env this world.
    monkeypatch.setattr(env_mod, "load_world", lambda *args: world)
    env = env_mod.CatheterNavEnv(EnvConfig())
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        obs, _, terminated, _, _ = env.step(np.array([0.0, 0.0, 1.0], dtype=np.float32))
        assert not terminated
    assert np.isfinite(obs).all()


# ------------------------------------------------------------------------------------------
# Slow: CT spacing and 0.7 mm meshes
# ------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("voxel_order, lv, coronaries",
                         [("LPS", True, True), ("RAS", False, False)])
def test_ct_label_map_round_trip(tmp_path: Path, voxel_order: str, lv: bool,
                                 coronaries: bool) -> None:
    ct = make_synthetic_ct(SyntheticCTConfig(voxel_order=voxel_order, lv=lv,
                                             coronaries=coronaries))
    paths = ct.write(tmp_path)
    args = [str(paths["aorta"]), "--out", str(tmp_path / "prepared")]
    if lv:
        args += ["--lv", str(paths["lv"])]
    if coronaries:
        args += ["--coronary", str(paths["coronary"])]
    case = Case(prepare_anatomy(args), ct.truth, 50.0, 200.0)
    assert case.result.usable, [c.message for c in case.result.validation.errors]
    _check_directory(case)
    err = landmark_errors_mm(case)
    assert max(err["annulus_center"], err["left_ostium"], err["right_ostium"],
               err["exit_off_axis"]) < 2.0, err
    assert err["root_axis_deg"] < 3.0, err
    assert max(hausdorff95_mm(case)) < 1.0
    source = "coronary label" if coronaries else "estimated"
    assert case.result.prepared.sources["right_ostium"] == source


@pytest.mark.slow
@pytest.mark.parametrize("frame", ["RAS", "LPS"])
def test_noisy_surface_mesh_round_trip(tmp_path: Path, frame: str) -> None:
    v, f, truth = synthetic_surface(frame=frame, noise_mm=0.3, seed=1)
    path = tmp_path / "lumen_scan.stl"
    trimesh.Trimesh(v, f, process=False).export(path)
    case = Case(prepare_anatomy([str(path), "--frame", frame, "--out",
                                 str(tmp_path / "prepared")]), truth, 50.0, 200.0)
    assert case.result.usable, [c.message for c in case.result.validation.errors]
    _check_directory(case)
    err = landmark_errors_mm(case)
    assert max(err["annulus_center"], err["left_ostium"], err["right_ostium"],
               err["exit_off_axis"]) < 2.0, err
    assert max(hausdorff95_mm(case)) < 1.0


@pytest.mark.slow
def test_mesh_in_lps_declared_ras_is_refused(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    v, f, _ = synthetic_surface(frame="LPS", spacing_mm=1.0)
    path = tmp_path / "lps.stl"
    trimesh.Trimesh(v, f, process=False).export(path)
    assert main([str(path), "--frame", "RAS", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "the x and y axes are flipped (LPS read as RAS, or RAS as LPS); check --frame" \
        in err[0]


@pytest.mark.slow
def test_absurd_ostium_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ct = make_synthetic_ct(SyntheticCTConfig(spacing_mm=(1.6, 1.6, 2.0)))
    paths = ct.write(tmp_path)
    far = ct.truth.landmarks["annulus_center"] + np.array([0.0, 0.0, 120.0])
    assert main([str(paths["aorta"]), "--out", str(tmp_path / "out"), "--left-ostium",
                 *map(str, far)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "expected the left ostium on the aortic wall (within 5 mm), found it" in err[0]

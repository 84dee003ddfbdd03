"""Mesh building blocks and user-mesh loading (millimetres, landmarks, clear errors)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from cgail_sim.anatomy import (
    Anatomy,
    AnatomyError,
    build_anatomy,
    load_anatomy_mesh,
    save_anatomy_mesh,
)
from cgail_sim.centerline import compute_centerlines
from cgail_sim.mesh_io import (
    clip_and_cap,
    marching_tetrahedra,
    MeshLoadError,
    read_mesh_mm,
    Remesher,
)

MM = 1e-3


def _sphere_field(r: float):
    return lambda p: np.linalg.norm(p, axis=1) - r


def _sphere_grid(r: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    ax = np.arange(-1.5 * r, 1.5 * r + h / 2, h)
    grid = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1)
    return _sphere_field(r)(grid.reshape(-1, 3)).reshape(grid.shape[:3]), np.full(3, ax[0])


@pytest.fixture(scope="module")
def default() -> Anatomy:
    return build_anatomy("default")


@pytest.fixture(scope="module")
def exported(default: Anatomy, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("mesh") / "aorta.stl"
    save_anatomy_mesh(default, path)
    return path


def test_marching_tetrahedra_sphere_is_closed_outward_and_accurate() -> None:
    values, origin = _sphere_grid(0.01, 0.001)
    v, f = marching_tetrahedra(values, origin, 0.001)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.euler_number == 2
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 0.01**3, rel=0.03)
    assert np.abs(np.linalg.norm(v, axis=1) - 0.01).max() < 2e-4


def test_remesher_reaches_target_edge_on_the_surface() -> None:
    values, origin = _sphere_grid(0.01, 0.001)
    v, f = marching_tetrahedra(values, origin, 0.001)
    field = _sphere_field(0.01)
    v2, f2 = Remesher(v, f, field, lambda p: np.full(len(p), 0.003)).run(iterations=4)
    mesh = trimesh.Trimesh(v2, f2, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert np.median(mesh.edges_unique_length) == pytest.approx(0.003, rel=0.15)
    assert np.abs(field(v2)).max() < 1e-6
    assert len(v2) < len(v) / 3


def test_clip_and_cap_closes_a_flat_end() -> None:
    v, f = marching_tetrahedra(*_sphere_grid(0.01, 0.001), 0.001)
    v, f = Remesher(v, f, _sphere_field(0.01), lambda p: np.full(len(p), 0.002)).run(3)
    point, normal = np.array([0.0, 0.0, 0.006]), np.array([0.0, 0.0, 1.0])
    v, f, kept, cap = clip_and_cap(v, f, point, normal, 0.012, 0.01, 0.002,
                                   _sphere_field(0.01))
    used = np.unique(f)
    mesh = trimesh.Trimesh(v[used], np.searchsorted(used, f), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert np.abs(v[cap, 2] - 0.006).max() < 1e-12
    rim = np.linalg.norm(v[cap, :2], axis=1).max()
    assert rim == pytest.approx(np.sqrt(0.01**2 - 0.006**2), abs=1e-6)
    assert len(kept) < len(f)


def test_round_trip_through_mm_stl_and_yaml(default: Anatomy, exported: Path) -> None:
    sidecar = yaml.safe_load(exported.with_suffix(".yaml").read_text())
    assert sidecar["units"] == "mm" and len(sidecar["caps"]) == 5
    loaded = load_anatomy_mesh(exported)
    assert loaded.name == "aorta"
    assert len(loaded.vertices) == len(default.vertices)
    assert loaded.mesh.volume == pytest.approx(default.mesh.volume, rel=1e-6)
    assert (~loaded.wall_face_mask).sum() == (~default.wall_face_mask).sum()
    assert len(loaded.fixed_vertices) == len(default.fixed_vertices)
    assert len(loaded.annulus_vertices) == len(default.annulus_vertices)
    for key in ("exit_point", "annulus_center", "start_point"):
        assert np.allclose(getattr(loaded, key), getattr(default, key), atol=1e-6)
    for key in ("exit_normal", "root_axis"):
        assert np.allclose(getattr(loaded, key), getattr(default, key), atol=1e-5)
    for side in ("left", "right"):
        assert np.allclose(loaded.ostia[side], default.ostia[side], atol=1e-6)
        v = loaded.vertices[loaded.ostium_vertices[side]]
        assert np.allclose(v, default.vertices[default.ostium_vertices[side]], atol=1e-6)


def test_landmarks_as_arguments_estimate_normals_and_centreline(default: Anatomy,
                                                                exported: Path) -> None:
    sidecar = yaml.safe_load(exported.with_suffix(".yaml").read_text())
    landmarks = {k: sidecar[k] for k in ("exit_point", "annulus_center", "left_ostium",
                                         "right_ostium", "caps")}
    loaded = load_anatomy_mesh(exported, landmarks, name="user")
    assert loaded.name == "user"
    assert np.allclose(loaded.exit_normal, default.exit_normal, atol=1e-6)
    assert np.allclose(loaded.root_axis, default.root_axis, atol=1e-6)
    assert loaded.contains(loaded.start_point[None])[0]
    lines = compute_centerlines(loaded)
    for side, line in lines.items():
        assert np.linalg.norm(line.points[-1] - loaded.ostia[side]) < 2 * MM
        assert loaded.contains(line.points).all()


def test_metres_and_centimetres_are_rejected(default: Anatomy, tmp_path: Path) -> None:
    for scale, unit in ((1.0, "metres"), (100.0, "centimetres")):
        path = tmp_path / f"aorta_{unit}.stl"
        trimesh.Trimesh(default.vertices * scale, default.faces).export(path)
        with pytest.raises(MeshLoadError, match=f"millimetres.*looks like {unit}"):
            read_mesh_mm(path)


def test_open_mesh_is_rejected(default: Anatomy, tmp_path: Path) -> None:
    path = tmp_path / "open.ply"
    trimesh.Trimesh(default.vertices * 1e3, default.faces[10:]).export(path)
    with pytest.raises(MeshLoadError, match="watertight"):
        read_mesh_mm(path)


def test_bad_files(tmp_path: Path) -> None:
    with pytest.raises(MeshLoadError, match=r"expected an \.stl, \.obj or \.ply file"):
        read_mesh_mm(tmp_path / "aorta.vtk")
    with pytest.raises(MeshLoadError, match="no file"):
        read_mesh_mm(tmp_path / "missing.stl")
    garbage = tmp_path / "garbage.obj"
    garbage.write_text("this is not a mesh\n")
    with pytest.raises(MeshLoadError):
        read_mesh_mm(garbage)


def test_missing_and_misplaced_landmarks(exported: Path, tmp_path: Path) -> None:
    sidecar = yaml.safe_load(exported.with_suffix(".yaml").read_text())
    partial = {k: sidecar[k] for k in ("exit_point", "annulus_center", "right_ostium")}
    with pytest.raises(MeshLoadError, match=r"missing.*'left_ostium'|'left_ostium'.*missing"):
        load_anatomy_mesh(exported, partial)
    far = dict(sidecar, left_ostium=[0.0, 0.0, -150.0])
    with pytest.raises(MeshLoadError, match="left_ostium must lie on the surface"):
        load_anatomy_mesh(exported, far)
    outside = dict(sidecar, start_point=[200.0, 0.0, 0.0])
    with pytest.raises(MeshLoadError, match="start_point must lie inside the lumen"):
        load_anatomy_mesh(exported, outside)
    bad = dict(sidecar, exit_point=[1.0, 2.0])
    with pytest.raises(MeshLoadError, match="exit_point must be 3 finite numbers"):
        load_anatomy_mesh(exported, bad)
    lone = tmp_path / "lone.stl"
    lone.write_bytes(exported.read_bytes())
    with pytest.raises(MeshLoadError, match="sidecar"):
        load_anatomy_mesh(lone)
    assert issubclass(MeshLoadError, AnatomyError) and issubclass(MeshLoadError, ValueError)

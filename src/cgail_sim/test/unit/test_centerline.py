"""Voronoi centrelines: inside the lumen, centred, from the descending aorta to each ostium."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cgail_sim.anatomy import Anatomy, ANATOMY_NAMES, anatomy_params, build_anatomy
from cgail_sim.centerline import (
    Centerline,
    CenterlineError,
    compute_centerlines,
    sample_wall,
)

MM = 1e-3


@pytest.fixture(scope="module", params=ANATOMY_NAMES)
def world(request: pytest.FixtureRequest) -> tuple[Anatomy, dict[str, Centerline]]:
    anatomy = build_anatomy(request.param)
    return anatomy, compute_centerlines(anatomy)


def test_two_branches_of_100_evenly_spaced_points(
        world: tuple[Anatomy, dict[str, Centerline]]) -> None:
    _, lines = world
    assert set(lines) == {"left", "right"}
    for branch, line in lines.items():
        assert line.branch == branch
        assert line.points.shape == (100, 3) and line.radii.shape == (100,)
        seg = np.linalg.norm(np.diff(line.points, axis=0), axis=1)
        assert seg.std() < 0.05 * seg.mean()
        assert 0.2 < line.length < 0.45


def test_inside_the_lumen_with_radius_consistent_with_wall_distance(
        world: tuple[Anatomy, dict[str, Centerline]]) -> None:
    anatomy, lines = world
    for line in lines.values():
        assert anatomy.contains(line.points).all()
        assert (line.radii > 0.0).all()
        # The inscribed radius is the distance to the wall (caps excluded), measured on the
        # mesh independently of the Voronoi samples.
        wall = trimesh.Trimesh(anatomy.vertices, anatomy.faces[anatomy.wall_face_mask],
                               process=False)
        dist = np.abs(trimesh.proximity.signed_distance(wall, line.points))
        assert np.allclose(line.radii, dist, atol=1.0 * MM)


def test_centred_in_the_descending_aorta_and_the_ascending_aorta(
        world: tuple[Anatomy, dict[str, Centerline]]) -> None:
    anatomy, lines = world
    p = anatomy_params(anatomy.name)
    for line in lines.values():
        # The first 20 waypoints run up the descending aorta with about its radius.
        assert np.median(line.radii[:20]) == pytest.approx(p.descending_diameter / 2,
                                                           abs=1.5 * MM)
        assert line.radii.max() < p.sinus_diameter / 2 + 1.0 * MM
        assert line.radii.max() > p.ascending_diameter / 2 - 2.0 * MM


def test_starts_in_the_descending_aorta_and_reaches_the_ostium(
        world: tuple[Anatomy, dict[str, Centerline]]) -> None:
    anatomy, lines = world
    for branch, line in lines.items():
        assert np.linalg.norm(line.points[0] - anatomy.start_point) < 5 * MM
        up = (line.points[5] - line.points[0]) @ anatomy.start_direction
        assert up > 0.0
        assert np.linalg.norm(line.points[-1] - anatomy.ostia[branch]) < 2 * MM
        # Over the arch: the highest waypoint is well above the annulus.
        assert (line.points[:, 2] - anatomy.annulus_center[2]).max() > 0.07
    # Both lines share the path up to the root and part only there.
    split = np.linalg.norm(lines["left"].points - lines["right"].points, axis=1)
    assert split[:80].max() < 3 * MM
    assert split[-1] > 15 * MM


def test_n_waypoints_and_validation(world: tuple[Anatomy, dict[str, Centerline]]) -> None:
    anatomy, _ = world
    lines = compute_centerlines(anatomy, n_waypoints=40)
    assert lines["left"].points.shape == (40, 3)
    with pytest.raises(ValueError, match="n_waypoints must be >= 10, found 3"):
        compute_centerlines(anatomy, n_waypoints=3)


def test_cached_per_anatomy(world: tuple[Anatomy, dict[str, Centerline]]) -> None:
    anatomy, lines = world
    again = compute_centerlines(anatomy)
    assert again["left"] is lines["left"]


def test_wall_samples_lie_on_wall_faces_only(world: tuple[Anatomy, dict[str, Centerline]]) -> None:
    anatomy, _ = world
    pts = sample_wall(anatomy, max_samples=2000)
    wall = trimesh.Trimesh(anatomy.vertices, anatomy.faces[anatomy.wall_face_mask],
                           process=False)
    _, dist, _ = trimesh.proximity.closest_point(wall, pts[::10])
    assert dist.max() < 1e-5


def test_unreachable_ostium_raises() -> None:
    # A closed tube plus a separate closed blob holding the "left ostium": no lumen path.
    tube = trimesh.creation.cylinder(radius=0.012, height=0.1, sections=24)
    tube = tube.subdivide().subdivide()
    blob = trimesh.creation.icosphere(subdivisions=2, radius=0.006)
    blob.apply_translation([0.05, 0.0, 0.0])
    verts = np.vstack([tube.vertices, blob.vertices])
    faces = np.vstack([tube.faces, blob.faces + len(tube.vertices)])
    z = np.array([0.0, 0.0, 1.0])
    anatomy = Anatomy(
        name="broken", vertices=verts, faces=faces,
        wall_face_mask=np.ones(len(faces), dtype=bool), exit_point=np.array([0.0, 0.0, -0.05]),
        exit_normal=-z, fixed_vertices=np.zeros(0, dtype=np.int64),
        annulus_vertices=np.zeros(0, dtype=np.int64), annulus_center=np.array([0, 0, 0.05]),
        root_axis=-z, ostia={"left": blob.vertices[0].copy(), "right": np.array([0.012, 0, 0.04])},
        ostium_vertices={"left": 0, "right": 0}, start_point=np.array([0.0, 0.0, -0.03]),
        start_direction=z)
    with pytest.raises(CenterlineError, match="left ostium to be reachable"):
        compute_centerlines(anatomy)

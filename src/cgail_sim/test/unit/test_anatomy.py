"""The parametric aorta: topology, orientation, landmarks and the ANATOMY.md dimensions."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh

from cgail_sim.anatomy import (
    Anatomy,
    ANATOMY_NAMES,
    anatomy_params,
    AnatomyError,
    AnatomyParams,
    AortaGeometry,
    build_anatomy,
    build_anatomy_from_params,
)
from cgail_sim.testing import curved_anatomy, CURVED_PARAMS

MM = 1e-3


@pytest.fixture(scope="module", params=ANATOMY_NAMES)
def anatomy(request: pytest.FixtureRequest) -> Anatomy:
    return build_anatomy(request.param)


@pytest.fixture(scope="module")
def default() -> Anatomy:
    return build_anatomy("default")


def _ray_radius(mesh: trimesh.Trimesh, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance from origin to the first wall hit along each direction."""
    origins = np.repeat(origin[None], len(directions), axis=0)
    locs, idx, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    dist = np.full(len(directions), np.nan)
    dist[idx] = np.linalg.norm(locs - origins[idx], axis=1)
    return dist


def _ring_directions(axis: np.ndarray, n: int = 24) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    e1 = np.cross(a, [0.0, 0.0, 1.0] if abs(a[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2


def _diameter_at(anatomy: Anatomy, geom: AortaGeometry, s: float) -> float:
    i = int(np.argmin(np.abs(geom.arc - s)))
    r = _ray_radius(anatomy.mesh, geom.spine[i], _ring_directions(geom.tangent[i]))
    return 2.0 * float(np.nanmean(r))


def test_types_and_shapes(anatomy: Anatomy) -> None:
    n, m = len(anatomy.vertices), len(anatomy.faces)
    assert anatomy.vertices.dtype == np.float64 and anatomy.vertices.shape == (n, 3)
    assert anatomy.faces.dtype == np.int64 and anatomy.faces.shape == (m, 3)
    assert anatomy.wall_face_mask.dtype == bool and anatomy.wall_face_mask.shape == (m,)
    assert anatomy.fixed_vertices.dtype == np.int64
    assert anatomy.annulus_vertices.dtype == np.int64
    for v in (anatomy.exit_normal, anatomy.root_axis, anatomy.start_direction):
        assert np.linalg.norm(v) == pytest.approx(1.0)
    assert set(anatomy.ostia) == {"left", "right"} == set(anatomy.ostium_vertices)
    assert 2000 <= n <= 4000


def test_watertight_outward_sphere_topology(anatomy: Anatomy) -> None:
    mesh = anatomy.mesh
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.volume > 0.0  # normals point out of the lumen
    assert mesh.euler_number == 2
    # Outward normals: a point just outside each wall face centre is outside the lumen.
    rng = np.random.default_rng(1)
    idx = rng.choice(np.flatnonzero(anatomy.wall_face_mask), 200, replace=False)
    centre = mesh.triangles_center[idx]
    normal = mesh.face_normals[idx]
    assert not anatomy.contains(centre + 0.5 * MM * normal).any()
    assert anatomy.contains(centre - 0.5 * MM * normal).all()


def test_triangle_quality_is_reasonably_uniform(anatomy: Anatomy) -> None:
    mesh = anatomy.mesh
    # Faces whose three vertices are prescribed (caps held fixed, valve plane moved rigidly)
    # never deform; the PBD wall sees the others.
    prescribed = np.zeros(len(anatomy.vertices), dtype=bool)
    prescribed[anatomy.fixed_vertices] = True
    prescribed[anatomy.annulus_vertices] = True
    free = ~prescribed[anatomy.faces].all(axis=1)
    min_angle = np.degrees(mesh.face_angles[free].min(axis=1))
    assert np.percentile(min_angle, 5) > 25.0
    assert min_angle.min() > 8.0
    edges = mesh.edges_unique_length
    assert np.median(edges) == pytest.approx(anatomy_params(anatomy.name).edge_length, rel=0.15)


def test_caps_are_flat_fixed_and_cover_the_six_open_ends(anatomy: Anatomy) -> None:
    caps = np.flatnonzero(~anatomy.wall_face_mask)
    cap_vertices = np.unique(anatomy.faces[caps])
    assert set(cap_vertices.tolist()) == set(anatomy.fixed_vertices.tolist())
    # Six caps: descending, three branches, two coronaries (vertex-connected components).
    sub = trimesh.Trimesh(anatomy.vertices, anatomy.faces[caps], process=False)
    assert len(sub.split(only_watertight=False)) == 6
    # The descending cap is the plane through exit_point normal to exit_normal.
    near = np.linalg.norm(anatomy.vertices[cap_vertices] - anatomy.exit_point, axis=1) < 0.02
    h = (anatomy.vertices[cap_vertices[near]] - anatomy.exit_point) @ anatomy.exit_normal
    assert np.abs(h).max() < 1e-9
    assert anatomy.exit_normal[2] < -0.99  # caudal
    assert not set(anatomy.fixed_vertices.tolist()) & set(anatomy.annulus_vertices.tolist())


def test_root_closed_by_flat_valve_plane_at_annulus_diameter(anatomy: Anatomy) -> None:
    p = anatomy_params(anatomy.name)
    ring = anatomy.vertices[anatomy.annulus_vertices] - anatomy.annulus_center
    assert np.abs(ring @ anatomy.root_axis).max() < 1e-9
    rim = np.linalg.norm(ring, axis=1).max()
    assert rim == pytest.approx(p.annulus_diameter / 2, abs=0.3 * MM)
    # The valve plane is wall (closed), not a cap.
    in_plane = np.isin(anatomy.faces, anatomy.annulus_vertices).all(axis=1)
    assert in_plane.sum() > 10 and anatomy.wall_face_mask[in_plane].all()
    c, a = anatomy.annulus_center, anatomy.root_axis
    assert anatomy.contains(np.array([c + 3 * MM * a]))[0]
    assert not anatomy.contains(np.array([c - 1 * MM * a]))[0]


def test_measured_lumen_diameters_match_parameters(anatomy: Anatomy) -> None:
    p = anatomy_params(anatomy.name)
    g = AortaGeometry(p)
    assert _diameter_at(anatomy, g, p.stj_height) == pytest.approx(p.stj_diameter, abs=1.2 * MM)
    mid_asc = 0.5 * (p.stj_height + p.annulus_to_brachiocephalic)
    assert _diameter_at(anatomy, g, mid_asc) == pytest.approx(p.ascending_diameter, abs=1.2 * MM)
    s_desc = g.s_exit - 0.015
    assert _diameter_at(anatomy, g, s_desc) == pytest.approx(p.descending_diameter,
                                                             abs=1.0 * MM)
    s_iso = g.s_branches["subclavian"] + 0.020
    assert _diameter_at(anatomy, g, s_iso) == pytest.approx(p.isthmus_diameter, abs=1.2 * MM)


def test_sinuses_of_valsalva_bulge_towards_their_cusps(anatomy: Anatomy) -> None:
    p = anatomy_params(anatomy.name)
    g = AortaGeometry(p)
    h = 0.5 * p.stj_height
    origin = anatomy.annulus_center + h * anatomy.root_axis
    cusp = np.array([np.cos(phi) * g.e1 + np.sin(phi) * g.e2 for phi in g.sinus_phis])
    commissure = np.array([np.cos(phi + np.pi / 3) * g.e1 + np.sin(phi + np.pi / 3) * g.e2
                           for phi in g.sinus_phis])
    r_cusp = _ray_radius(anatomy.mesh, origin, cusp)
    r_comm = _ray_radius(anatomy.mesh, origin, commissure)
    # Cusp directions: the sinus diameter; commissures: much narrower (three lobes).
    assert r_cusp.mean() * 2 == pytest.approx(p.sinus_diameter, abs=1.2 * MM)
    assert (r_cusp - r_comm).min() > 2.0 * MM


def test_coronary_ostia_heights_angle_orientation_and_openings(anatomy: Anatomy) -> None:
    p = anatomy_params(anatomy.name)
    a, c = anatomy.root_axis, anatomy.annulus_center
    rad = {}
    for side, height in (("left", p.left_ostium_height), ("right", p.right_ostium_height)):
        o = anatomy.ostia[side]
        assert (o - c) @ a == pytest.approx(height, abs=1e-6)
        v = anatomy.vertices[anatomy.ostium_vertices[side]]
        assert np.linalg.norm(v - o) < 3.0 * MM
        radial = (o - c) - ((o - c) @ a) * a
        rad[side] = radial / np.linalg.norm(radial)
        # An opening: 3 mm beyond the ostium, along the stub, is still lumen ...
        assert anatomy.contains(np.array([o + 3 * MM * rad[side]]))[0]
        # ... while 3 mm beyond the sinus wall 40 deg around the root is not.
        turned = np.cos(0.7) * rad[side] + np.sin(0.7) * np.cross(a, rad[side])
        wall = c + height * a + 0.0165 * turned
        assert not anatomy.contains(np.array([wall + 3 * MM * turned]))[0]
    angle = math.degrees(math.acos(float(rad["left"] @ rad["right"])))
    assert angle == pytest.approx(math.degrees(p.ostia_angle), abs=0.5)
    assert rad["right"][1] < -0.5          # right coronary: anterior (-y)
    assert rad["left"][0] > 0.3             # left coronary: towards the patient's left (+x)


def test_three_supra_aortic_branches_on_top_of_the_arch(anatomy: Anatomy) -> None:
    p = anatomy_params(anatomy.name)
    g = AortaGeometry(p)
    stubs = [t for t in g.tubes if not t.name.endswith("coronary")]
    assert [t.name for t in stubs] == ["brachiocephalic", "carotid", "subclavian"]
    for tube, dia in zip(stubs, (p.brachiocephalic_diameter, p.carotid_diameter,
                                 p.subclavian_diameter), strict=True):
        assert tube.direction[2] > 0.3      # cranial
        probe = tube.end - 0.008 * tube.direction
        assert anatomy.contains(probe[None])[0]
        r = _ray_radius(anatomy.mesh, probe, _ring_directions(tube.direction, 16))
        assert 2 * np.nanmean(r) == pytest.approx(dia, abs=0.8 * MM)
    # Spacing along the centreline between origins.
    s = g.s_branches
    assert s["carotid"] - s["brachiocephalic"] == pytest.approx(p.brachiocephalic_to_carotid)
    assert s["brachiocephalic"] == pytest.approx(p.annulus_to_brachiocephalic)


def test_start_and_exit_landmarks(anatomy: Anatomy) -> None:
    assert anatomy.contains(anatomy.start_point[None])[0]
    assert anatomy.start_direction[2] > 0.95
    assert not anatomy.contains((anatomy.exit_point + 2 * MM * anatomy.exit_normal)[None])[0]
    assert anatomy.contains((anatomy.exit_point - 2 * MM * anatomy.exit_normal)[None])[0]
    assert 0.01 < (anatomy.start_point - anatomy.exit_point) @ -anatomy.exit_normal < 0.05


def test_the_two_built_in_anatomies_differ_clearly() -> None:
    d, e = build_anatomy("default"), build_anatomy("elongated")
    top = {a.name: (a.vertices - a.annulus_center) @ np.array([0.0, 0.0, 1.0]) for a in (d, e)}
    # Elongated: higher arch (deeper, longer ascending aorta) by more than 15 mm.
    assert top["elongated"].max() - top["default"].max() > 0.015
    # Narrower arch: horizontal distance ascending (arch start) -> descending.
    gd, ge = AortaGeometry(anatomy_params("default")), AortaGeometry(anatomy_params("elongated"))
    width = {n: float(np.linalg.norm((g.exit_point - g.spine[np.argmin(np.abs(g.arc - p))])[:2]))
             for n, g, p in (("default", gd, 0.05), ("elongated", ge, 0.068))}
    assert width["default"] - width["elongated"] > 0.006
    assert e.mesh.volume > 1.1 * d.mesh.volume


def test_build_is_cached_and_read_only(default: Anatomy) -> None:
    assert build_anatomy("default") is default
    with pytest.raises(ValueError):
        default.vertices[0, 0] = 1.0


def test_unknown_anatomy_name() -> None:
    with pytest.raises(AnatomyError, match="anatomy must be one of"):
        build_anatomy("giraffe")


@pytest.mark.parametrize(("field", "value"), [
    ("annulus_diameter", 0.005),
    ("sinus_diameter", 0.2),
    ("stj_height", -0.01),
    ("arch_width", 0.5),
    ("carotid_angle", 2.0),
    ("edge_length", 0.0),
    ("descending_length", float("nan")),
    ("descending_bend", math.radians(70.0)),
    ("descending_bend_length", 0.01),
])
def test_params_validation_names_the_field(field: str, value: float) -> None:
    with pytest.raises(AnatomyError, match=f"^{field} must be in"):
        AnatomyParams(**{field: value})


def test_params_cross_checks() -> None:
    with pytest.raises(AnatomyError, match="left_ostium_height must be at least 2 mm below"):
        AnatomyParams(left_ostium_height=0.019)
    with pytest.raises(AnatomyError, match="brachiocephalic_to_carotid must leave"):
        AnatomyParams(brachiocephalic_to_carotid=0.010)
    with pytest.raises(AnatomyError, match="sinus_diameter must exceed"):
        AnatomyParams(sinus_diameter=0.026)
    assert dataclasses.replace(AnatomyParams(), arch_height=0.05).arch_height == 0.05
    with pytest.raises(AnatomyError, match="descending_bend_length must be <= descending_length"):
        AnatomyParams(descending_length=0.08, descending_bend_length=0.09)


def test_descending_bend_turns_the_open_end_towards_right_anterior() -> None:
    straight = AortaGeometry(AnatomyParams())
    bent = AortaGeometry(CURVED_PARAMS)
    assert straight.exit_normal @ np.array([0.0, 0.0, -1.0]) > 0.9999
    down, towards = np.array([0.0, 0.0, -1.0]), np.array([-1.0, -1.0, 0.0]) / math.sqrt(2.0)
    expected = math.cos(math.radians(30.0)) * down + math.sin(math.radians(30.0)) * towards
    assert math.degrees(math.acos(min(1.0, float(bent.exit_normal @ expected)))) < 2.0
    # the same arc length of descending aorta, and the same aorta above the bend
    assert bent.s_exit == pytest.approx(straight.s_exit, abs=1.5 * MM)
    above = straight.arc < straight.s_exit - 0.09  # (the bend, plus the 28 mm smoothing)
    np.testing.assert_allclose(bent.spine[:above.sum()], straight.spine[above], atol=1e-9)


def test_curved_descending_aorta_meshes_with_consistent_landmarks() -> None:
    anatomy = curved_anatomy()
    mesh = anatomy.mesh
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
    cap = anatomy.faces[~anatomy.wall_face_mask]
    exit_cap = cap[np.linalg.norm(anatomy.vertices[cap].mean(axis=1) - anatomy.exit_point,
                                  axis=1) < 0.015]
    normals = mesh.face_normals[np.flatnonzero(~anatomy.wall_face_mask)][
        np.linalg.norm(anatomy.vertices[cap].mean(axis=1) - anatomy.exit_point, axis=1) < 0.015]
    assert len(exit_cap) > 5
    assert np.all(normals @ anatomy.exit_normal > 0.999)
    assert anatomy.contains(anatomy.start_point[None])[0]
    assert float((anatomy.start_point - anatomy.exit_point) @ -anatomy.exit_normal) == \
        pytest.approx(0.020, abs=1 * MM)


_VARIANTS = {
    # About -1 SD diameters (ANATOMY.md), narrow and low arch, low ostia.
    "small": dict(annulus_diameter=0.021, sinus_diameter=0.027, stj_diameter=0.022,
                  ascending_diameter=0.027, proximal_arch_diameter=0.025,
                  arch_proximal_diameter=0.024, arch_distal_diameter=0.022,
                  isthmus_diameter=0.021, descending_diameter=0.021, arch_width=0.064,
                  arch_height=0.038, left_ostium_height=0.0115, right_ostium_height=0.014),
    # About +1 SD diameters, wide arch, steep branches, wider ostia angle.
    "large": dict(annulus_diameter=0.0255, sinus_diameter=0.035, stj_diameter=0.027,
                  ascending_diameter=0.035, proximal_arch_diameter=0.033,
                  arch_proximal_diameter=0.031, arch_distal_diameter=0.030,
                  isthmus_diameter=0.028, descending_diameter=0.027, arch_width=0.080,
                  brachiocephalic_diameter=0.0145, subclavian_diameter=0.012,
                  brachiocephalic_to_carotid=0.018, brachiocephalic_angle=0.55,
                  subclavian_angle=0.65, ostia_angle=2.37),
}


@pytest.mark.slow
@pytest.mark.parametrize("variant", sorted(_VARIANTS))
def test_parameter_variants_build_valid_meshes(variant: str) -> None:
    from cgail_sim.centerline import compute_centerlines

    params = AnatomyParams(**_VARIANTS[variant])
    anatomy = build_anatomy_from_params(params, variant)
    mesh = anatomy.mesh
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
    assert mesh.volume > 0 and 1800 < len(anatomy.vertices) < 4000
    g = AortaGeometry(params)
    assert _diameter_at(anatomy, g, g.s_exit - 0.015) == pytest.approx(
        params.descending_diameter, abs=1.0 * MM)
    for side, line in compute_centerlines(anatomy).items():
        assert anatomy.contains(line.points).all()
        assert np.linalg.norm(line.points[-1] - anatomy.ostia[side]) < 2 * MM


def test_converging_branch_stubs_are_rejected() -> None:
    params = AnatomyParams(carotid_angle=0.6, subclavian_angle=0.1)
    with pytest.raises(AnatomyError, match="carotid_angle and subclavian_angle must keep"):
        AortaGeometry(params)
    with pytest.raises(AnatomyError, match="params must be an AnatomyParams"):
        build_anatomy_from_params({"arch_width": 0.07})  # type: ignore[arg-type]

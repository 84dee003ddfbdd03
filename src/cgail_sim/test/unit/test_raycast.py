"""Ray casts and closest points against the wall BVH (exact values on a faceted tube)."""

import math

import numpy as np
import pytest
import trimesh

from cgail_sim.raycast import (
    closest_point_triangle,
    closest_segment_triangle,
    WallBVH,
)

R = 0.012
N_AROUND = 32
LENGTH = 0.1


def tube(radius=R, length=LENGTH, n_around=N_AROUND, n_rings=11):
    """Closed faceted tube along +z (outward normals), ring vertices at angles 2 pi j / n."""
    z = np.linspace(0.0, length, n_rings)
    phi = 2 * np.pi * np.arange(n_around) / n_around
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    verts = np.concatenate([np.column_stack([ring, np.full(n_around, zi)]) for zi in z])
    faces = []
    for i in range(n_rings - 1):
        for j in range(n_around):
            a0, a1 = i * n_around + j, i * n_around + (j + 1) % n_around
            faces += [[a0, a1, a1 + n_around], [a0, a1 + n_around, a0 + n_around]]
    n_wall = len(faces)
    c0, c1 = len(verts), len(verts) + 1
    verts = np.vstack([verts, [0.0, 0.0, 0.0], [0.0, 0.0, length]])
    last = (n_rings - 1) * n_around
    for j in range(n_around):
        faces.append([c0, (j + 1) % n_around, j])
        faces.append([c1, last + j, last + (j + 1) % n_around])
    faces = np.array(faces)
    mask = np.arange(len(faces)) < n_wall
    return verts, faces, mask


@pytest.fixture(scope="module")
def bvh():
    v, f, m = tube()
    return WallBVH(v, f, m)


def test_tube_fixture_is_closed_and_outward():
    v, f, _ = tube()
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight
    assert mesh.volume > 0  # outward normals


def test_rays_towards_vertices_hit_at_the_radius(bvh):
    phi = 2 * np.pi * np.arange(N_AROUND) / N_AROUND
    dirs = np.column_stack([np.cos(phi), np.sin(phi), np.zeros(N_AROUND)])
    origins = np.tile([0.0, 0.0, 0.05], (N_AROUND, 1))  # mid-ring height: vertices there
    hits = bvh.raycast(origins, dirs, 0.05)
    np.testing.assert_allclose(hits, R, rtol=0, atol=1e-12)


def test_rays_towards_facet_middles_hit_at_the_apothem(bvh):
    phi = 2 * np.pi * (np.arange(N_AROUND) + 0.5) / N_AROUND
    dirs = np.column_stack([np.cos(phi), np.sin(phi), np.zeros(N_AROUND)])
    origins = np.tile([0.0, 0.0, 0.037], (N_AROUND, 1))
    hits = bvh.raycast(origins, dirs, 0.05)
    np.testing.assert_allclose(hits, R * math.cos(math.pi / N_AROUND), rtol=0, atol=1e-12)


def test_off_axis_origin_and_oblique_ray(bvh):
    # From (x0, 0, z) towards +x: the wall facet around phi = 0 is the chord between the vertices
    # at +-pi/n... the vertex at phi = 0 lies on the ray itself: hit at R - x0.
    x0 = 0.004
    hit = bvh.raycast(np.array([[x0, 0.0, 0.05]]), np.array([[1.0, 0.0, 0.0]]), 0.05)
    assert hit[0] == pytest.approx(R - x0, abs=1e-12)
    # Oblique (45 deg towards +z) from the axis: the radial distance R is crossed at R * sqrt(2).
    d = np.array([[1.0, 0.0, 1.0]]) / math.sqrt(2.0)
    hit = bvh.raycast(np.array([[0.0, 0.0, 0.02]]), d, 0.05)
    assert hit[0] == pytest.approx(R * math.sqrt(2.0), abs=1e-12)


def test_caps_are_transparent_and_misses_return_max_dist(bvh):
    origins = np.array([[0.0, 0.0, 0.05], [0.0, 0.0, 0.05], [0.0, 0.0, 0.05]])
    dirs = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    hits = bvh.raycast(origins, dirs, 0.2)
    assert hits[0] == 0.2 and hits[1] == 0.2  # through the end caps
    assert hits[2] == pytest.approx(R, abs=1e-12)
    short = bvh.raycast(origins[2:], dirs[2:], 0.005)  # wall beyond the ray length
    assert short[0] == 0.005


def test_refit_follows_moved_vertices():
    v, f, m = tube()
    bvh = WallBVH(v, f, m)
    o = np.array([[0.0, 0.0, 0.05]])
    d = np.array([[1.0, 0.0, 0.0]])
    assert bvh.raycast(o, d, 0.1)[0] == pytest.approx(R, abs=1e-12)
    bvh.refit(v + np.array([0.003, 0.0, 0.0]))
    assert bvh.raycast(o, d, 0.1)[0] == pytest.approx(R + 0.003, abs=1e-12)
    bvh.refit(v * np.array([2.0, 2.0, 1.0]))  # inflate
    assert bvh.raycast(o, d, 0.1)[0] == pytest.approx(2 * R, abs=1e-12)


def test_agrees_with_trimesh_on_random_rays():
    v, f, m = tube(n_around=24, n_rings=7)
    bvh = WallBVH(v, f, m)
    rng = np.random.default_rng(3)
    n = 200
    origins = np.column_stack([rng.uniform(-0.006, 0.006, (n, 2)), rng.uniform(0.01, 0.09, n)])
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = bvh.raycast(origins, dirs, 1.0)
    wall = trimesh.Trimesh(v, f[m], process=False)
    locs, idx_ray, _ = trimesh.ray.ray_triangle.RayMeshIntersector(wall).intersects_location(
        origins, dirs, multiple_hits=True)
    ref = np.full(n, 1.0)
    dist = np.einsum("ij,ij->i", locs - origins[idx_ray], dirs[idx_ray])
    for k, t in zip(idx_ray, dist, strict=True):
        if t > 0:
            ref[k] = min(ref[k], t)
    np.testing.assert_allclose(hits, ref, atol=1e-9)


def test_closest_point_signed_by_outward_normal(bvh):
    apothem = R * math.cos(math.pi / N_AROUND)
    sd, q, n, face = bvh.closest_point(np.array([0.0, 0.0, 0.05]))
    assert face >= 0
    assert sd == pytest.approx(-apothem, abs=1e-12)  # inside the lumen: negative
    sd, q, n, _ = bvh.closest_point(np.array([0.02, 0.0, 0.05]))  # on the vertex line phi=0
    assert sd == pytest.approx(0.02 - R, abs=1e-12)
    np.testing.assert_allclose(n, [1.0, 0.0, 0.0], atol=1e-12)  # vertex pseudo-normal
    np.testing.assert_allclose(q, [R, 0.0, 0.05], atol=1e-12)
    sd, _, _, face = bvh.closest_point(np.array([0.0, 0.0, 0.05]), max_dist=0.001)
    assert face == -1 and sd == math.inf


def test_closest_point_and_segment_primitives():
    a = np.array([0.0, 0.0, 0.0])
    b = np.array([1.0, 0.0, 0.0])
    c = np.array([0.0, 1.0, 0.0])
    q, u, v, w = closest_point_triangle(np.array([0.25, 0.25, 2.0]), a, b, c)
    np.testing.assert_allclose(q, [0.25, 0.25, 0.0])
    assert (u, v, w) == pytest.approx((0.5, 0.25, 0.25))
    q, u, v, w = closest_point_triangle(np.array([-1.0, -1.0, 0.0]), a, b, c)
    np.testing.assert_allclose(q, a)
    # Segment above the triangle, parallel to it.
    d, qs, qt, *_ = closest_segment_triangle(np.array([0.1, 0.1, 0.5]),
                                             np.array([0.2, 0.1, 0.5]), a, b, c)
    assert d == pytest.approx(0.5)
    assert qt[2] == pytest.approx(0.0)
    # Piercing segment: distance 0 at the piercing point.
    d, qs, qt, *_ = closest_segment_triangle(np.array([0.2, 0.2, -1.0]),
                                             np.array([0.2, 0.2, 1.0]), a, b, c)
    assert d == 0.0
    np.testing.assert_allclose(qs, [0.2, 0.2, 0.0], atol=1e-15)
    # Segment passing beside an edge: closest between the segment and edge b-c.
    d, qs, qt, u, v, w = closest_segment_triangle(np.array([1.0, 1.0, -1.0]),
                                                  np.array([1.0, 1.0, 1.0]), a, b, c)
    assert d == pytest.approx(math.sqrt(0.5))
    assert u == pytest.approx(0.0) and v == pytest.approx(0.5)


@pytest.mark.parametrize("bad, match", [
    (dict(origins=np.zeros((2, 2))), "origins must have shape"),
    (dict(directions=np.zeros((3, 3))), "directions must have the shape"),
    (dict(max_dist=0.0), "max_dist must be"),
    (dict(origins=np.full((2, 3), np.nan)), "finite"),
])
def test_bad_ray_input_raises(bvh, bad, match):
    args = dict(origins=np.zeros((2, 3)), directions=np.tile([1.0, 0, 0], (2, 1)), max_dist=0.1)
    args.update(bad)
    with pytest.raises(ValueError, match=match):
        bvh.raycast(**args)


def test_bad_mesh_raises():
    v, f, m = tube()
    with pytest.raises(ValueError, match="wall_face_mask must mark"):
        WallBVH(v, f, np.zeros(len(f), bool))
    with pytest.raises(ValueError, match="wall_face_mask must have shape"):
        WallBVH(v, f, m[:-1])

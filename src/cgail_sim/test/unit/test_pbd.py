"""XPBD wall solver: topology, rest-state conservation, recovery, fixed rings, config checks."""

import math

import numpy as np
import pytest

from cgail_sim.pbd import (
    build_topology,
    internal_forces,
    particle_forces,
    PBDConfig,
    secant_factor,
)


def tube(radius=0.012, length=0.1, n_around=24, n_rings=21):
    """Closed tube along +z: vertices, faces (outward), wall mask, bottom ring, top ring."""
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
    bottom = np.r_[np.arange(n_around), c0]
    top = np.r_[np.arange(last, last + n_around), c1]
    return verts, np.array(faces), np.arange(len(faces)) < n_wall, bottom, top


def edge_lengths(x, edges):
    return np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)


def run(topo, x, v, cfg, steps, dt=0.1):
    """Plain PBD loop without heartbeat or contact (what DeformableWall does per substep)."""
    from cgail_sim.pbd import predict, solve, solve_vbd

    n = x.shape[0]
    factor = np.ones(len(topo.edges))
    x_old = np.zeros((n, 3))
    v_d = np.zeros((n, 3))
    e = np.zeros(0, np.int64)
    z = np.zeros((1, 3))
    for _ in range(steps):
        secant_factor(x, topo.edges, topo.edge_rest, cfg.stiffening, factor, 0.5)
        predict(x, v, topo.inv_mass, dt, cfg.damping, x_old, v_d)
        no_faces = np.zeros((1, 3), np.int64)
        if cfg.solver == "vbd":
            solve_vbd(x, topo.inv_mass, topo.mass, topo.rest, topo.adj_ptr, topo.adj_other,
                      topo.adj_k, topo.adj_rest, topo.adj_edge, factor, topo.tether_k,
                      topo.vertex_order, dt, cfg.iterations, no_faces, no_faces, z, z, z, e, e,
                      z, 0.0, np.zeros((n, 3)), np.zeros(n, np.int8), 0.0)
        else:
            solve(x, topo.inv_mass, topo.rest, topo.edges, topo.edge_rest, topo.edge_k, factor,
                  topo.hinges, topo.hinge_rest, topo.hinge_k, topo.tether_k, dt, cfg.iterations,
                  no_faces, no_faces, z, z, z, e, e, z, 0.0, np.zeros((n, 3)),
                  np.zeros(n, np.int8))
        v[:] = (x - x_old) / dt
    return x


@pytest.fixture(scope="module")
def mesh():
    return tube()


def test_topology_counts_masses_and_stiffness(mesh):
    v, f, _, bottom, top = mesh
    cfg = PBDConfig(bending_ratio=0.05)
    topo = build_topology(v, f, top, bottom, cfg)
    n, m = len(v), len(f)
    assert len(topo.edges) == 3 * m // 2  # closed surface: every edge shared by two faces
    assert len(topo.hinges) == len(topo.edges)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert topo.mass.sum() == pytest.approx(cfg.density * cfg.thickness * area.sum())
    assert topo.area.sum() == pytest.approx(area.sum())
    assert np.all(topo.inv_mass[top] == 0) and np.all(topo.inv_mass[bottom] == 0)
    free = np.setdiff1d(np.arange(n), np.r_[top, bottom])
    np.testing.assert_allclose(topo.inv_mass[free], 1.0 / topo.mass[free])
    # k_e = E h A_e / L0^2 for one edge, recomputed by hand.
    i, j = topo.edges[0]
    adj = [k for k, face in enumerate(f) if i in face and j in face]
    a_e = area[adj].sum()
    l0 = np.linalg.norm(v[i] - v[j])
    assert topo.edge_k[0] == pytest.approx(cfg.youngs_modulus * cfg.thickness * a_e / l0**2)
    assert topo.max_edge == pytest.approx(edge_lengths(v, topo.edges).max())
    # Every spring appears twice in the per-particle incidence lists.
    assert len(topo.adj_other) == 2 * (len(topo.edges) + len(topo.hinges))
    assert sorted(topo.vertex_order.tolist()) == list(range(n))
    # Without bending the hinges are left out.
    assert len(build_topology(v, f, top, bottom, PBDConfig()).hinges) == 0


def test_vertex_order_colours_share_no_spring(mesh):
    v, f, _, bottom, top = mesh
    topo = build_topology(v, f, top, bottom, PBDConfig(bending_ratio=0.05))
    seen: set[int] = set()
    first_colour = []
    for i in topo.vertex_order.tolist():
        nbrs = set(topo.adj_other[topo.adj_ptr[i]:topo.adj_ptr[i + 1]].tolist())
        if nbrs & seen:
            break
        seen.add(i)
        first_colour.append(i)
    assert len(first_colour) >= 10


def test_edge_groups_share_no_vertex_within_a_colour(mesh):
    v, f, _, bottom, top = mesh
    topo = build_topology(v, f, top, bottom, PBDConfig())
    # The reordered edges form runs of vertex-disjoint edges; check the first run is disjoint.
    seen: set[int] = set()
    run_len = 0
    for i, j in topo.edges.tolist():
        if i in seen or j in seen:
            break
        seen.update((i, j))
        run_len += 1
    assert run_len >= len(v) // 4


SOLVERS = [PBDConfig(), PBDConfig(solver="xpbd"), PBDConfig(bending_ratio=0.05),
           PBDConfig(solver="xpbd", bending_ratio=0.05)]


@pytest.mark.parametrize("cfg", SOLVERS)
def test_rest_state_is_conserved_exactly(mesh, cfg):
    v, f, _, bottom, top = mesh
    topo = build_topology(v, f, top, bottom, cfg)
    x = v.copy()
    run(topo, x, np.zeros_like(x), cfg, steps=200)
    np.testing.assert_allclose(edge_lengths(x, topo.edges), topo.edge_rest, rtol=0, atol=1e-12)
    np.testing.assert_allclose(x, v, atol=1e-12)


@pytest.mark.parametrize("cfg", SOLVERS)
def test_perturbed_wall_recovers_rest_lengths_and_fixed_rings_stay(mesh, cfg):
    v, f, _, bottom, top = mesh
    topo = build_topology(v, f, top, bottom, cfg)
    rng = np.random.default_rng(0)
    x = v + rng.normal(scale=0.5e-3, size=v.shape) * (topo.inv_mass > 0)[:, None]
    strain0 = np.abs(edge_lengths(x, topo.edges) / topo.edge_rest - 1).max()
    assert strain0 > 0.05
    run(topo, x, np.zeros_like(x), cfg, steps=100)
    strain = np.abs(edge_lengths(x, topo.edges) / topo.edge_rest - 1).max()
    assert strain < 1e-3  # edge lengths within 0.1 % of rest
    np.testing.assert_array_equal(x[top], v[top])
    np.testing.assert_array_equal(x[bottom], v[bottom])


def test_contact_neighbourhood_grows_by_rings(mesh):
    from cgail_sim.pbd import contact_neighbourhood

    v, f, _, bottom, top = mesh
    topo = build_topology(v, f, top, bottom, PBDConfig())
    touched = np.zeros(len(v), np.int8)
    seed = 5 * 24 + 3  # a wall vertex mid-tube
    touched[seed] = 2
    ring0 = contact_neighbourhood(touched, topo.adj_ptr, topo.adj_other, topo.vertex_order, 0)
    assert ring0.tolist() == [seed]
    ring1 = contact_neighbourhood(touched, topo.adj_ptr, topo.adj_other, topo.vertex_order, 1)
    nbrs = set(topo.adj_other[topo.adj_ptr[seed]:topo.adj_ptr[seed + 1]].tolist())
    assert set(ring1.tolist()) == nbrs | {seed}
    ring2 = contact_neighbourhood(touched, topo.adj_ptr, topo.adj_other, topo.vertex_order, 2)
    assert set(ring1.tolist()) < set(ring2.tolist())
    order_rank = {int(i): k for k, i in enumerate(topo.vertex_order)}
    assert [order_rank[int(i)] for i in ring2] == sorted(order_rank[int(i)] for i in ring2)


def test_secant_factor_and_internal_forces():
    x = np.array([[0.0, 0.0, 0.0], [1.1, 0.0, 0.0]])
    edges = np.array([[0, 1]])
    out = np.zeros(1)
    secant_factor(x, edges, np.array([1.0]), 10.0, out, 1.0)
    assert out[0] == pytest.approx(math.expm1(1.0) / 1.0)  # b eps = 10 * 0.1
    secant_factor(x, edges, np.array([1.2]), 10.0, out, 1.0)  # compressed: linear
    assert out[0] == 1.0
    secant_factor(x, edges, np.array([1.0]), 10.0, out, 0.5)  # under-relaxed update
    assert out[0] == pytest.approx(1.0 + 0.5 * (math.expm1(1.0) - 1.0))
    f = internal_forces(x, x.copy(), edges, np.array([1.0]), np.array([100.0]), 10.0,
                        np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0), np.zeros(2))
    # sigma-type law: k g (L - L0) = 100 * (e - 1) * 0.1, pulling the ends together.
    mag = 100.0 * math.expm1(1.0) * 0.1
    np.testing.assert_allclose(f, [[mag, 0, 0], [-mag, 0, 0]])


def test_internal_forces_vanish_at_rest(mesh):
    v, f, _, bottom, top = mesh
    cfg = PBDConfig()
    topo = build_topology(v, f, top, bottom, cfg)
    forces = internal_forces(v, topo.rest, topo.edges, topo.edge_rest, topo.edge_k,
                             cfg.stiffening, topo.hinges, topo.hinge_rest, topo.hinge_k,
                             topo.tether_k)
    assert np.abs(forces).max() < 1e-9


def test_particle_forces_are_the_rows_of_internal_forces(mesh):
    v, f, _, bottom, top = mesh
    cfg = PBDConfig(bending_ratio=0.05)  # hinges too
    topo = build_topology(v, f, top, bottom, cfg)
    rng = np.random.default_rng(3)
    x = topo.rest + rng.normal(scale=5e-4, size=topo.rest.shape)  # stretched and compressed
    full = internal_forces(x, topo.rest, topo.edges, topo.edge_rest, topo.edge_k,
                           cfg.stiffening, topo.hinges, topo.hinge_rest, topo.hinge_k,
                           topo.tether_k)
    idx = np.array([0, 5, len(x) // 2, len(x) - 1], dtype=np.int64)
    part = particle_forces(x, topo.rest, idx, topo.adj_ptr, topo.adj_other, topo.adj_k,
                           topo.adj_rest, topo.adj_edge, cfg.stiffening, topo.tether_k)
    assert np.abs(full[idx]).max() > 1e-3  # not trivially zero
    np.testing.assert_allclose(part, full[idx], rtol=1e-9, atol=1e-12)
    assert particle_forces(x, topo.rest, idx[:0], topo.adj_ptr, topo.adj_other, topo.adj_k,
                           topo.adj_rest, topo.adj_edge, cfg.stiffening,
                           topo.tether_k).shape == (0, 3)


def test_padded_springs_hold_the_csr_springs(mesh):
    v, f, _, bottom, top = mesh
    topo = build_topology(v, f, top, bottom, PBDConfig(bending_ratio=0.05))
    n, width = topo.ell_other.shape
    assert n == len(v) and width % 8 == 0
    for i in range(n):
        lo, hi = topo.adj_ptr[i], topo.adj_ptr[i + 1]
        if topo.inv_mass[i] > 0:
            np.testing.assert_array_equal(topo.ell_other[i, :hi - lo], topo.adj_other[lo:hi])
            np.testing.assert_array_equal(topo.ell_k[i, :hi - lo], topo.adj_k[lo:hi])
            np.testing.assert_array_equal(topo.ell_rest[i, :hi - lo], topo.adj_rest[lo:hi])
            np.testing.assert_array_equal(topo.ell_edge[i, :hi - lo], topo.adj_edge[lo:hi])
            pad = slice(hi - lo, width)
        else:
            pad = slice(0, width)
        assert np.all(topo.ell_other[i, pad] == i) and np.all(topo.ell_k[i, pad] == 0.0)
        assert np.all(topo.ell_edge[i, pad] == -1)


def test_padded_sweep_equals_the_csr_sweep(mesh):
    """The vectorised sweep over padded rows moves every particle as the per-spring CSR loop
    (bending springs included, so rows wider than one SIMD chunk), to round-off."""
    from cgail_sim.pbd import _padded_secant, _sweep_csr, _sweep_padded

    v, f, _, bottom, top = mesh
    cfg = PBDConfig(bending_ratio=0.05)
    topo = build_topology(v, f, top, bottom, cfg)
    assert topo.ell_other.shape[1] > 8
    rng = np.random.default_rng(4)
    x0 = topo.rest + rng.normal(scale=5e-4, size=topo.rest.shape)
    y = topo.rest + rng.normal(scale=5e-4, size=topo.rest.shape)
    factor = 1.0 + rng.uniform(0.0, 2.0, len(topo.edges))
    keff = np.where(topo.adj_edge >= 0, topo.adj_k * factor[topo.adj_edge], topo.adj_k)
    ell_keff = np.empty_like(topo.ell_k)
    _padded_secant(topo.ell_k, topo.ell_edge, factor, ell_keff)
    a = x0.copy()
    b = x0.copy()
    for _ in range(3):
        _sweep_csr(a, y, topo.inv_mass, topo.mass, 100.0, topo.tether_k, topo.rest,
                   topo.vertex_order, topo.adj_ptr, topo.adj_other, topo.adj_k, topo.adj_rest,
                   topo.adj_edge, keff, 0.0)
        _sweep_padded(b, y, topo.inv_mass, topo.mass, 100.0, topo.tether_k, topo.rest,
                      topo.vertex_order, topo.ell_other, ell_keff, topo.ell_rest)
    assert np.abs(a - x0).max() > 1e-5  # the sweeps did move the particles
    np.testing.assert_allclose(b, a, rtol=0.0, atol=1e-15)


@pytest.mark.parametrize("field, value, match", [
    ("youngs_modulus", 0.0, "youngs_modulus must be in"),
    ("stiffening", -1.0, "stiffening must be in"),
    ("thickness", 0.1, "thickness must be in"),
    ("density", float("inf"), "density must be in"),
    ("tether_stiffness", -1.0, "tether_stiffness must be in"),
    ("bending_ratio", 2.0, "bending_ratio must be in"),
    ("solver", "jacobi", "solver must be 'vbd' or 'xpbd'"),
    ("local_iterations", -1, "local_iterations must be an int"),
    ("local_rings", 21, "local_rings must be an int"),
    ("iterations", 0, "iterations must be an int"),
    ("iterations", 2.5, "iterations must be an int"),
    ("substeps", True, "substeps must be an int"),
    ("damping", -1.0, "damping must be in"),
    ("penetration_tolerance", 0.01, "penetration_tolerance must be in"),
])
def test_bad_config_raises(field, value, match):
    with pytest.raises(ValueError, match=match):
        PBDConfig(**{field: value})


def test_bad_topology_input_raises(mesh):
    v, f, _, bottom, top = mesh
    with pytest.raises(ValueError, match="faces must index vertices"):
        build_topology(v, f + len(v), top, bottom, PBDConfig())
    with pytest.raises(ValueError, match="fixed vertex indices"):
        build_topology(v, f, np.array([len(v) + 3]), bottom, PBDConfig())
    with pytest.raises(ValueError, match="every vertex must belong"):
        build_topology(np.vstack([v, [1.0, 1.0, 1.0]]), f, top, bottom, PBDConfig())

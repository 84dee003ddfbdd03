"""The fast paths of the dynamic wall give the same answers as the straightforward ones.

* the one-call VBD wall step (:func:`cgail_sim.pbd.step_vbd`: broad phase on the tree of
  the last refit, grown by the displacement since) against the substep loop that refits the tree
  at the predicted positions and calls the kernels one by one: equal to round-off (1e-14 m);
* the pseudo-normal of one closest feature against the full per-mesh normals;
* the tree refit inside the step against a tree built from scratch on the new shape;
* the dynamic env's wall solver: configurable, and its default (5 Chebyshev-accelerated sweeps)
  keeps the heartbeat amplitude; the acceleration converges faster than plain sweeps.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from cgail_sim.config import EnvConfig
from cgail_sim.contact import narrow_pairs
from cgail_sim.env import CatheterNavEnv, DYNAMIC_PBD_CONFIG
from cgail_sim.heartbeat import HeartbeatConfig
from cgail_sim.pbd import (
    contact_neighbourhood,
    PBDConfig,
    predict,
    secant_factor,
    solve_vbd,
)
from cgail_sim.raycast import closest_kernel, WallBVH
from cgail_sim.vec_env import CatheterNavVecEnv
from cgail_sim.wall import _SECANT_RELAX, DeformableWall
from cgail_sim.worlds import load_world

R = 0.012
LENGTH = 0.12
N_AROUND = 24
N_RINGS = 25
CATHETER_R = 0.0035
DT = 0.1


def tube_anatomy() -> SimpleNamespace:
    """Closed tube along +z: the annulus is the z=0 ring, the z=LENGTH ring is fixed."""
    z = np.linspace(0.0, LENGTH, N_RINGS)
    phi = 2 * np.pi * np.arange(N_AROUND) / N_AROUND
    ring = np.stack([R * np.cos(phi), R * np.sin(phi)], axis=1)
    verts = np.concatenate([np.column_stack([ring, np.full(N_AROUND, zi)]) for zi in z])
    faces = []
    for i in range(N_RINGS - 1):
        for j in range(N_AROUND):
            a0, a1 = i * N_AROUND + j, i * N_AROUND + (j + 1) % N_AROUND
            faces += [[a0, a1, a1 + N_AROUND], [a0, a1 + N_AROUND, a0 + N_AROUND]]
    n_wall = len(faces)
    c0, c1 = len(verts), len(verts) + 1
    verts = np.vstack([verts, [0.0, 0.0, 0.0], [0.0, 0.0, LENGTH]])
    last = (N_RINGS - 1) * N_AROUND
    for j in range(N_AROUND):
        faces.append([c0, (j + 1) % N_AROUND, j])
        faces.append([c1, last + j, last + (j + 1) % N_AROUND])
    return SimpleNamespace(
        name="tube", vertices=verts, faces=np.array(faces),
        wall_face_mask=np.arange(len(faces)) < n_wall,
        fixed_vertices=np.r_[np.arange(last, last + N_AROUND), c1],
        annulus_vertices=np.r_[np.arange(N_AROUND), c0],
        annulus_center=np.zeros(3), root_axis=np.array([0.0, 0.0, 1.0]),
    )


@pytest.fixture(scope="module")
def tube():
    return tube_anatomy()


def body_at(k: int) -> np.ndarray:
    """A catheter sliding along the wall at phi = 0, pressing up to 2 mm into it."""
    ind = 0.002 * np.sin(0.4 * k) ** 2
    x = R - CATHETER_R + ind
    z_tip = 0.04 + 0.002 * k
    zs = np.arange(z_tip - 0.03, z_tip + 1e-9, 0.005)
    return np.column_stack([np.full(len(zs), x), 0.001 * np.sin(zs * 200.0), zs])


def reference_step(wall: DeformableWall, t: float, dt: float, pts: np.ndarray,
                   radius: float) -> None:
    """The substep loop spelled out: refit at the predicted positions, one kernel at a time."""
    cfg = wall.pbd_config
    topo = wall.topology
    bvh = wall._bvh
    h = dt / cfg.substeps
    x = wall.vertices
    v = wall.velocities
    wall._impulse[:] = 0.0
    wall._touched[:] = 0
    wall._dp[:] = 0.0
    for k in range(cfg.substeps):
        secant_factor(x, topo.edges, topo.edge_rest, cfg.stiffening, wall._factor,
                      _SECANT_RELAX)
        predict(x, v, topo.inv_mass, h, cfg.damping, wall._x_old, wall._v_damped)
        x[topo.annulus] = topo.rest[topo.annulus] + wall.heartbeat.displacement(
            t - dt + (k + 1) * h)
        x[topo.fixed] = topo.rest[topo.fixed]
        bvh.refit(x)
        reach = radius + cfg.contact_margin
        pf, ps = bvh.faces_near_segments(pts, reach)
        pf, ps = narrow_pairs(x, bvh.faces, pf, ps, pts, reach)
        args = (bvh.faces, bvh.face_edges, wall._rest_fn, wall._rest_vn, wall._rest_en, pf, ps,
                pts, radius, wall._impulse, wall._touched, 0.0)
        solve_vbd(x, topo.inv_mass, topo.mass, topo.rest, topo.adj_ptr, topo.adj_other,
                  topo.adj_k, topo.adj_rest, topo.adj_edge, wall._factor, topo.tether_k,
                  topo.vertex_order, h, cfg.iterations, *args, cfg.chebyshev_rho)
        if pf.size and cfg.local_iterations:
            local = contact_neighbourhood(wall._touched, topo.adj_ptr, topo.adj_other,
                                          topo.vertex_order, cfg.local_rings)
            if local.size:
                solve_vbd(x, topo.inv_mass, topo.mass, topo.rest, topo.adj_ptr,
                          topo.adj_other, topo.adj_k, topo.adj_rest, topo.adj_edge,
                          wall._factor, topo.tether_k, local, h, cfg.local_iterations, *args)
        v_new = (x - wall._x_old) / h
        wall._dp += topo.mass[:, None] * (v_new - wall._v_damped)
        v[:] = v_new
    bvh.refit(x)


@pytest.mark.parametrize(("substeps", "rho"), [(1, 0.0), (2, 0.0), (1, 0.85)])
def test_one_call_step_equals_the_substep_loop(tube, substeps, rho):
    cfg = PBDConfig(substeps=substeps, chebyshev_rho=rho)
    hb = HeartbeatConfig()
    fast = DeformableWall(tube, cfg, hb)
    ref = DeformableWall(tube, cfg, hb)
    forces = []
    for k in range(25):
        t = (k + 1) * DT
        pts = body_at(k)
        if k % 4 == 3:
            # A fast wall (3.4 mm predicted motion after damping) towards the catheter: pairs
            # that only come within reach at the predicted positions must still be found.
            for w in (fast, ref):
                w.velocities[:] = (-0.25, 0.0, 0.0)
        fast.step(t, DT, pts, CATHETER_R)
        reference_step(ref, t, DT, pts, CATHETER_R)
        # Same arithmetic, but two separately compiled fastmath kernels may vectorise
        # (reassociate) a sum differently: equal to round-off, not always to the bit.
        np.testing.assert_allclose(fast.vertices, ref.vertices, rtol=0, atol=1e-14)
        np.testing.assert_allclose(fast.velocities, ref.velocities, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(fast._touched, ref._touched)
        np.testing.assert_allclose(fast._dp, ref._dp, rtol=0, atol=1e-15)
        a = fast.tip_contact(pts[-1], CATHETER_R, DT)
        b = ref.tip_contact(pts[-1], CATHETER_R, DT)
        assert a.force == pytest.approx(b.force, rel=1e-9, abs=1e-12)
        assert a.penetration == pytest.approx(b.penetration, abs=1e-14)
        forces.append(a.force)
    assert max(forces) > 0.0  # the comparison covered steps with contact forces


def test_tree_is_refit_to_the_new_shape_inside_the_step(tube):
    wall = DeformableWall(tube)
    rng = np.random.default_rng(0)
    origins = np.column_stack([rng.uniform(-0.004, 0.004, (60, 2)), rng.uniform(0.0, 0.1, 60)])
    dirs = rng.normal(size=(60, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for k in range(6):
        wall.step((k + 1) * DT, DT, body_at(k), CATHETER_R)
        fresh = WallBVH(wall.vertices, tube.faces, tube.wall_face_mask)
        np.testing.assert_array_equal(wall.raycast(origins, dirs, 0.05),
                                      fresh.raycast(origins, dirs, 0.05))
        for p in origins[:10]:  # (ties between faces may break differently in a new tree)
            sd_a, q_a, n_a, _ = wall._bvh.closest_point(p)
            sd_b, q_b, n_b, _ = fresh.closest_point(p)
            assert sd_a == pytest.approx(sd_b, abs=1e-15)
            np.testing.assert_allclose(q_a, q_b, atol=1e-15)
            np.testing.assert_allclose(n_a, n_b, atol=1e-12)
    assert np.abs(wall.vertices - tube.vertices).max() > 1e-3  # the wall did move


def test_feature_normal_matches_the_full_pseudo_normals(tube):
    rng = np.random.default_rng(2)
    verts = tube.vertices + rng.normal(scale=4e-4, size=tube.vertices.shape)
    bvh = WallBVH(verts, tube.faces, tube.wall_face_mask)
    fn, vn, en = bvh.pseudo_normals()
    kinds = set()
    queries = np.column_stack([rng.uniform(-0.02, 0.02, (400, 2)), rng.uniform(0.0, 0.12, 400)])
    for p in queries:
        _, face, _, u, v, w = closest_kernel(*bvh.query_arrays[:9], p, np.inf)
        zero = [k for k, b in enumerate((u, v, w)) if b <= 1e-12]
        if len(zero) == 2:
            ref = vn[bvh.faces[face, ({0, 1, 2} - set(zero)).pop()]]
        elif len(zero) == 1:
            ref = en[bvh.face_edges[face, (zero[0] + 1) % 3]]
        else:
            ref = fn[face]
        kinds.add(len(zero))
        _, _, n, _ = bvh.closest_point(p)
        np.testing.assert_allclose(n, ref / np.linalg.norm(ref), atol=1e-12)
    assert kinds == {0, 1, 2}  # face, edge and vertex regions all checked


def test_dynamic_wall_is_deterministic(tube):
    a = DeformableWall(tube)
    b = DeformableWall(tube)
    for k in range(10):
        a.step((k + 1) * DT, DT, body_at(k), CATHETER_R)
        b.step((k + 1) * DT, DT, body_at(k), CATHETER_R)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    a.reset()
    for k in range(10):
        a.step((k + 1) * DT, DT, body_at(k), CATHETER_R)
    np.testing.assert_array_equal(a.vertices, b.vertices)


def test_env_wall_solver_is_configurable():
    env = CatheterNavEnv(EnvConfig(mode="dynamic"))
    assert env.engine.walls[0].pbd_config == DYNAMIC_PBD_CONFIG
    env10 = CatheterNavEnv(EnvConfig(mode="dynamic"), pbd_config=PBDConfig())
    assert env10.engine.walls[0].pbd_config.iterations == 10
    vec = CatheterNavVecEnv(EnvConfig(mode="dynamic"), num_envs=2,
                            pbd_config=PBDConfig(iterations=6))
    assert [w.pbd_config.iterations for w in vec.engine.walls] == [6, 6]
    with pytest.raises(ValueError, match="pbd_config must be a PBDConfig"):
        CatheterNavEnv(EnvConfig(mode="dynamic"), pbd_config={"iterations": 8})


def _ostium_amplitudes(world, cfg: PBDConfig) -> np.ndarray:
    """Largest ostium-target displacement over beats 3-4 (steps 18-34 at 70 bpm), m."""
    targets = np.array([t.vertex for t in world.scenarios.targets])
    wall = DeformableWall(world.anatomy, cfg)
    disp = []
    for k in range(1, 35):  # four beats at 70 bpm
        wall.step(k * DT, DT, np.zeros((0, 3)), CATHETER_R)
        disp.append(wall.vertices[targets] - world.anatomy.vertices[targets])
    return np.linalg.norm(np.array(disp[17:]), axis=2).max(axis=0)


def test_env_default_sweeps_keep_the_ostium_heartbeat_amplitude():
    """The documented trade of DYNAMIC_PBD_CONFIG: ostium amplitudes within 5 % of 10 plain
    sweeps (beats 3-4), and no further from a 20-sweep solve than 8 plain sweeps are."""
    world = load_world("default")
    amp10 = _ostium_amplitudes(world, PBDConfig())
    amp20 = _ostium_amplitudes(world, PBDConfig(iterations=20))
    amp8 = _ostium_amplitudes(world, PBDConfig(iterations=8))
    env = _ostium_amplitudes(world, DYNAMIC_PBD_CONFIG)
    assert amp10.min() > 0.004  # the ostia do move with the beat (mm scale)
    ratio = env / amp10
    assert np.all(np.abs(ratio - 1.0) < 0.05), ratio
    assert np.all(np.abs(env / amp20 - 1.0) <= np.abs(amp8 / amp20 - 1.0) + 1e-3)


def test_chebyshev_sweeps_converge_faster_than_plain_ones(tube):
    """Same sweep count, Chebyshev-accelerated sweeps end closer to the converged solve."""
    cfg = PBDConfig()
    wall = DeformableWall(tube, cfg)
    topo = wall.topology
    x0 = topo.rest.copy()
    x0[topo.annulus] += (0.0, 0.0, -0.008)  # annulus pulled down 8 mm, the wall not yet
    e = np.zeros(0, dtype=np.int64)
    no_faces = np.zeros((0, 3), dtype=np.int64)
    z = np.zeros((0, 3))
    factor = np.ones(len(topo.edges))

    def solve(sweeps: int, rho: float) -> np.ndarray:
        x = x0.copy()
        solve_vbd(x, topo.inv_mass, topo.mass, topo.rest, topo.adj_ptr, topo.adj_other,
                  topo.adj_k, topo.adj_rest, topo.adj_edge, factor, topo.tether_k,
                  topo.vertex_order, DT, sweeps, no_faces, no_faces, z, z, z, e, e,
                  np.zeros((1, 3)), CATHETER_R, np.zeros_like(x), np.zeros(len(x), np.int8),
                  0.0, rho)
        return x

    converged = solve(2000, 0.0)

    def rms_error(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((x - converged) ** 2, axis=1))))

    for sweeps in (5, 10, 20):
        plain = rms_error(solve(sweeps, 0.0))
        fast = rms_error(solve(sweeps, 0.85))
        assert fast < (0.95 if sweeps < 20 else 0.8) * plain, (sweeps, fast, plain)
    np.testing.assert_array_equal(solve(5, 0.0), solve(5, 0.0))  # deterministic
    with pytest.raises(ValueError, match="chebyshev_rho must be in"):
        PBDConfig(chebyshev_rho=1.0)

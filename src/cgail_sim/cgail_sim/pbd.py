"""Position-based dynamics of the aortic wall (numba, deterministic Gauss-Seidel sweeps).

The wall is a particle system on the mesh vertices, advanced with the position-based scheme of
Mueller et al. 2007 ("Position based dynamics": predict positions from velocities, solve
constraints on positions, derive velocities from the position change) in the implicit-Euler /
compliant form of XPBD (Macklin et al. 2016), so stiffnesses are physical (N/m) and independent
of the time step. Model:

* particles = the mesh vertices; mass ``m_i = density * thickness * A_i`` with ``A_i`` one third
  of the area of the triangles around vertex ``i``;
* **stretch**: a distance constraint ``C = |x_i - x_j| - L0`` on every mesh edge. Its stiffness is
  the membrane stiffness of the wall, ``k_e = E h A_e / L0^2`` with ``A_e`` the area of the (one
  or two) triangles sharing the edge; for an equilateral mesh this is the classic
  ``sqrt(3)/2 E h`` of a spring network that matches a membrane of Young's modulus E and
  thickness h. The material stiffens with strain (Fung-type curve): the spring uses the secant
  stiffness ``k_e g(eps)`` with ``g(eps) = (exp(b eps) - 1) / (b eps)`` for ``eps > 0``
  (``g = 1`` in compression; ``b eps`` capped at 5), so a uniaxially stretched membrane follows
  ``sigma(eps) = E / b (exp(b eps) - 1)``. ``g`` is evaluated once per substep from the
  strain at its start (lagged secant, under-relaxed by 1/2 for stability) to keep the inner
  loop free of ``exp``;
* **bending**: the edge-pair (isometric "hinge") form, a distance constraint between the two
  vertices opposite each interior edge, stiffness ``bending_ratio * k_e`` (off by default, see
  :attr:`PBDConfig.bending_ratio`);
* **tethering**: a zero-length spring from each particle to its rest position, stiffness
  ``tether_stiffness * A_i``: the support of the surrounding tissue (mediastinum, pericardium);
* **fixed rings** (``Anatomy.fixed_vertices``) have inverse mass 0 and stay at rest;
* **annulus ring** (``Anatomy.annulus_vertices``) is kinematic, placed by the heartbeat;
* **damping**: velocities decay as ``exp(-damping dt)`` before the prediction;
* **contact**: the catheter's capsule chain, a hard position projection after every sweep
  (linearised per step: :func:`cgail_sim.contact.project_planes`) and twice more
  exactly at the end (:func:`cgail_sim.contact.project_contacts`), so the wall ends
  each step outside the catheter.

Two solvers for the elastic part (``PBDConfig.solver``), both sequential and deterministic:

* ``"vbd"`` (default): vertex-block Gauss-Seidel (Chen et al. 2024, "Vertex Block Descent"):
  each particle takes a 3x3 Newton step on the incremental potential of all its springs and its
  tether at once. Wall particles are light (~4e-5 kg) and the control step long (0.1 s), so
  ``m / dt^2`` is tiny next to every stiffness; block descent still weighs the soft tether
  against the stiff stretch springs correctly, and the heartbeat propagates as it should.
* ``"xpbd"``: classic per-constraint XPBD projections (compliance ``alpha = 1 / k``,
  ``d_lambda = (-C - alpha~ lambda) / (sum w |grad C|^2 + alpha~)``, ``alpha~ = alpha / dt^2``).
  With light particles and long steps every constraint, even the soft tether, acts as hard
  within the few iterations of a step, so the root motion barely reaches the wall above it
  (measured on a tube: 0.08 mm at 10 mm above an 11 mm annulus motion, against 8.8 mm with
  VBD). Kept for comparison and for small-step use (e.g. many substeps).

Speed (VBD): the sweeps read each particle's springs from fixed-width padded rows
(:func:`padded_springs`, built once per mesh) so the compiler vectorises them, and may be
Chebyshev-accelerated (``PBDConfig.chebyshev_rho``; the dynamic environment uses 5 accelerated
sweeps, as converged as 8-10 plain ones: ``bench/bench_wall.py --accuracy``). The exact-law
sweep of the calibration keeps the per-spring CSR loop.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from numba import njit
import numpy as np

from cgail_sim import contact, raycast
from cgail_sim.contact import (
    linearize_contacts,
    narrow_pairs,
    project_contacts,
    project_planes,
)
from cgail_sim.raycast import (
    drop_stale_numba_cache,
    faces_near_segments_kernel,
    refit_tree,
)

drop_stale_numba_cache(__file__, [__file__, contact.__file__, raycast.__file__])

#: Cap of ``b eps`` in the stiffening law: beyond it the secant stiffness stays at
#: ``g(_Z_MAX) ~ 29.5`` (strain 0.32 for b = 15.7, far past physiological stretch), which keeps
#: forces finite when a coarse mesh is indented locally.
_Z_MAX = 5.0
_G_MAX = math.expm1(_Z_MAX) / _Z_MAX
#: Springs from a contact triangle within which the Chebyshev-accelerated sweeps take plain
#: steps (see :func:`solve_vbd`).
_PLAIN_RINGS = 3

__all__ = [
    "PBDConfig",
    "WallTopology",
    "build_topology",
    "contact_neighbourhood",
    "internal_forces",
    "largest_displacement",
    "padded_springs",
    "particle_forces",
    "predict",
    "secant_factor",
    "solve",
    "solve_vbd",
    "step_vbd",
]


@dataclass(frozen=True)
class PBDConfig:
    """Material and solver parameters of the PBD wall (SI units)."""

    youngs_modulus: float = 0.4958e6
    """Small-strain Young's modulus E of the spring-network material, Pa; in [1e3, 1e8].
    Default: :func:`cgail_sim.calibration.calibrate` fitted to the default target curve
    (0.5 MPa small-strain, an estimate from the Moens-Korteweg wave speed, see ANATOMY.md, and
    80 kPa at stretch 1.08, Jadidi 2020, PMC6982607): 0.4958 MPa, rms error 0.02 %."""
    stiffening: float = 15.67
    """Fung exponent b of the material law ``sigma = E / b (exp(b eps) - 1)``
    (dimensionless); in [0, 100]; 0 gives a linear material. Default: the same calibration
    (the target curve itself has b = 15.705)."""
    thickness: float = 0.0025
    """Wall thickness h, m (2.5 mm; MESA, Turkbey 2014); in [0.1 mm, 10 mm]."""
    density: float = 1100.0
    """Wall density, kg/m^3 (~1,100 for soft tissue); in [100, 10000]."""
    tether_stiffness: float = 1.25e5
    """Stiffness per unit wall area of the zero-length tether to the rest shape, N/m^3
    (estimate): with E h ~ 1,250 N/m the root motion decays along the aorta over
    ``sqrt(E h / k) ~ 100 mm``, the annulus-to-arch distance, so the 10 mm systolic descent is
    shared by the root and the ascending aorta (median edge strain there 5-10 % at
    end-systole; the ascending aorta is known to stretch lengthwise by several per cent per
    beat, e.g. Beller et al. 2004); in [0, 1e9]."""
    bending_ratio: float = 0.0
    """Stiffness of each bending (hinge) spring as a fraction of the stretch stiffness of its
    edge; in [0, 1]. 0 (default) leaves the hinges out: the plate-bending stiffness of the
    aortic wall relative to its membrane stiffness is ~h^2 / (12 R^2) ~ 0.4 % (negligible), the
    tethers already keep the surface smooth, and the hinges double the solver cost. Use e.g.
    0.05 as a regulariser for coarse or noisy patient meshes."""
    solver: str = "vbd"
    """``"vbd"`` (vertex-block Gauss-Seidel, default) or ``"xpbd"`` (per-constraint
    projections); see the module docstring for why VBD is the default."""
    iterations: int = 10
    """Gauss-Seidel sweeps per substep; in [1, 1000]."""
    local_iterations: int = 20
    """Extra sweeps (VBD solver only) over the particles within :attr:`local_rings` springs of
    a catheter contact, after the global sweeps: they settle the dent, whose force otherwise
    reads several times its equilibrium value on the step after a sudden push; in [0, 1000]."""
    local_rings: int = 3
    """Size of that neighbourhood, in springs from a contacted particle; in [0, 20]."""
    chebyshev_rho: float = 0.0
    """Spectral-radius estimate for the Chebyshev acceleration of the global sweeps (VBD
    solver only, see :func:`solve_vbd`); 0 (default) = plain sweeps; in [0, 0.999]."""
    substeps: int = 1
    """Substeps per :meth:`step` (each solves the constraints with ``dt / substeps``);
    in [1, 100]."""
    damping: float = 20.0
    """Velocity damping rate, 1/s: velocities are multiplied by ``exp(-damping dt)`` each
    substep (heavily damped tissue; estimate); in [0, 1e4]."""
    contact_margin: float = 0.002
    """Extra reach of the contact broad phase beyond the catheter radius, m (covers wall
    motion within a substep); in [0, 0.05]."""
    penetration_tolerance: float = 5e-5
    """Geometric penetration below this depth is reported as 0, m (the residual of the
    iterative contact projection); in [0, 1 mm]."""
    max_displacement: float = 0.04
    """Bound on any particle's distance from its rest position, m; a step that exceeds it
    raises :class:`cgail_sim.wall.WallError` instead of going on with a wall that has
    blown up (e.g. pushed by a catheter body lying outside the lumen). 40 mm is three times the
    largest displacement of normal episodes in the built-in anatomies (12-13 mm: the 11 mm
    heartbeat excursion of the root plus catheter contact) and more than the widest lumen
    (35 mm): a particle that far has crossed the vessel. In [5 mm, 1 m]."""

    def __post_init__(self) -> None:
        for name, low, high in (
            ("youngs_modulus", 1e3, 1e8), ("stiffening", 0.0, 100.0),
            ("thickness", 1e-4, 1e-2), ("density", 100.0, 1e4),
            ("tether_stiffness", 0.0, 1e9), ("bending_ratio", 0.0, 1.0),
            ("damping", 0.0, 1e4), ("contact_margin", 0.0, 0.05),
            ("penetration_tolerance", 0.0, 1e-3), ("chebyshev_rho", 0.0, 0.999),
            ("max_displacement", 0.005, 1.0),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float))
                                               and math.isfinite(value)
                                               and low <= value <= high):
                raise ValueError(f"{name} must be in [{low}, {high}], found {value!r}")
        if self.solver not in ("vbd", "xpbd"):
            raise ValueError(f"solver must be 'vbd' or 'xpbd', found {self.solver!r}")
        for name, low, high in (("iterations", 1, 1000), ("substeps", 1, 100),
                                ("local_iterations", 0, 1000), ("local_rings", 0, 20)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an int in [{low}, {high}], found {value!r}")


#: Wall solver of the dynamic env unless one is given: the calibrated wall with 5
#: Chebyshev-accelerated Gauss-Seidel sweeps per step (``chebyshev_rho=0.85``, see
#: :func:`cgail_sim.pbd.solve_vbd`) instead of the 10 plain sweeps of ``PBDConfig()``:
#: the wall step is ~35 % cheaper and at least as converged as 8 plain sweeps. Measured against
#: a 60-sweep reference over four beats (``bench/bench_wall.py --accuracy``), default anatomy:
#: rms particle error 1.05 mm (8 plain sweeps 1.16, 10 plain 1.01), ostium heartbeat amplitude
#: 5.4-9.5 % short (8 plain 7.6-13.9 %, 10 plain 6.4-10.8 %); elongated anatomy: 1.00 mm
#: (1.09, 0.95) and 3.6-11.5 % (9.9-16.9 %, 8.9-13.4 %). Random-action rollouts (12 episodes)
#: end with the same collisions as with 8 plain sweeps (11 at the same step, one a step
#: earlier), contact forces within 0.02 N (median) of 20 plain sweeps (8 plain: 0.024 N).
#: ``rho`` 0.95 overshoots (amplitudes 10-60 % too large); 0.85 leaves a margin.
DYNAMIC_PBD_CONFIG = PBDConfig(iterations=5, chebyshev_rho=0.85)


@dataclass(frozen=True)
class WallTopology:
    """Constraint sets and per-particle quantities of one mesh (rest shape), SI units."""

    rest: np.ndarray
    """(N, 3) rest positions, m."""
    mass: np.ndarray
    """(N,) particle masses, kg."""
    area: np.ndarray
    """(N,) vertex area shares, m^2."""
    inv_mass: np.ndarray
    """(N,) inverse masses, 1/kg; 0 for fixed and annulus (kinematic) particles."""
    edges: np.ndarray
    """(E, 2) mesh edges (stretch constraints)."""
    edge_rest: np.ndarray
    """(E,) rest lengths, m."""
    edge_k: np.ndarray
    """(E,) small-strain stretch stiffness ``E h A_e / L0^2``, N/m."""
    hinges: np.ndarray
    """(H, 2) vertex pairs opposite interior edges (bending constraints)."""
    hinge_rest: np.ndarray
    """(H,) rest distances, m."""
    hinge_k: np.ndarray
    """(H,) bending spring stiffness, N/m."""
    tether_k: np.ndarray
    """(N,) tether stiffness, N/m (0 for kinematic particles)."""
    fixed: np.ndarray
    """(K,) fixed particle indices."""
    annulus: np.ndarray
    """(R,) annulus particle indices driven by the heartbeat (fixed ones excluded)."""
    max_edge: float
    """Longest rest edge, m."""
    adj_ptr: np.ndarray
    """(N+1,) CSR offsets of the springs (edges and hinges) incident to each particle."""
    adj_other: np.ndarray
    """(S,) the other particle of each incident spring."""
    adj_k: np.ndarray
    """(S,) small-strain stiffness of each incident spring, N/m."""
    adj_rest: np.ndarray
    """(S,) rest length of each incident spring, m."""
    adj_edge: np.ndarray
    """(S,) index into :attr:`edges` for stretch springs (their stiffening factor), -1 for
    bending springs."""
    vertex_order: np.ndarray
    """(N,) particle visiting order of the block Gauss-Seidel sweep: colour groups of
    particles that share no spring, so consecutive updates are independent."""
    ell_other: np.ndarray
    """(N, W) the springs of each free particle as a padded row (:func:`padded_springs`): the
    other particle (the particle itself in padding slots)."""
    ell_k: np.ndarray
    """(N, W) small-strain stiffness of each row slot, N/m (0 in padding slots)."""
    ell_rest: np.ndarray
    """(N, W) rest length of each row slot, m."""
    ell_edge: np.ndarray
    """(N, W) index into :attr:`edges` of each row slot, -1 for bending springs and padding."""


def _color_order(pairs: np.ndarray, n: int) -> np.ndarray:
    """Permutation of ``pairs`` grouping them into sets that share no vertex (greedy colouring).

    Consecutive Gauss-Seidel projections then touch different particles, so the CPU can
    overlap them instead of waiting on each other's writes (about 3x faster here); the sweep
    stays sequential and deterministic.
    """
    color = np.full(len(pairs), -1, dtype=np.int64)
    used: list[set[int]] = [set() for _ in range(n)]
    for e, (i, j) in enumerate(pairs.tolist()):
        taken = used[i] | used[j]
        c = 0
        while c in taken:
            c += 1
        color[e] = c
        used[i].add(c)
        used[j].add(c)
    return np.argsort(color, kind="stable")


def _color_order_vertices(adj_ptr: np.ndarray, adj_other: np.ndarray, n: int) -> np.ndarray:
    """Particles ordered by a greedy colouring of the spring graph (no spring inside a colour)."""
    color = np.full(n, -1, dtype=np.int64)
    ptr = adj_ptr.tolist()
    other = adj_other.tolist()
    for i in range(n):
        taken = {int(color[j]) for j in other[ptr[i]:ptr[i + 1]]}
        c = 0
        while c in taken:
            c += 1
        color[i] = c
    return np.argsort(color, kind="stable").astype(np.int64)


def build_topology(vertices: np.ndarray, faces: np.ndarray, fixed: np.ndarray,
                   annulus: np.ndarray, config: PBDConfig) -> WallTopology:
    """Derive the constraints of a closed triangle mesh (caps included) from its rest shape.

    Args:
        vertices: (N, 3) rest positions, m.
        faces: (M, 3) triangles (all of them: caps keep their shape too).
        fixed: indices held at rest.
        annulus: indices prescribed by the heartbeat.
        config: material parameters.
    """
    x = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = x.shape[0]
    if x.ndim != 2 or x.shape[1] != 3 or n < 3:
        raise ValueError(f"vertices must have shape (N>=3, 3), found {x.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.size == 0:
        raise ValueError(f"faces must have shape (M>=1, 3), found {f.shape}")
    if f.min() < 0 or f.max() >= n:
        raise ValueError(
            f"faces must index vertices in [0, {n - 1}], found [{f.min()}, {f.max()}]")
    fixed = np.unique(np.asarray(fixed, dtype=np.int64))
    annulus = np.setdiff1d(np.asarray(annulus, dtype=np.int64), fixed)
    for name, idx in (("fixed", fixed), ("annulus", annulus)):
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise ValueError(f"{name} vertex indices must be in [0, {n - 1}], found {idx}")

    tri = x[f]
    face_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                      axis=1)
    area = np.zeros(n)
    np.add.at(area, f.ravel(), np.repeat(face_area / 3.0, 3))
    if np.any(area <= 0):
        raise ValueError(f"every vertex must belong to a triangle of non-zero area, found "
                         f"{int(np.sum(area <= 0))} that do not")
    mass = config.density * config.thickness * area
    kinematic = np.zeros(n, dtype=bool)
    kinematic[fixed] = True
    kinematic[annulus] = True
    inv_mass = np.where(kinematic, 0.0, 1.0 / mass)

    # Edges with their adjacent faces (local edge k = (f_k, f_{k+1}), opposite vertex f_{k+2}).
    he = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)
    opp = np.roll(f, -2, axis=1).reshape(-1)
    he_face = np.repeat(np.arange(len(f)), 3)
    key = np.sort(he, axis=1)
    edges, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    # Reorder the edges into vertex-disjoint colour groups (see _color_order).
    perm = _color_order(edges, n)
    rank = np.empty_like(perm)
    rank[perm] = np.arange(len(perm))
    edges = edges[perm]
    inv = rank[inv]
    edge_area = np.zeros(len(edges))
    np.add.at(edge_area, inv, face_area[he_face])
    edge_rest = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
    edge_k = config.youngs_modulus * config.thickness * edge_area / edge_rest**2

    # Hinges: the two opposite vertices of each edge shared by exactly two triangles.
    order = np.argsort(inv, kind="stable")
    counts = np.bincount(inv, minlength=len(edges))
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    two = np.flatnonzero(counts == 2)
    hinges = np.stack([opp[order[first[two]]], opp[order[first[two] + 1]]], axis=1)
    keep = hinges[:, 0] != hinges[:, 1]
    hinge_edge_k = edge_k[two][keep]
    hinges = hinges[keep]
    if config.bending_ratio == 0.0:  # no bending springs at all
        hinges = hinges[:0]
        hinge_edge_k = hinge_edge_k[:0]
    hperm = _color_order(hinges, n)
    hinges = hinges[hperm]
    hinge_edge_k = hinge_edge_k[hperm]
    hinge_rest = np.linalg.norm(x[hinges[:, 0]] - x[hinges[:, 1]], axis=1)
    hinge_k = config.bending_ratio * hinge_edge_k

    tether_k = np.where(kinematic, 0.0, config.tether_stiffness * area)

    # Per-particle incidence (CSR) of all springs, both directions.
    src = np.concatenate([edges[:, 0], edges[:, 1], hinges[:, 0], hinges[:, 1]])
    dst = np.concatenate([edges[:, 1], edges[:, 0], hinges[:, 1], hinges[:, 0]])
    eidx = np.arange(len(edges))
    kind = np.concatenate([eidx, eidx, np.full(2 * len(hinges), -1)])
    kk = np.concatenate([edge_k, edge_k, hinge_k, hinge_k])
    rr = np.concatenate([edge_rest, edge_rest, hinge_rest, hinge_rest])
    o = np.argsort(src, kind="stable")
    adj_ptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=n))]).astype(np.int64)
    vertex_order = _color_order_vertices(adj_ptr, dst[o], n)
    adj_other = np.ascontiguousarray(dst[o], dtype=np.int64)
    adj_k = np.ascontiguousarray(kk[o])
    adj_rest = np.ascontiguousarray(rr[o])
    adj_edge = np.ascontiguousarray(kind[o], dtype=np.int64)
    ell_other, ell_k, ell_rest, ell_edge = padded_springs(inv_mass, adj_ptr, adj_other, adj_k,
                                                          adj_rest, adj_edge)
    return WallTopology(
        rest=x.copy(), mass=mass, area=area, inv_mass=inv_mass,
        edges=np.ascontiguousarray(edges, dtype=np.int64), edge_rest=edge_rest, edge_k=edge_k,
        hinges=np.ascontiguousarray(hinges, dtype=np.int64), hinge_rest=hinge_rest,
        hinge_k=hinge_k, tether_k=tether_k, fixed=fixed, annulus=annulus,
        max_edge=float(edge_rest.max()),
        adj_ptr=adj_ptr, adj_other=adj_other, adj_k=adj_k, adj_rest=adj_rest, adj_edge=adj_edge,
        vertex_order=vertex_order, ell_other=ell_other, ell_k=ell_k, ell_rest=ell_rest,
        ell_edge=ell_edge,
    )


@njit(cache=True)
def secant_factor(x, edges, edge_rest, b, out, relax=1.0):
    """Secant stiffening ``g(eps) = (exp(b eps) - 1) / (b eps)`` of every edge (1 if eps <= 0).

    With ``relax < 1`` the new value is blended into ``out``: ``out += relax (g - out)``. The
    plain lagged update (relax = 1) is a fixed-point iteration that diverges above ~10 %
    uniaxial strain with b ~ 16 (measured on the calibration strip); relax = 0.5 converges to
    the exact law there and at 16 %.
    """
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        d2 = 0.0
        for a in range(3):
            d2 += (x[i, a] - x[j, a]) ** 2
        z = b * (np.sqrt(d2) / edge_rest[e] - 1.0)
        if z <= 1e-9:
            g = 1.0
        else:
            z = min(z, _Z_MAX)
            g = np.expm1(z) / z
        out[e] += relax * (g - out[e])


@njit(cache=True)
def largest_displacement(x, rest):
    """``(index, distance)`` of the particle furthest from its rest position (a NaN position
    counts as infinitely far), m."""
    worst = -1.0
    k = 0
    for i in range(x.shape[0]):
        d2 = 0.0
        for a in range(3):
            d2 += (x[i, a] - rest[i, a]) ** 2
        if not d2 <= 1e300:  # NaN or inf
            return i, np.inf
        if d2 > worst:
            worst = d2
            k = i
    return k, math.sqrt(max(worst, 0.0))


@njit(cache=True)
def predict(x, v, inv_mass, dt, damping, x_old, v_damped):
    """Damp velocities and move free particles to their inertial prediction (in place)."""
    decay = np.exp(-damping * dt)
    for i in range(x.shape[0]):
        for a in range(3):
            x_old[i, a] = x[i, a]
            if inv_mass[i] > 0.0:
                v[i, a] *= decay
                x[i, a] += v[i, a] * dt
            v_damped[i, a] = v[i, a]


@njit(cache=True)
def _coefficients(w, pairs, k, factor, use_factor, dt2, alpha, inv_den):
    """Per-constraint XPBD constants of a substep: alpha~ = 1/(k dt^2), 1/(w_i + w_j + alpha~)."""
    for e in range(pairs.shape[0]):
        kk = k[e] * factor[e] if use_factor else k[e]
        a = 1.0 / (kk * dt2) if kk > 0.0 else 1e30
        wsum = w[pairs[e, 0]] + w[pairs[e, 1]]
        alpha[e] = a
        inv_den[e] = 1.0 / (wsum + a) if wsum > 0.0 else 0.0


@njit(cache=True)
def _distance_sweep(x, w, pairs, rest_len, alpha, inv_den, lam):
    for e in range(pairs.shape[0]):
        if inv_den[e] == 0.0:
            continue
        i = pairs[e, 0]
        j = pairs[e, 1]
        dx = x[i, 0] - x[j, 0]
        dy = x[i, 1] - x[j, 1]
        dz = x[i, 2] - x[j, 2]
        ln = np.sqrt(dx * dx + dy * dy + dz * dz)
        if ln < 1e-15:
            continue
        dl = (rest_len[e] - ln - alpha[e] * lam[e]) * inv_den[e]
        lam[e] += dl
        s = dl / ln
        si = w[i] * s
        sj = w[j] * s
        x[i, 0] += si * dx
        x[i, 1] += si * dy
        x[i, 2] += si * dz
        x[j, 0] -= sj * dx
        x[j, 1] -= sj * dy
        x[j, 2] -= sj * dz


@njit(cache=True)
def _tether_sweep(x, w, rest, alpha, inv_den, lam):
    for i in range(x.shape[0]):
        if inv_den[i] == 0.0:
            continue
        dx = x[i, 0] - rest[i, 0]
        dy = x[i, 1] - rest[i, 1]
        dz = x[i, 2] - rest[i, 2]
        ln = np.sqrt(dx * dx + dy * dy + dz * dz)
        if ln < 1e-15:
            continue
        dl = (-ln - alpha[i] * lam[i]) * inv_den[i]
        lam[i] += dl
        s = w[i] * dl / ln
        x[i, 0] += s * dx
        x[i, 1] += s * dy
        x[i, 2] += s * dz


@njit(cache=True)
def solve(x, inv_mass, rest, edges, edge_rest, edge_k, factor, hinges, hinge_rest, hinge_k,
          tether_k, dt, iterations, faces, face_edges, face_normals, vertex_normals,
          edge_normals, pair_face, pair_seg, points, radius, impulse, touched):
    """XPBD constraint solve of one substep (in place); returns the last contact violation."""
    dt2 = dt * dt
    n = x.shape[0]
    ne = edges.shape[0]
    nh = hinges.shape[0]
    lam_e = np.zeros(ne)
    lam_h = np.zeros(nh)
    lam_t = np.zeros(n)
    a_e = np.empty(ne)
    d_e = np.empty(ne)
    a_h = np.empty(nh)
    d_h = np.empty(nh)
    a_t = np.empty(n)
    d_t = np.empty(n)
    _coefficients(inv_mass, edges, edge_k, factor, True, dt2, a_e, d_e)
    _coefficients(inv_mass, hinges, hinge_k, factor, False, dt2, a_h, d_h)
    for i in range(n):
        if inv_mass[i] > 0.0 and tether_k[i] > 0.0:
            a_t[i] = 1.0 / (tether_k[i] * dt2)
            d_t[i] = 1.0 / (inv_mass[i] + a_t[i])
        else:
            a_t[i] = 0.0
            d_t[i] = 0.0
    has_contact = pair_face.shape[0] > 0
    worst = 0.0
    bary, anchor, normal, mark = linearize_contacts(
        x, rest, faces, face_edges, face_normals, vertex_normals, edge_normals, pair_face,
        pair_seg, points, radius)
    for _ in range(iterations):
        _distance_sweep(x, inv_mass, edges, edge_rest, a_e, d_e, lam_e)
        _distance_sweep(x, inv_mass, hinges, hinge_rest, a_h, d_h, lam_h)
        _tether_sweep(x, inv_mass, rest, a_t, d_t, lam_t)
        if has_contact:
            project_planes(x, inv_mass, faces, pair_face, bary, anchor, normal, mark, radius,
                           dt, impulse, touched)
    if has_contact:
        for _ in range(2):
            worst = project_contacts(x, rest, inv_mass, faces, face_edges, face_normals,
                                     vertex_normals, edge_normals, pair_face, pair_seg, points,
                                     radius, dt, impulse, touched)
    return worst


#: Spring slots of a padded row processed together (one SIMD vector of doubles).
_LANES = 8


@njit(cache=True)
def padded_springs(inv_mass, adj_ptr, adj_other, adj_k, adj_rest, adj_edge):
    """The springs of every free particle as fixed-width rows (the ELL sparse layout).

    Row ``i`` lists the springs of particle ``i`` (as in the CSR ``adj_*`` arrays), padded to
    a width that is a multiple of :data:`_LANES` with zero-stiffness springs from ``i`` to
    itself; rows of kinematic particles are all padding (they are never swept).

    Returns:
        ``(other, k, rest, edge)``, each (N, W): other particle, small-strain stiffness (N/m),
        rest length (m) and stretch-edge index (-1 for bending springs and padding).
    """
    n = adj_ptr.shape[0] - 1
    width = 1
    for i in range(n):
        if inv_mass[i] > 0.0:
            width = max(width, adj_ptr[i + 1] - adj_ptr[i])
    width = (width + _LANES - 1) // _LANES * _LANES
    other = np.empty((n, width), np.int64)
    k = np.zeros((n, width))
    rest = np.zeros((n, width))
    edge = np.full((n, width), -1, np.int64)
    for i in range(n):
        lo = adj_ptr[i]
        count = adj_ptr[i + 1] - lo if inv_mass[i] > 0.0 else 0
        for s in range(width):
            if s < count:
                other[i, s] = adj_other[lo + s]
                k[i, s] = adj_k[lo + s]
                rest[i, s] = adj_rest[lo + s]
                edge[i, s] = adj_edge[lo + s]
            else:
                other[i, s] = i
    return other, k, rest, edge


@njit(cache=True)
def _padded_secant(ell_k, ell_edge, factor, out):
    """``out = k * factor[edge]`` for the stretch springs, ``k`` otherwise (padded rows)."""
    for i in range(ell_k.shape[0]):
        for s in range(ell_k.shape[1]):
            e = ell_edge[i, s]
            out[i, s] = ell_k[i, s] * factor[e] if e >= 0 else ell_k[i, s]


@njit(cache=True, fastmath=True)
def _sweep_padded(x, y, inv_mass, mass, inv_h2, tether_k, rest, order, ell_other, ell_keff,
                  ell_rest):
    """One block Gauss-Seidel sweep with the lagged secant springs in padded rows (in place).

    The fixed-width rows let the compiler vectorise the spring loop (packed sqrt and divide):
    ~12 % faster per sweep than the CSR loop of :func:`_sweep_csr` on the aorta mesh, the same
    arithmetic per spring (the row sums are reassociated, as ``fastmath`` allows anyway);
    padding springs have zero stiffness and add exactly 0.
    """
    width = ell_other.shape[1]
    for oi in range(order.shape[0]):
        i = order[oi]
        if inv_mass[i] <= 0.0:
            continue
        mh = mass[i] * inv_h2
        kt = tether_k[i]
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        g0 = mh * (xi0 - y[i, 0]) + kt * (xi0 - rest[i, 0])
        g1 = mh * (xi1 - y[i, 1]) + kt * (xi1 - rest[i, 1])
        g2 = mh * (xi2 - y[i, 2]) + kt * (xi2 - rest[i, 2])
        d = mh + kt
        h00 = d
        h11 = d
        h22 = d
        h01 = 0.0
        h02 = 0.0
        h12 = 0.0
        for b in range(width // _LANES):
            for lane in range(_LANES):
                a = b * _LANES + lane
                j = ell_other[i, a]
                dx = xi0 - x[j, 0]
                dy = xi1 - x[j, 1]
                dz = xi2 - x[j, 2]
                ln = np.sqrt(dx * dx + dy * dy + dz * dz)
                k = ell_keff[i, a] if ln >= 1e-15 else 0.0
                inv = 1.0 / max(ln, 1e-15)
                nx = dx * inv
                ny = dy * inv
                nz = dz * inv
                fs = k * (ln - ell_rest[i, a])
                g0 += fs * nx
                g1 += fs * ny
                g2 += fs * nz
                c = max(fs * inv, 0.0)  # geometric stiffness k (1 - L0 / L), clamped to PSD
                kn = k - c
                h00 += kn * nx * nx + c
                h11 += kn * ny * ny + c
                h22 += kn * nz * nz + c
                h01 += kn * nx * ny
                h02 += kn * nx * nz
                h12 += kn * ny * nz
        # Solve H d = -g (symmetric 3x3, Cramer's rule).
        c00 = h11 * h22 - h12 * h12
        c01 = h02 * h12 - h01 * h22
        c02 = h01 * h12 - h02 * h11
        det = h00 * c00 + h01 * c01 + h02 * c02
        if det <= 1e-300:
            continue
        c11 = h00 * h22 - h02 * h02
        c12 = h01 * h02 - h00 * h12
        c22 = h00 * h11 - h01 * h01
        idet = 1.0 / det
        x[i, 0] = xi0 - (c00 * g0 + c01 * g1 + c02 * g2) * idet
        x[i, 1] = xi1 - (c01 * g0 + c11 * g1 + c12 * g2) * idet
        x[i, 2] = xi2 - (c02 * g0 + c12 * g1 + c22 * g2) * idet


@njit(cache=True, fastmath=True)
def _sweep_csr(x, y, inv_mass, mass, inv_h2, tether_k, rest, order, adj_ptr, adj_other, adj_k,
               adj_rest, adj_edge, keff, exact_b):
    """One sweep over the CSR springs; with ``exact_b > 0`` the exact stiffening law."""
    exact = exact_b > 0.0
    for oi in range(order.shape[0]):
        i = order[oi]
        if inv_mass[i] <= 0.0:
            continue
        mh = mass[i] * inv_h2
        kt = tether_k[i]
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        g0 = mh * (xi0 - y[i, 0]) + kt * (xi0 - rest[i, 0])
        g1 = mh * (xi1 - y[i, 1]) + kt * (xi1 - rest[i, 1])
        g2 = mh * (xi2 - y[i, 2]) + kt * (xi2 - rest[i, 2])
        d = mh + kt
        h00 = d
        h11 = d
        h22 = d
        h01 = 0.0
        h02 = 0.0
        h12 = 0.0
        for a in range(adj_ptr[i], adj_ptr[i + 1]):
            j = adj_other[a]
            dx = xi0 - x[j, 0]
            dy = xi1 - x[j, 1]
            dz = xi2 - x[j, 2]
            ln = np.sqrt(dx * dx + dy * dy + dz * dz)
            if ln < 1e-15:
                continue
            l0 = adj_rest[a]
            inv = 1.0 / ln
            nx = dx * inv
            ny = dy * inv
            nz = dz * inv
            if exact and adj_edge[a] >= 0:
                # Exact stiffening law: force k L0 / b expm1(z), tangent k exp(z).
                z = exact_b * (ln - l0) / l0
                if z <= 0.0:
                    k = adj_k[a]
                    fs = k * (ln - l0)
                    kt = k
                elif z <= _Z_MAX:
                    k = adj_k[a] * np.expm1(z) / z
                    fs = k * (ln - l0)
                    kt = adj_k[a] * np.exp(z)
                else:
                    k = adj_k[a] * _G_MAX
                    fs = k * (ln - l0)
                    kt = k
            else:
                kt = keff[a]
                fs = kt * (ln - l0)
            g0 += fs * nx
            g1 += fs * ny
            g2 += fs * nz
            c = fs * inv  # geometric stiffness k (1 - L0 / L), clamped to PSD
            if c < 0.0:
                c = 0.0
            kn = kt - c
            h00 += kn * nx * nx + c
            h11 += kn * ny * ny + c
            h22 += kn * nz * nz + c
            h01 += kn * nx * ny
            h02 += kn * nx * nz
            h12 += kn * ny * nz
        # Solve H d = -g (symmetric 3x3, Cramer's rule).
        c00 = h11 * h22 - h12 * h12
        c01 = h02 * h12 - h01 * h22
        c02 = h01 * h12 - h02 * h11
        det = h00 * c00 + h01 * c01 + h02 * c02
        if det <= 1e-300:
            continue
        c11 = h00 * h22 - h02 * h02
        c12 = h01 * h02 - h00 * h12
        c22 = h00 * h11 - h01 * h01
        idet = 1.0 / det
        x[i, 0] = xi0 - (c00 * g0 + c01 * g1 + c02 * g2) * idet
        x[i, 1] = xi1 - (c01 * g0 + c11 * g1 + c12 * g2) * idet
        x[i, 2] = xi2 - (c02 * g0 + c12 * g1 + c22 * g2) * idet


@njit(cache=True, fastmath=True)
def _iterate(x, inv_mass, mass, rest, tether_k, order, dt, iterations, faces, face_edges,
             face_normals, vertex_normals, edge_normals, pair_face, pair_seg, points, radius,
             impulse, touched, rho, exact_b, adj_ptr, adj_other, adj_k, adj_rest, adj_edge,
             keff, ell_other, ell_keff, ell_rest):
    """The sweeps and contact projections of :func:`solve_vbd`: CSR springs (``keff``) when
    ``exact_b > 0``, padded rows (``ell_*``) otherwise."""
    y = x.copy()
    inv_h2 = 1.0 / (dt * dt)
    exact = exact_b > 0.0
    has_contact = pair_face.shape[0] > 0
    worst = 0.0
    bary, anchor, normal, mark = linearize_contacts(
        x, rest, faces, face_edges, face_normals, vertex_normals, edge_normals, pair_face,
        pair_seg, points, radius)
    accel = rho > 0.0 and iterations > 1
    # The contact neighbourhood takes plain sweeps (see solve_vbd).
    plain = (contact_faces_neighbourhood(faces, pair_face, adj_ptr, adj_other, _PLAIN_RINGS)
             if accel and has_contact else np.zeros(0, np.bool_))
    prev = x.copy() if accel else np.empty((0, 3))  # x_(n-1)
    prev2 = x.copy() if accel else np.empty((0, 3))  # x_(n-2)
    omega = 1.0
    for it in range(iterations):
        if exact:
            _sweep_csr(x, y, inv_mass, mass, inv_h2, tether_k, rest, order, adj_ptr, adj_other,
                       adj_k, adj_rest, adj_edge, keff, exact_b)
        else:
            _sweep_padded(x, y, inv_mass, mass, inv_h2, tether_k, rest, order, ell_other,
                          ell_keff, ell_rest)
        if accel:
            if it == 1:
                omega = 2.0 / (2.0 - rho * rho)
            elif it > 1:
                omega = 4.0 / (4.0 - rho * rho * omega)
            # Flat over all particles: those the sweep left alone (kinematic, or outside
            # ``order``) have x = x_(n-1) = x_(n-2) and stay exactly where they are.
            xf = x.reshape(-1)
            p1 = prev.reshape(-1)
            p2 = prev2.reshape(-1)
            masked = plain.shape[0] > 0
            for a in range(xf.shape[0]):
                if masked and plain[a // 3]:
                    xn = xf[a]
                else:
                    xn = p2[a] + omega * (xf[a] - p2[a])
                p2[a] = p1[a]
                p1[a] = xn
                xf[a] = xn
        if has_contact:
            project_planes(x, inv_mass, faces, pair_face, bary, anchor, normal, mark, radius,
                           dt, impulse, touched)
            if accel:
                prev[:] = x
    if has_contact:
        for _ in range(2):
            worst = project_contacts(x, rest, inv_mass, faces, face_edges, face_normals,
                                     vertex_normals, edge_normals, pair_face, pair_seg, points,
                                     radius, dt, impulse, touched)
    return worst


@njit(cache=True, fastmath=True)
def solve_vbd(x, inv_mass, mass, rest, adj_ptr, adj_other, adj_k, adj_rest, adj_edge, factor,
              tether_k, order, dt, iterations, faces, face_edges, face_normals, vertex_normals,
              edge_normals, pair_face, pair_seg, points, radius, impulse, touched, exact_b=0.0,
              rho=0.0):
    """Vertex-block Gauss-Seidel solve of one (sub)step (in place); returns the contact violation.

    Each sweep visits the particles (colour order) and moves particle i by one Newton step of
    the incremental potential restricted to it,
    ``E_i = m_i / (2 dt^2) |x_i - y_i|^2 + k_t / 2 |x_i - r_i|^2 + sum_s k_s / 2 (L_s - L0_s)^2``
    (``y`` the inertial prediction, the sum over the springs at i), with the spring Hessian
    ``k n n^T + k max(0, 1 - L0 / L) (I - n n^T)`` (projected to positive semi-definite).
    ``order`` may list a subset of the particles (a local solve around the contacts). The
    contact projections follow each sweep, and twice more at the end. With
    ``exact_b > 0`` the stretch springs use the exact stiffening law and its tangent inside
    the sweep instead of the lagged secant ``factor`` (costlier: used by the calibration).
    With ``0 < rho < 1`` the sweeps are Chebyshev-accelerated (Wang 2015; Chen et al. 2024,
    "Vertex Block Descent", section on acceleration): after sweep ``n`` every particle of
    ``order`` is moved to ``x_(n-2) + w_n (x - x_(n-2))`` with ``w_1 = 1``,
    ``w_2 = 2 / (2 - rho^2)``, ``w_n = 4 / (4 - rho^2 w_(n-1))``, ``rho`` an estimate of the
    spectral radius of the plain sweep. The particles within ``_PLAIN_RINGS`` (3) springs of a
    contact triangle are not extrapolated: there the contact projections move particles
    between sweeps and the dent's springs sit far up the stiffening curve, so the iteration is
    not the linear one ``rho`` was fitted to; extrapolated, a catheter riding the wall of the
    built-in aortas pumped a dent to 25 mm (and past the 40 mm bound on harder pushes) where
    plain sweeps keep it at the indentation (``bench/bench_wall.py --contact``).

    Compiled with ``fastmath`` (reassociated sums, ~20 % faster; results move by ~1e-13 m and
    stay deterministic run to run on one machine).
    """
    if exact_b > 0.0:
        # Effective (secant) stiffness of every incident spring (bending springs: k).
        keff = np.empty(adj_k.shape[0])
        for a in range(adj_k.shape[0]):
            e = adj_edge[a]
            keff[a] = adj_k[a] * factor[e] if e >= 0 else adj_k[a]
        ell_other = np.empty((0, 0), np.int64)
        ell_keff = np.empty((0, 0))
        ell_rest = np.empty((0, 0))
    else:
        keff = np.empty(0)
        ell_other, ell_k, ell_rest, ell_edge = padded_springs(inv_mass, adj_ptr, adj_other,
                                                              adj_k, adj_rest, adj_edge)
        ell_keff = np.empty_like(ell_k)
        _padded_secant(ell_k, ell_edge, factor, ell_keff)
    return _iterate(x, inv_mass, mass, rest, tether_k, order, dt, iterations, faces, face_edges,
                    face_normals, vertex_normals, edge_normals, pair_face, pair_seg, points,
                    radius, impulse, touched, rho, exact_b, adj_ptr, adj_other, adj_k, adj_rest,
                    adj_edge, keff, ell_other, ell_keff, ell_rest)


@njit(cache=True)
def contact_faces_neighbourhood(faces, pair_face, adj_ptr, adj_other, rings):
    """(N,) bool: the vertices of the contact candidate triangles ``pair_face`` and every
    particle within ``rings`` springs of them."""
    n = adj_ptr.shape[0] - 1
    active = np.zeros(n, np.bool_)
    for p in range(pair_face.shape[0]):
        for k in range(3):
            active[faces[pair_face[p], k]] = True
    for _ in range(rings):
        grown = active.copy()
        for i in range(n):
            if active[i]:
                for a in range(adj_ptr[i], adj_ptr[i + 1]):
                    grown[adj_other[a]] = True
        active = grown
    return active


@njit(cache=True)
def contact_neighbourhood(touched, adj_ptr, adj_other, vertex_order, rings):
    """Particles within ``rings`` springs of a particle a contact moved, in sweep order."""
    n = touched.shape[0]
    active = np.zeros(n, np.bool_)
    for i in range(n):
        if touched[i] > 0:
            active[i] = True
    for _ in range(rings):
        grown = active.copy()
        for i in range(n):
            if active[i]:
                for a in range(adj_ptr[i], adj_ptr[i + 1]):
                    grown[adj_other[a]] = True
        active = grown
    count = 0
    for i in range(n):
        if active[i]:
            count += 1
    out = np.empty(count, np.int64)
    k = 0
    for oi in range(n):
        i = vertex_order[oi]
        if active[i]:
            out[k] = i
            k += 1
    return out


@njit(cache=True)
def internal_forces(x, rest, edges, edge_rest, edge_k, b, hinges, hinge_rest, hinge_k,
                    tether_k):
    """(N, 3) elastic force of the wall material on every particle at positions x, N.

    Stretch uses the full (not lagged) secant law ``k_e g(eps) (L - L0)``, bending and tethers
    are linear springs; kinematic particles get their share too (their reaction).
    """
    n = x.shape[0]
    f = np.zeros((n, 3))
    for group in range(2):
        pairs = edges if group == 0 else hinges
        rl = edge_rest if group == 0 else hinge_rest
        kk = edge_k if group == 0 else hinge_k
        for e in range(pairs.shape[0]):
            i = pairs[e, 0]
            j = pairs[e, 1]
            dx = x[i, 0] - x[j, 0]
            dy = x[i, 1] - x[j, 1]
            dz = x[i, 2] - x[j, 2]
            ln = np.sqrt(dx * dx + dy * dy + dz * dz)
            if ln < 1e-15:
                continue
            g = 1.0
            if group == 0:
                z = min(b * (ln / rl[e] - 1.0), _Z_MAX)
                if z > 1e-9:
                    g = np.expm1(z) / z
            s = kk[e] * g * (ln - rl[e]) / ln
            f[i, 0] -= s * dx
            f[i, 1] -= s * dy
            f[i, 2] -= s * dz
            f[j, 0] += s * dx
            f[j, 1] += s * dy
            f[j, 2] += s * dz
    for i in range(n):
        for a in range(3):
            f[i, a] -= tether_k[i] * (x[i, a] - rest[i, a])
    return f


@njit(cache=True)
def particle_forces(x, rest, idx, adj_ptr, adj_other, adj_k, adj_rest, adj_edge, b, tether_k):
    """(len(idx), 3) elastic force on the particles ``idx`` only, N: the rows ``idx`` of
    :func:`internal_forces` (same law, summed over each particle's CSR springs, so equal to
    round-off), at a cost proportional to ``len(idx)`` instead of the whole mesh."""
    f = np.zeros((idx.shape[0], 3))
    for r in range(idx.shape[0]):
        i = idx[r]
        for a in range(adj_ptr[i], adj_ptr[i + 1]):
            j = adj_other[a]
            dx = x[i, 0] - x[j, 0]
            dy = x[i, 1] - x[j, 1]
            dz = x[i, 2] - x[j, 2]
            ln = np.sqrt(dx * dx + dy * dy + dz * dz)
            if ln < 1e-15:
                continue
            g = 1.0
            if adj_edge[a] >= 0:
                z = min(b * (ln / adj_rest[a] - 1.0), _Z_MAX)
                if z > 1e-9:
                    g = np.expm1(z) / z
            s = adj_k[a] * g * (ln - adj_rest[a]) / ln
            f[r, 0] -= s * dx
            f[r, 1] -= s * dy
            f[r, 2] -= s * dz
        for c in range(3):
            f[r, c] -= tether_k[i] * (x[i, c] - rest[i, c])
    return f


@njit(cache=True)
def step_vbd(x, v, x_old, v_damped, dp, factor, impulse, touched, inv_mass, mass, rest, edges,
             edge_rest, stiffening, relax, adj_ptr, adj_other, adj_k, adj_rest, adj_edge,
             tether_k, order, annulus, annulus_disp, fixed, h, damping, iterations,
             local_iterations, local_rings, faces, face_edges, face_normals, vertex_normals,
             edge_normals, tree_min, tree_max, tree_left, tree_right, tree_start, tree_count,
             tree_order, tree_fit, tree_nodes, points, radius, reach, rho=0.0, ell_other=None,
             ell_k=None, ell_rest=None, ell_edge=None):
    """One wall step of the VBD solver, all substeps in one call (in place).

    Per substep ``k`` (length ``h``): lagged secant update, inertial prediction, annulus at
    ``rest + annulus_disp[k]``, fixed particles at rest, contact broad + narrow phase against
    the capsule chain ``points`` (none when it is empty), global sweeps, local settling sweeps
    around the contacts, velocities and momentum change ``dp`` (accumulated). ``impulse``,
    ``touched`` and ``dp`` are accumulated (the caller clears them).

    The broad phase uses the BVH as last refit at positions ``tree_fit`` with every box grown
    by the largest per-axis particle displacement since then: the candidate pairs are a
    superset, in the same order, of those of a tree refit at the predicted positions, and the
    exact narrow phase keeps the same pairs, so no refit is needed inside the step. The tree
    is refit to the final positions at the end (and ``tree_fit`` updated).

    ``rho``: Chebyshev acceleration of the global sweeps (see :func:`solve_vbd`). ``ell_*``:
    the springs as padded rows (:func:`padded_springs`, :attr:`WallTopology.ell_other` ...);
    built from the CSR arrays when not given.

    Returns:
        The last contact violation of the last substep, m.
    """
    worst = 0.0
    n = x.shape[0]
    has_points = points.shape[0] > 0
    sweep_points = points if has_points else np.zeros((1, 3))
    if ell_other is None:
        e_other, e_k, e_rest, e_edge = padded_springs(inv_mass, adj_ptr, adj_other, adj_k,
                                                      adj_rest, adj_edge)
    else:
        e_other, e_k, e_rest, e_edge = ell_other, ell_k, ell_rest, ell_edge
    e_keff = np.empty_like(e_k)
    no_keff = np.empty(0)
    for k in range(annulus_disp.shape[0]):
        secant_factor(x, edges, edge_rest, stiffening, factor, relax)
        _padded_secant(e_k, e_edge, factor, e_keff)
        predict(x, v, inv_mass, h, damping, x_old, v_damped)
        for a in range(annulus.shape[0]):
            i = annulus[a]
            for c in range(3):
                x[i, c] = rest[i, c] + annulus_disp[k, c]
        for a in range(fixed.shape[0]):
            i = fixed[a]
            for c in range(3):
                x[i, c] = rest[i, c]
        if has_points:
            grow = 0.0
            for i in range(n):
                for c in range(3):
                    d = abs(x[i, c] - tree_fit[i, c])
                    if d > grow:
                        grow = d
            pf, ps = faces_near_segments_kernel(tree_min, tree_max, tree_left, tree_right,
                                                tree_start, tree_count, tree_order, points,
                                                reach + grow)
            pf, ps = narrow_pairs(x, faces, pf, ps, points, reach)
        else:
            pf = np.zeros(0, np.int64)
            ps = np.zeros(0, np.int64)
        worst = _iterate(x, inv_mass, mass, rest, tether_k, order, h, iterations, faces,
                         face_edges, face_normals, vertex_normals, edge_normals, pf, ps,
                         sweep_points, radius, impulse, touched, rho, 0.0, adj_ptr, adj_other,
                         adj_k, adj_rest, adj_edge, no_keff, e_other, e_keff, e_rest)
        if pf.shape[0] > 0 and local_iterations > 0:
            local = contact_neighbourhood(touched, adj_ptr, adj_other, order, local_rings)
            if local.shape[0] > 0:
                worst = _iterate(x, inv_mass, mass, rest, tether_k, local, h,
                                 local_iterations, faces, face_edges, face_normals,
                                 vertex_normals, edge_normals, pf, ps, sweep_points, radius,
                                 impulse, touched, 0.0, 0.0, adj_ptr, adj_other, adj_k,
                                 adj_rest, adj_edge, no_keff, e_other, e_keff, e_rest)
        for i in range(n):
            for c in range(3):
                vn = (x[i, c] - x_old[i, c]) / h
                dp[i, c] += mass[i] * (vn - v_damped[i, c])
                v[i, c] = vn
    refit_tree(x, faces, tree_order, tree_min, tree_max, tree_left, tree_right, tree_start,
               tree_count, tree_nodes)
    for i in range(n):
        for c in range(3):
            tree_fit[i, c] = x[i, c]
    return worst

"""The vessel wall seen by the environment: one API, a rigid and a deformable implementation.

* :class:`StaticWall` - the rest shape, never moves (the paper's static environment).
* :class:`DeformableWall` - PBD wall (:mod:`~cgail_sim.pbd`) driven by the heartbeat
  (:mod:`~cgail_sim.heartbeat`) and pushed by the catheter body
  (:mod:`~cgail_sim.contact`).

Both answer ray casts and tip-contact queries from the same numba BVH
(:mod:`~cgail_sim.raycast`) over the wall triangles only (caps are transparent), so with
the heartbeat off and no catheter contact the two give identical answers. Everything is
deterministic: the same calls give the same numbers. Units: m, s, N.

Typical use by the environment::

    wall = DeformableWall(anatomy)          # or StaticWall(anatomy)
    wall.reset()
    wall.step(t, dt, body_points, body_radius)
    hits = wall.raycast(origins, directions, ray_length)
    contact = wall.tip_contact(tip, body_radius, dt)
    target = wall.vertex_position(anatomy.ostium_vertices["left"])
"""

from __future__ import annotations

import itertools
import math
from typing import TYPE_CHECKING

import numpy as np

from cgail_sim.contact import Contact, narrow_pairs
from cgail_sim.heartbeat import Heartbeat, HeartbeatConfig
from cgail_sim.mesh_io import AnatomyError
from cgail_sim.pbd import (
    build_topology,
    largest_displacement,
    particle_forces,
    PBDConfig,
    predict,
    secant_factor,
    solve,
    step_vbd,
)
from cgail_sim.raycast import WallBVH

if TYPE_CHECKING:
    from cgail_sim.anatomy import Anatomy

#: Under-relaxation of the lagged secant stiffening update (see ``pbd.secant_factor``).
_SECANT_RELAX = 0.5
#: Slack of the side-continuity test of a deformable wall's tip query, m
#: (:meth:`DeformableWall._signed_distance`).
_SIDE_SLACK = 0.002

__all__ = ["Contact", "DeformableWall", "StaticWall", "WallError"]


class WallError(AnatomyError):
    """The deformable wall left its physical range (a particle beyond
    ``PBDConfig.max_displacement`` from rest): the simulation stops rather than go on with a
    blown-up wall. The usual cause is a catheter body outside the lumen (an anatomy whose
    introducer leaves it)."""


def _check_finite_scalar(name: str, value: float, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ValueError(f"{name} must be a real number, found {value!r}")
    v = float(value)
    if not math.isfinite(v) or (positive and v <= 0.0):
        raise ValueError(f"{name} must be a finite number{' > 0' if positive else ''}, "
                         f"found {value!r}")
    return v


def _check_points(name: str, points: np.ndarray, allow_empty: bool) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 1 and p.shape == (3,):
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 3 or (p.shape[0] == 0 and not allow_empty):
        raise ValueError(f"{name} must have shape (B, 3), found {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name} must be finite, found NaN or inf")
    return np.ascontiguousarray(p)


class StaticWall:
    """Rigid wall at the anatomy's rest shape.

    Args:
        anatomy: the vessel (its wall faces are the obstacles; caps are transparent).
    """

    def __init__(self, anatomy: Anatomy):
        self.anatomy = anatomy
        self._rest = np.ascontiguousarray(anatomy.vertices, dtype=np.float64)
        self.vertices = self._rest.copy()
        self._bvh = WallBVH(self._rest, anatomy.faces, anatomy.wall_face_mask)
        self._tolerance = 0.0

    def reset(self) -> None:
        """Back to the rest shape, t = 0 (nothing to do for a rigid wall)."""
        self.vertices = self._rest.copy()

    def step(self, t: float, dt: float, body_points: np.ndarray, body_radius: float) -> None:
        """Nothing moves in a rigid wall (the arguments are still validated)."""
        _check_finite_scalar("t", t)
        _check_finite_scalar("dt", dt, positive=True)
        pts = _check_points("body_points", body_points, allow_empty=True)
        if pts.shape[0]:
            _check_finite_scalar("body_radius", body_radius, positive=True)

    @property
    def bvh(self) -> WallBVH:
        """The bounding-volume tree the wall casts rays on (for kernels that call the ray
        kernel directly, e.g. the planner's rollout). A deformable wall refits it lazily: cast a
        ray first to bring it up to date."""
        return self._bvh

    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                ) -> np.ndarray:
        """(R,) distance along each unit direction to the first wall hit, m.

        Args:
            origins: (R, 3) ray origins, m.
            directions: (R, 3) unit directions.
            max_dist: ray length, m; returned where no wall face is hit within it.
        """
        return self._bvh.raycast(origins, directions, max_dist)

    def cast_unchecked(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                       ) -> np.ndarray:
        """:meth:`raycast` for trusted input (the hot path of the environment's own rays:
        C-contiguous float64 (R, 3) arrays, a float > 0), without the checks."""
        return self._bvh.cast_unchecked(origins, directions, max_dist)

    def distance(self, points: np.ndarray, max_dist: float) -> np.ndarray:
        """(P,) distance from each point to the nearest point of the wall, m (unsigned: a point
        beyond the wall has its distance to the surface too); inf where none is within
        ``max_dist``. The ``paper_code`` observation's probes read it.

        Args:
            points: (P, 3) query points, m.
            max_dist: search radius, m (> 0).
        """
        pts = _check_points("points", points, allow_empty=True)
        _check_finite_scalar("max_dist", max_dist, positive=True)
        return self.distance_unchecked(pts, float(max_dist))

    def distance_unchecked(self, points: np.ndarray, max_dist: float) -> np.ndarray:
        """:meth:`distance` for trusted input (C-contiguous float64 (P, 3) points, a float
        > 0), without the checks."""
        return self._bvh.distance_unchecked(points, max_dist)

    @property
    def penetration_tolerance(self) -> float:
        """Depth below which :meth:`tip_contact` reports no penetration, m (0: rigid wall)."""
        return self._tolerance

    def _signed_distance(self, tip: np.ndarray) -> tuple[float, np.ndarray, int]:
        """(signed distance, outward normal, face) of ``tip`` vs the current wall (negative
        on the lumen side; face -1: no wall)."""
        sd, _, normal, face = self._bvh.closest_point(tip, max_dist=np.inf)
        return sd, normal, face

    def _geometric_contact(self, tip: np.ndarray, radius: float
                           ) -> tuple[float, float, np.ndarray]:
        """(penetration, clearance, outward normal) of the tip sphere vs the current wall."""
        sd, normal, face = self._signed_distance(tip)
        if face < 0:
            return 0.0, float("inf"), np.zeros(3)
        depth = radius + sd  # sd < 0 on the lumen side
        penetration = depth if depth > self._tolerance else 0.0
        clearance = max(-depth, 0.0)
        return penetration, clearance, normal

    def tip_contact(self, tip: np.ndarray, radius: float, dt: float) -> Contact:
        """Tip sphere vs the wall (checked; :meth:`tip_contact_unchecked` is the query).

        A rigid wall has no moving particles, so the Newton's-law force is 0; any crossing of
        the wall is reported as ``penetration`` (> 0), which the environment treats as a
        non-minor collision. A :class:`DeformableWall` adds the force on the particles the
        tip moved.

        Args:
            tip: (3,) tip centre, m (on a deformable wall normally the last body point of the
                last step).
            radius: tip (catheter) radius, m.
            dt: length of the last step, s (unused by a rigid wall).
        """
        p = _check_points("tip", tip, allow_empty=False)
        if p.shape[0] != 1:
            raise ValueError(f"tip must have shape (3,), found {np.shape(tip)}")
        r = _check_finite_scalar("radius", radius, positive=True)
        dt = _check_finite_scalar("dt", dt, positive=True)
        return self.tip_contact_unchecked(p[0], r, dt)

    def tip_contact_unchecked(self, tip: np.ndarray, radius: float, dt: float) -> Contact:
        """:meth:`tip_contact` for trusted input (the environment's hot path: a (3,) float64
        tip, floats > 0), without the checks."""
        pen, clearance, normal = self._geometric_contact(tip, radius)
        return Contact(penetration=pen, force=0.0, normal=normal,
                       in_contact=bool(pen > 0.0 or clearance == 0.0), clearance=clearance)

    def vertex_position(self, index: int) -> np.ndarray:
        """(3,) current position of wall particle ``index``, m (a copy)."""
        n = self.vertices.shape[0]
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) \
                or not 0 <= int(index) < n:
            raise ValueError(f"index must be an int in [0, {n - 1}], found {index!r}")
        return self.vertices[int(index)].copy()


class DeformableWall(StaticWall):
    """PBD wall with heartbeat-driven annulus and catheter contact.

    Args:
        anatomy: the vessel at rest (end-diastole).
        pbd_config: wall material and solver parameters (defaults: calibrated aorta).
        heartbeat_config: annulus motion (defaults: 10 mm axial, 5 mm in-plane, 70 bpm).
    """

    def __init__(self, anatomy: Anatomy, pbd_config: PBDConfig | None = None,
                 heartbeat_config: HeartbeatConfig | None = None):
        super().__init__(anatomy)
        self.pbd_config = pbd_config if pbd_config is not None else PBDConfig()
        if not isinstance(self.pbd_config, PBDConfig):
            raise ValueError(
                f"pbd_config must be a PBDConfig, found {type(self.pbd_config).__name__}")
        hb = heartbeat_config if heartbeat_config is not None else HeartbeatConfig()
        if not isinstance(hb, HeartbeatConfig):
            raise ValueError(f"heartbeat_config must be a HeartbeatConfig, found "
                             f"{type(hb).__name__}")
        self.heartbeat = Heartbeat(anatomy.root_axis, hb)
        fixed = np.asarray(anatomy.fixed_vertices, dtype=np.int64)
        center = np.asarray(anatomy.annulus_center, dtype=float)
        near = np.linalg.norm(self._rest[fixed] - center, axis=1) < hb.heart_borne_radius
        #: Fixed vertices released to move with the wall (coronary-stub ends), see
        #: ``HeartbeatConfig.heart_borne_radius``.
        self.heart_borne_vertices = fixed[near]
        self.topology = build_topology(self._rest, anatomy.faces, fixed[~near],
                                       anatomy.annulus_vertices, self.pbd_config)
        self._tolerance = self.pbd_config.penetration_tolerance
        self._wall_faces = self._bvh.faces
        n = self._rest.shape[0]
        self._factor = np.ones(len(self.topology.edges))
        self._x_old = np.zeros((n, 3))
        self._v_damped = np.zeros((n, 3))
        self._impulse = np.zeros((n, 3))
        self._touched = np.zeros(n, dtype=np.int8)
        self._dp = np.zeros((n, 3))
        self._last_dt = 0.0
        # Rest-shape pseudo-normals: the contact side test (lumen side or beyond the wall)
        # uses them, so a locally folded, deeply indented mesh cannot flip the push direction.
        self._rest_fn, self._rest_vn, self._rest_en = self._bvh.pseudo_normals()
        self.last_contact_violation = 0.0
        self._step_move = 0.0
        self.reset()

    def reset(self) -> None:
        """Back to the rest shape with zero velocity, t = 0."""
        self.vertices = self._rest.copy()
        self.velocities = np.zeros_like(self._rest)
        self.t = 0.0
        #: Steps since :meth:`reset`.
        self.steps = 0
        #: Largest particle distance from rest after the last step, m (checked against
        #: ``PBDConfig.max_displacement``).
        self.max_displacement = 0.0
        self._impulse[:] = 0.0
        self._touched[:] = 0
        self._dp[:] = 0.0
        self._factor[:] = 1.0
        self._bvh.refit(self.vertices)
        self._dirty = False
        self._last_tip: np.ndarray | None = None
        self._last_sd = 0.0
        #: Tip queries whose side of the wall was kept from the last one (see
        #: :meth:`_signed_distance`) since :meth:`reset`.
        self.side_vetoes = 0

    def step(self, t: float, dt: float, body_points: np.ndarray, body_radius: float) -> None:
        """Advance the wall from ``t - dt`` to ``t``.

        Args:
            t: time at the end of the step, s (the heartbeat phase is taken from it).
            dt: step length, s (> 0).
            body_points: (B, 3) catheter body, proximal end first, tip last (B may be 0).
            body_radius: catheter radius, m (> 0 when B > 0).

        Raises:
            WallError: a particle ended the step further than ``PBDConfig.max_displacement``
                from its rest position (the message names the step, the particle, the
                distance and, when the body lies outside the rest wall, where).
        """
        t = _check_finite_scalar("t", t)
        dt = _check_finite_scalar("dt", dt, positive=True)
        pts = _check_points("body_points", body_points, allow_empty=True)
        radius = _check_finite_scalar("body_radius", body_radius, positive=pts.shape[0] > 0) \
            if pts.shape[0] else 0.0
        self.step_unchecked(t, dt, pts, radius)

    def step_unchecked(self, t: float, dt: float, pts: np.ndarray, radius: float) -> None:
        """:meth:`step` for trusted input (the environment's hot path: floats, C-contiguous
        float64 (B, 3) body points, a radius > 0 when B > 0), without the checks."""
        start = self.vertices.copy()
        self._impulse[:] = 0.0
        self._touched[:] = 0
        self._dp[:] = 0.0
        if self.pbd_config.solver == "vbd":
            self._step_vbd(t, dt, pts, radius)  # refits the tree to the new shape
            self._dirty = False
        else:
            self._step_xpbd(t, dt, pts, radius)
            self._dirty = True
        self.t = t
        self._last_dt = dt
        self.steps += 1
        moved = self.vertices - start
        self._step_move = float(np.sqrt(np.max(np.einsum("ij,ij->i", moved, moved))))
        self._check_displacement(pts)

    def _check_displacement(self, pts: np.ndarray) -> None:
        """Raise :class:`WallError` when a particle is beyond ``max_displacement`` from rest."""
        i, d = largest_displacement(self.vertices, self._rest)
        self.max_displacement = float(d)
        bound = self.pbd_config.max_displacement
        if d <= bound:
            return
        where = self._rest[int(i)] * 1e3
        body = ""
        if pts.shape[0]:  # (the error path: a rest-shape tree just for the message)
            rest = WallBVH(self._rest, self.anatomy.faces, self.anatomy.wall_face_mask)
            # the body's capsule axes, every millimetre, on the lumen side of the exit plane
            axis = [pts[:1]]
            for a, b in itertools.pairwise(pts):
                m = max(int(np.linalg.norm(b - a) / 1e-3), 1)
                axis.append(a + np.linspace(0.0, 1.0, m + 1)[1:, None] * (b - a))
            samples = np.vstack(axis)
            exit_point = getattr(self.anatomy, "exit_point", None)
            if exit_point is not None:
                samples = samples[(samples - exit_point) @ self.anatomy.exit_normal < 0.0]
            sd = np.array([rest.closest_point(q)[0] for q in samples])
            if sd.size and sd.max() > 0.0:
                q = samples[int(np.argmax(sd))]
                body = (f"; the catheter body runs {sd.max() * 1e3:.1f} mm outside the rest "
                        f"wall at ({', '.join(f'{v * 1e3:.1f}' for v in q)}) mm: an "
                        "introducer outside the lumen?")
        raise WallError(
            f"deformable wall: expected every particle within {bound * 1e3:.0f} mm of its rest "
            f"position (PBDConfig.max_displacement), found particle {int(i)} (rest "
            f"({where[0]:.1f}, {where[1]:.1f}, {where[2]:.1f}) mm) {d * 1e3:.1f} mm away at "
            f"step {self.steps} (t = {self.t:.2f} s){body}")

    def _step_vbd(self, t: float, dt: float, pts: np.ndarray, radius: float) -> None:
        """All substeps of the VBD solver in one numba call (:func:`~.pbd.step_vbd`)."""
        cfg = self.pbd_config
        topo = self.topology
        h = dt / cfg.substeps
        disp = np.empty((cfg.substeps, 3))
        for k in range(cfg.substeps):
            disp[k] = self.heartbeat.displacement(t - dt + (k + 1) * h)
        tmin, tmax, left, right, start, count, order, fitted, n_nodes = self._bvh.tree
        worst = step_vbd(
            self.vertices, self.velocities, self._x_old, self._v_damped, self._dp, self._factor,
            self._impulse, self._touched, topo.inv_mass, topo.mass, topo.rest, topo.edges,
            topo.edge_rest, cfg.stiffening, _SECANT_RELAX, topo.adj_ptr, topo.adj_other,
            topo.adj_k, topo.adj_rest, topo.adj_edge, topo.tether_k, topo.vertex_order,
            topo.annulus, disp, topo.fixed, h, cfg.damping, cfg.iterations,
            cfg.local_iterations, cfg.local_rings, self._wall_faces, self._bvh.face_edges,
            self._rest_fn, self._rest_vn, self._rest_en, tmin, tmax, left, right, start, count,
            order, fitted, n_nodes, pts, radius, radius + cfg.contact_margin,
            cfg.chebyshev_rho, topo.ell_other, topo.ell_k, topo.ell_rest, topo.ell_edge)
        self._bvh.refitted(self.vertices)
        self.last_contact_violation = float(worst)

    def _step_xpbd(self, t: float, dt: float, pts: np.ndarray, radius: float) -> None:
        """The per-constraint XPBD solver, substep by substep (comparison and small steps)."""
        cfg = self.pbd_config
        topo = self.topology
        h = dt / cfg.substeps
        x = self.vertices
        v = self.velocities
        ann_rest = topo.rest[topo.annulus]
        empty = np.zeros(0, dtype=np.int64)
        worst = 0.0
        for k in range(cfg.substeps):
            t_k = t - dt + (k + 1) * h
            secant_factor(x, topo.edges, topo.edge_rest, cfg.stiffening, self._factor,
                          _SECANT_RELAX)
            predict(x, v, topo.inv_mass, h, cfg.damping, self._x_old, self._v_damped)
            if topo.annulus.size:
                x[topo.annulus] = ann_rest + self.heartbeat.displacement(t_k)
            if topo.fixed.size:
                x[topo.fixed] = topo.rest[topo.fixed]
            pf, ps = empty, empty
            if pts.shape[0]:
                self._bvh.refit(x)
                reach = radius + cfg.contact_margin
                pf, ps = self._bvh.faces_near_segments(pts, reach)
                pf, ps = narrow_pairs(x, self._wall_faces, pf, ps, pts, reach)
            points = pts if pts.shape[0] else np.zeros((1, 3))
            worst = solve(
                x, topo.inv_mass, topo.rest, topo.edges, topo.edge_rest, topo.edge_k,
                self._factor, topo.hinges, topo.hinge_rest, topo.hinge_k, topo.tether_k, h,
                cfg.iterations, self._wall_faces, self._bvh.face_edges, self._rest_fn,
                self._rest_vn, self._rest_en, pf, ps, points, radius, self._impulse,
                self._touched)
            v_new = (x - self._x_old) / h
            self._dp += topo.mass[:, None] * (v_new - self._v_damped)
            v[:] = v_new
        self.last_contact_violation = float(worst)

    def _sync(self) -> None:
        if self._dirty:
            self._bvh.refit(self.vertices)
            self._dirty = False

    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                ) -> np.ndarray:
        """(R,) distance to the first hit on the current (deformed) wall; see StaticWall."""
        self._sync()
        return self._bvh.raycast(origins, directions, max_dist)

    def cast_unchecked(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                       ) -> np.ndarray:
        """:meth:`raycast` without the checks (see :meth:`StaticWall.cast_unchecked`)."""
        self._sync()
        return self._bvh.cast_unchecked(origins, directions, max_dist)

    def distance_unchecked(self, points: np.ndarray, max_dist: float) -> np.ndarray:
        """:meth:`StaticWall.distance_unchecked` on the current (deformed) wall."""
        self._sync()
        return self._bvh.distance_unchecked(points, max_dist)

    def _signed_distance(self, tip: np.ndarray) -> tuple[float, np.ndarray, int]:
        """:meth:`StaticWall._signed_distance` on the deformed wall, with the side kept
        continuous.

        The side test (the closest feature's pseudo-normal) is exact on a closed surface
        that does not cross itself. On real roots the beating wall can fold (faces of the
        valve plane or of a deep crease invert for part of the cycle), and a tip well inside
        the lumen then reads as deep beyond the wall: on AVT D10, 10.7 mm inside at one step
        and "11.8 mm beyond" at the next, 0.5 mm further on. A real crossing between two tip
        queries cannot be longer than the tip's own move plus the largest particle move of
        the step (the distance to the wall is 1-Lipschitz in both), so a change of side with
        ``|sd_before| + |sd_now|`` beyond that (plus :data:`_SIDE_SLACK`) keeps the side of the
        query before; :attr:`side_vetoes` counts them.
        """
        sd, normal, face = super()._signed_distance(tip)
        last = self._last_tip
        if face >= 0 and last is not None and (sd > 0.0) != (self._last_sd > 0.0):
            reach = math.sqrt(float((tip - last) @ (tip - last))) + self._step_move
            if abs(sd) + abs(self._last_sd) > reach + _SIDE_SLACK:
                sd, normal = math.copysign(sd, self._last_sd), -normal
                self.side_vetoes += 1
        if face >= 0:
            self._last_tip = np.array(tip, dtype=np.float64)
            self._last_sd = sd
        return sd, normal, face

    def tip_contact_unchecked(self, tip: np.ndarray, radius: float, dt: float) -> Contact:
        """Tip sphere vs the deformed wall, with the force from Newton's second law (the
        checked :meth:`~StaticWall.tip_contact` calls this).

        ``force = |sum_{i in S} (dp_i / dt - f_i^elastic)|`` over the particles ``S`` the tip
        sphere (the last body point of the last :meth:`step`) moved, kept when within
        ``radius + max rest edge`` of ``tip`` (see :mod:`cgail_sim.contact`); ``dt``
        is the length of the last step (the impulse is turned into a mean force with it).
        """
        r = radius
        self._sync()
        pen, clearance, normal = self._geometric_contact(tip, r)
        touched = np.flatnonzero(self._touched == 2)
        if touched.size:  # the tip-sphere contacts of the last step near this tip
            touched = touched[np.linalg.norm(self.vertices[touched] - tip, axis=1)
                              <= r + self.topology.max_edge]
        force = 0.0
        if touched.size:
            topo = self.topology
            # the elastic force on the touched particles only (= internal_forces[touched])
            elastic = particle_forces(self.vertices, topo.rest, touched, topo.adj_ptr,
                                      topo.adj_other, topo.adj_k, topo.adj_rest, topo.adj_edge,
                                      self.pbd_config.stiffening, topo.tether_k)
            f = (self._dp[touched] / dt - elastic).sum(axis=0)
            force = float(np.linalg.norm(f))
        in_contact = bool(pen > 0.0 or clearance == 0.0 or touched.size > 0)
        return Contact(penetration=pen, force=force, normal=normal, in_contact=in_contact,
                       clearance=clearance)

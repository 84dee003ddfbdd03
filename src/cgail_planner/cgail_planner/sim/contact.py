"""Catheter-wall contact: the capsule-chain projection used inside the PBD loop and the tip result.

Catheter body. The body is a chain of capsules of radius ``r`` through the body points
``P_0 .. P_{B-1}`` (segment ``s`` joins ``P_s`` and ``P_{s+1}``; a single point is a sphere). The
catheter is kinematic (its shape is prescribed by the follow-the-leader agent), so contact is
a one-sided inequality constraint on the wall: for every wall triangle near a segment, with
``q_t`` the closest point of the triangle to the segment, ``q_s`` that of the segment, and
``d = |q_t - q_s|``,

    C = r - d <= 0 is required; when violated the triangle is moved along n = (q_t - q_s) / d.

The correction of a triangle point with barycentric weights ``b_k`` is spread over its three
vertices with inverse masses ``w_k`` (the standard PBD point-triangle projection against a
kinematic collider): ``dx_k = w_k b_k C / (sum_j w_j b_j^2) n``, which moves the point
``q_t = sum b_k x_k`` by exactly ``C n``. When the segment has crossed the triangle (it is on the
outer side of the triangle's interior, or pierces it) the triangle is pushed along its outward
normal beyond the segment.

Force (Newton's second law on the wall particles). For each particle ``i``:
``m_i a_i = f_i^contact + f_i^elastic + f_i^damping``, so the force the catheter exerts on a set
``S`` of wall particles over a step of length ``dt`` is

    F = sum_{i in S} [ dp_i / dt - f_i^elastic(x_end) ]

with ``dp_i = m_i (v_i^end - v_i^damped)`` the momentum change the constraints (elastic and
contact) gave particle ``i`` during the step (the damping's share is removed), and
``f_i^elastic`` the force of the calibrated wall material (stretch, bending and tethering
springs, see :mod:`cgail_planner.sim.pbd`) on particle ``i`` at the end of the step. ``S`` is the
set of particles the tip's contact moved during the last step (those within
``radius + max rest edge length`` of the tip). Wall particles are light (~4e-5 kg each), so
at the control step of 0.1 s the inertial term is negligible and ``F`` is in effect the elastic
reaction of the indented wall: it grows with the indentation through the calibrated
stress-strain curve. (``m dx / dt^2`` of the contact projection alone is not used: with
unconverged Gauss-Seidel iterations and light particles it is ~1e-4 N whatever the
indentation.) The paper classifies a collision as minor when ``F < 0.8 N`` and there is no
penetration; that decision belongs to the environment.

Penetration is geometric: the depth by which the tip sphere crosses the current wall surface,
``r - signed_distance`` (signed distance negative on the lumen side), clipped at 0.
"""

from __future__ import annotations

from dataclasses import dataclass

from numba import njit
import numpy as np

from cgail_planner.sim.raycast import closest_segment_triangle

__all__ = ["Contact", "project_contacts"]


@dataclass(frozen=True)
class Contact:
    """Result of :meth:`~cgail_planner.sim.wall.StaticWall.tip_contact` (SI units)."""

    penetration: float
    """Depth, m, by which the tip sphere crosses the wall surface; 0 when it does not."""
    force: float
    """Magnitude, N, of the force the tip exerts on the wall particles (Newton's second law
    on the particles it displaced, see the module docstring); 0 for a rigid wall."""
    normal: np.ndarray
    """(3,) unit outward wall normal at the closest wall point (away from the lumen): the
    direction the tip pushes the wall; the reaction on the catheter is ``-normal``."""
    in_contact: bool
    """True when the tip sphere touches or crosses the wall, or displaced wall particles in the
    last step."""
    clearance: float = 0.0
    """Distance, m, from the tip sphere's surface to the wall when not touching; 0 otherwise."""


@njit(cache=True)
def project_contacts(x, inv_mass, faces, pair_face, pair_seg, points, radius, dt, impulse,
                     touched):
    """One Gauss-Seidel sweep of the capsule-chain contact constraints (in place).

    Args:
        x: (N, 3) particle positions, updated.
        inv_mass: (N,) inverse masses (0 = kinematic).
        faces: (M, 3) wall triangles.
        pair_face, pair_seg: candidate (triangle, segment) pairs from the broad phase.
        points: (B, 3) body points.
        radius: capsule radius, m.
        dt: (sub)step length, s.
        impulse: (N, 3) accumulates ``m_i dx_i / dt`` of the contact corrections, N s.
        touched: (N,) int8, set to 1 for every particle a contact moved.

    Returns:
        Largest remaining violation ``C`` found in this sweep (before its correction), m.
    """
    worst = 0.0
    nb = points.shape[0]
    for p in range(pair_face.shape[0]):
        f = pair_face[p]
        s = pair_seg[p]
        i0 = faces[f, 0]
        i1 = faces[f, 1]
        i2 = faces[f, 2]
        a = x[i0]
        b = x[i1]
        c = x[i2]
        p0 = points[s]
        p1 = points[min(s + 1, nb - 1)]
        dist, qs, qt, u, v, w = closest_segment_triangle(p0, p1, a, b, c)
        if dist >= radius:
            continue
        nf = np.cross(b - a, c - a)
        ln = np.sqrt(np.sum(nf * nf))
        if ln <= 0.0:
            continue
        nf = nf / ln
        diff = qt - qs
        interior = u > 1e-9 and v > 1e-9 and w > 1e-9
        if dist > 1e-12 and (np.dot(diff, nf) >= 0.0 or not interior):
            # Lumen side (or an edge/vertex feature, whose side the face normal cannot tell):
            # push the triangle away from the segment.
            n = diff / dist
            cval = radius - dist
        elif dist > 1e-12:  # the segment lies beyond the triangle's interior
            n = nf
            cval = radius + dist
        else:  # the segment pierces the triangle: push beyond its outer end
            h = max(np.dot(p0 - a, nf), np.dot(p1 - a, nf), 0.0)
            n = nf
            cval = radius + h
        wsum = inv_mass[i0] * u * u + inv_mass[i1] * v * v + inv_mass[i2] * w * w
        if wsum <= 0.0:
            continue
        if cval > worst:
            worst = cval
        lam = cval / wsum
        for k in range(3):
            idx = i0 if k == 0 else (i1 if k == 1 else i2)
            beta = u if k == 0 else (v if k == 1 else w)
            wk = inv_mass[idx]
            if wk <= 0.0 or beta <= 0.0:
                continue
            step = wk * beta * lam
            for ax in range(3):
                x[idx, ax] += step * n[ax]
                # m_k * dx_k / dt with m_k = 1 / w_k
                impulse[idx, ax] += beta * lam * n[ax] / dt
            touched[idx] = 1
    return worst

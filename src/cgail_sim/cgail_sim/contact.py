"""Catheter-wall contact: the capsule-chain projection used inside the PBD loop and the tip result.

Catheter body. The body is a chain of capsules of radius ``r`` through the body points
``P_0 .. P_{B-1}`` (segment ``s`` joins ``P_s`` and ``P_{s+1}``; a single point is a sphere). The
catheter is kinematic (its shape is prescribed by the follow-the-leader agent), so contact is
a one-sided inequality constraint on the wall: for every wall triangle near a segment, with
``q_t`` the closest point of the triangle to the segment, ``q_s`` that of the segment, and
``d = |q_t - q_s|``,

    C = r - d <= 0 is required; when violated the triangle is moved along n = (q_t - q_s) / d.

Which side of the wall the segment is on is decided by the angle-weighted pseudo-normal of the
closest feature (face, edge or vertex; Baerentzen & Aanaes 2005) of the REST shape (a deeply
indented, locally folded mesh cannot flip it), so a segment that has ended up
beyond the wall (e.g. the beating root swept over the catheter) moves the wall past it instead
of pulling the wall inwards. It does so only when the segment lies on the lumen side of the
same triangle point in the rest shape (the wall moved over it). A segment that is beyond the
triangle at rest too leaves the triangle alone: it is the wall of a neighbouring vessel within
reach (branches and arch limbs a few mm apart on patient meshes) or the flank of a dent the
catheter has slid under; moving such a wall through the catheter, by up to ``r`` + the reach
each step, dragged dents deeper step after step and blew the wall up past the 40 mm bound
within a few steps of a catheter riding the wall of the elongated arch. A single correction
is capped at ``r``: larger ones are spread over the iterations and steps.

The correction of a triangle point with barycentric weights ``b_k`` is spread over its three
vertices with inverse masses ``w_k`` (the standard PBD point-triangle projection against a
kinematic collider): ``dx_k = w_k b_k C / (sum_j w_j b_j^2) n``, which moves the point
``q_t = sum b_k x_k`` by exactly ``C n``. A segment that pierces the triangle pushes it along its
outward normal beyond the segment's outer end. No vertex moves further than twice the
violation in one correction (``_STEP_CAP``): next to kinematic vertices the formula above
asks a free vertex for ``C / b_k``, unbounded as ``b_k -> 0``.

Force (Newton's second law on the wall particles). For each particle ``i``:
``m_i a_i = f_i^contact + f_i^elastic + f_i^damping``, so the force the catheter exerts on a set
``S`` of wall particles over a step of length ``dt`` is

    F = sum_{i in S} [ dp_i / dt - f_i^elastic(x_end) ]

with ``dp_i = m_i (v_i^end - v_i^damped)`` the momentum change the constraints (elastic and
contact) gave particle ``i`` during the step (the damping's share is removed), and
``f_i^elastic`` the force of the calibrated wall material (stretch, bending and tethering
springs, see :mod:`cgail_sim.pbd`) on particle ``i`` at the end of the step. ``S`` is the
set of particles the tip moved during the last step: those moved by a contact whose point on the
catheter lies within one radius of the tip (the last body point), i.e. by the tip sphere.
Springs inside ``S`` cancel, so ``F`` is exactly the contact force on ``S`` (the rest of the
body pressing elsewhere does not count towards the tip's force). Wall particles are light
(~4e-5 kg each), so at the control step of 0.1 s the inertial term is negligible and ``F`` is
in effect the elastic reaction of the indented wall: it grows with the indentation through the
calibrated stress-strain curve. (``m dx / dt^2`` of the contact projection alone is not used:
with light particles and a few iterations per step it is ~1e-4 N whatever the indentation.)
The paper classifies a collision as minor when ``F < 0.8 N`` and there is no
penetration; that decision belongs to the environment.

Penetration is geometric: the depth by which the tip sphere crosses the current wall surface,
``r - signed_distance`` (signed distance negative on the lumen side), clipped at 0.
"""

from __future__ import annotations

from dataclasses import dataclass

from numba import njit
import numpy as np

from cgail_sim import raycast
from cgail_sim.raycast import cst_scalar, drop_stale_numba_cache

drop_stale_numba_cache(__file__, [__file__, raycast.__file__])

#: Bound of one contact correction of a particle, as a multiple of the constraint violation
#: it corrects. The triangle point ``sum b_k x_k`` moves by the violation ``C``; its vertex k
#: moves by ``w_k b_k C / sum_j w_j b_j^2``, up to ~1.4 C for a triangle of free particles of
#: similar masses, but unbounded as ``b_k -> 0`` next to kinematic (fixed or annulus) vertices:
#: a catheter pressing 1 mm into a triangle of the fixed descending ring moved its one free
#: vertex 5.9 mm in a single projection and blew the wall up the step after.
_STEP_CAP = 2.0

__all__ = ["Contact", "linearize_contacts", "narrow_pairs", "project_contacts",
           "project_planes"]


@dataclass(frozen=True)
class Contact:
    """Result of :meth:`~cgail_sim.wall.StaticWall.tip_contact` (SI units)."""

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
def _lumen_side_at_rest(rest, i0, i1, i2, u, v, w, p0x, p0y, p0z, p1x, p1y, p1z, sp, pn):
    """True when the segment point ``sp`` lies on the lumen side of the triangle's point
    ``(u, v, w)`` in the REST shape (along the rest pseudo-normal ``pn``)."""
    s = 0.0
    for c in range(3):
        q = u * rest[i0, c] + v * rest[i1, c] + w * rest[i2, c]
        a = p0x if c == 0 else (p0y if c == 1 else p0z)
        b = p1x if c == 0 else (p1y if c == 1 else p1z)
        s += (q - (a + sp * (b - a))) * pn[c]
    return s >= 0.0


@njit(cache=True)
def project_contacts(x, rest, inv_mass, faces, face_edges, face_normals, vertex_normals,
                     edge_normals, pair_face, pair_seg, points, radius, dt, impulse, touched):
    """One Gauss-Seidel sweep of the capsule-chain contact constraints (in place).

    Args:
        x: (N, 3) particle positions, updated.
        rest: (N, 3) rest positions (the side test of a segment found beyond the wall).
        inv_mass: (N,) inverse masses (0 = kinematic).
        faces: (M, 3) wall triangles.
        face_edges: (M, 3) edge id of local edge k = (f_k, f_{k+1}) of every wall triangle.
        face_normals, vertex_normals, edge_normals: face normals and angle-weighted vertex and
            edge pseudo-normals of the wall at rest (they decide on which side of the surface a
            segment lies when its closest feature is an edge or a vertex).
        pair_face, pair_seg: candidate (triangle, segment) pairs from the broad phase.
        points: (B, 3) body points.
        radius: capsule radius, m.
        dt: (sub)step length, s.
        impulse: (N, 3) accumulates ``m_i dx_i / dt`` of the contact corrections, N s.
        touched: (N,) int8, raised to 2 for particles moved by a contact of the tip sphere (the
            segment point within ``radius`` of the last body point), to 1 for other contacts.

    Returns:
        Largest violation ``C`` found in this sweep (before its correction), m.
    """
    worst = 0.0
    nb = points.shape[0]
    for p in range(pair_face.shape[0]):
        f = pair_face[p]
        s = pair_seg[p]
        i0 = faces[f, 0]
        i1 = faces[f, 1]
        i2 = faces[f, 2]
        j = min(s + 1, nb - 1)
        ax, ay, az = x[i0, 0], x[i0, 1], x[i0, 2]
        bx, by, bz = x[i1, 0], x[i1, 1], x[i1, 2]
        cx, cy, cz = x[i2, 0], x[i2, 1], x[i2, 2]
        p0x, p0y, p0z = points[s, 0], points[s, 1], points[s, 2]
        p1x, p1y, p1z = points[j, 0], points[j, 1], points[j, 2]
        dist, sp, u, v, w = cst_scalar(p0x, p0y, p0z, p1x, p1y, p1z,
                                       ax, ay, az, bx, by, bz, cx, cy, cz)
        if dist > 1e-12:
            # Side test with the rest pseudo-normal of the closest feature.
            if u <= 1e-9 and v <= 1e-9:
                pn = vertex_normals[i2]
            elif v <= 1e-9 and w <= 1e-9:
                pn = vertex_normals[i0]
            elif u <= 1e-9 and w <= 1e-9:
                pn = vertex_normals[i1]
            elif w <= 1e-9:
                pn = edge_normals[face_edges[f, 0]]
            elif u <= 1e-9:
                pn = edge_normals[face_edges[f, 1]]
            elif v <= 1e-9:
                pn = edge_normals[face_edges[f, 2]]
            else:
                pn = face_normals[f]
            # diff = q_tri - q_seg
            dfx = u * ax + v * bx + w * cx - (p0x + sp * (p1x - p0x))
            dfy = u * ay + v * by + w * cy - (p0y + sp * (p1y - p0y))
            dfz = u * az + v * bz + w * cz - (p0z + sp * (p1z - p0z))
            if dfx * pn[0] + dfy * pn[1] + dfz * pn[2] >= 0.0:
                # segment on the lumen side: push the wall away from it
                if dist >= radius:
                    continue
                nx, ny, nz = dfx / dist, dfy / dist, dfz / dist
                cval = radius - dist
            else:  # segment beyond the wall: move the wall past it, if it swept over it
                if not _lumen_side_at_rest(rest, i0, i1, i2, u, v, w, p0x, p0y, p0z, p1x,
                                           p1y, p1z, sp, pn):
                    continue
                nx, ny, nz = -dfx / dist, -dfy / dist, -dfz / dist
                cval = radius + dist
        else:  # the segment pierces the triangle: push beyond its outer end
            nfx = (by - ay) * (cz - az) - (bz - az) * (cy - ay)
            nfy = (bz - az) * (cx - ax) - (bx - ax) * (cz - az)
            nfz = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            ln = np.sqrt(nfx * nfx + nfy * nfy + nfz * nfz)
            if ln <= 0.0:
                continue
            nx, ny, nz = nfx / ln, nfy / ln, nfz / ln
            h0 = (p0x - ax) * nx + (p0y - ay) * ny + (p0z - az) * nz
            h1 = (p1x - ax) * nx + (p1y - ay) * ny + (p1z - az) * nz
            cval = radius + max(h0, h1, 0.0)
        wsum = inv_mass[i0] * u * u + inv_mass[i1] * v * v + inv_mass[i2] * w * w
        if wsum <= 0.0:
            continue
        # Contacts of the tip sphere (segment point within one radius of the last body point)
        # mark their particles 2, the rest of the body 1.
        tx = p0x + sp * (p1x - p0x) - points[nb - 1, 0]
        ty = p0y + sp * (p1y - p0y) - points[nb - 1, 1]
        tz = p0z + sp * (p1z - p0z) - points[nb - 1, 2]
        mark = 2 if tx * tx + ty * ty + tz * tz <= radius * radius * (1.0 + 1e-9) else 1
        if cval > worst:
            worst = cval
        # Large corrections (a wall swept into the catheter) are spread over iterations.
        corr = min(cval, radius)
        lam = corr / wsum
        for k in range(3):
            idx = i0 if k == 0 else (i1 if k == 1 else i2)
            beta = u if k == 0 else (v if k == 1 else w)
            wk = inv_mass[idx]
            if wk <= 0.0 or beta <= 0.0:
                continue
            step = min(wk * beta * lam, _STEP_CAP * corr)
            x[idx, 0] += step * nx
            x[idx, 1] += step * ny
            x[idx, 2] += step * nz
            # m_k * dx_k / dt with m_k = 1 / w_k
            imp = step / (wk * dt)
            impulse[idx, 0] += imp * nx
            impulse[idx, 1] += imp * ny
            impulse[idx, 2] += imp * nz
            if touched[idx] < mark:
                touched[idx] = mark
    return worst


@njit(cache=True)
def narrow_pairs(x, faces, pair_face, pair_seg, points, reach):
    """Keep the broad-phase pairs whose exact segment-triangle distance is below ``reach``."""
    nb = points.shape[0]
    keep = np.zeros(pair_face.shape[0], np.bool_)
    for p in range(pair_face.shape[0]):
        f = pair_face[p]
        s = pair_seg[p]
        j = min(s + 1, nb - 1)
        i0 = faces[f, 0]
        i1 = faces[f, 1]
        i2 = faces[f, 2]
        dist, _, _, _, _ = cst_scalar(points[s, 0], points[s, 1], points[s, 2],
                                      points[j, 0], points[j, 1], points[j, 2],
                                      x[i0, 0], x[i0, 1], x[i0, 2], x[i1, 0], x[i1, 1],
                                      x[i1, 2], x[i2, 0], x[i2, 1], x[i2, 2])
        keep[p] = dist < reach
    return pair_face[keep].copy(), pair_seg[keep].copy()


@njit(cache=True)
def linearize_contacts(x, rest, faces, face_edges, face_normals, vertex_normals, edge_normals,
                       pair_face, pair_seg, points, radius):
    """Freeze each pair's contact feature at the current positions for the inner iterations.

    For every pair the closest-point weights ``b`` on the triangle, an anchor ``A`` and a
    normal ``n`` are computed with the same side test as :func:`project_contacts`, so that the
    pair's constraint becomes the plane ``(sum_k b_k x_k - A) . n >= radius``: a few flops per
    iteration instead of a segment-triangle distance. The exact projection still closes every
    step. Returns ``(bary (P, 3), anchor (P, 3), normal (P, 3), mark (P,))`` with ``mark`` 2 for
    pairs of the tip sphere, 1 otherwise, 0 for pairs that :func:`project_contacts` leaves
    alone (a segment beyond the wall that was beyond it at rest too).
    """
    m = pair_face.shape[0]
    nb = points.shape[0]
    bary = np.zeros((m, 3))
    anchor = np.zeros((m, 3))
    normal = np.zeros((m, 3))
    mark = np.ones(m, np.int8)
    for p in range(m):
        f = pair_face[p]
        s = pair_seg[p]
        i0 = faces[f, 0]
        i1 = faces[f, 1]
        i2 = faces[f, 2]
        j = min(s + 1, nb - 1)
        ax, ay, az = x[i0, 0], x[i0, 1], x[i0, 2]
        bx, by, bz = x[i1, 0], x[i1, 1], x[i1, 2]
        cx, cy, cz = x[i2, 0], x[i2, 1], x[i2, 2]
        p0x, p0y, p0z = points[s, 0], points[s, 1], points[s, 2]
        p1x, p1y, p1z = points[j, 0], points[j, 1], points[j, 2]
        dist, sp, u, v, w = cst_scalar(p0x, p0y, p0z, p1x, p1y, p1z,
                                       ax, ay, az, bx, by, bz, cx, cy, cz)
        qsx = p0x + sp * (p1x - p0x)
        qsy = p0y + sp * (p1y - p0y)
        qsz = p0z + sp * (p1z - p0z)
        qtx = u * ax + v * bx + w * cx
        qty = u * ay + v * by + w * cy
        qtz = u * az + v * bz + w * cz
        bary[p, 0] = u
        bary[p, 1] = v
        bary[p, 2] = w
        tx = qsx - points[nb - 1, 0]
        ty = qsy - points[nb - 1, 1]
        tz = qsz - points[nb - 1, 2]
        if tx * tx + ty * ty + tz * tz <= radius * radius * (1.0 + 1e-9):
            mark[p] = 2
        if dist > 1e-12:
            if u <= 1e-9 and v <= 1e-9:
                pn = vertex_normals[i2]
            elif v <= 1e-9 and w <= 1e-9:
                pn = vertex_normals[i0]
            elif u <= 1e-9 and w <= 1e-9:
                pn = vertex_normals[i1]
            elif w <= 1e-9:
                pn = edge_normals[face_edges[f, 0]]
            elif u <= 1e-9:
                pn = edge_normals[face_edges[f, 1]]
            elif v <= 1e-9:
                pn = edge_normals[face_edges[f, 2]]
            else:
                pn = face_normals[f]
            dfx = qtx - qsx
            dfy = qty - qsy
            dfz = qtz - qsz
            sign = 1.0 if dfx * pn[0] + dfy * pn[1] + dfz * pn[2] >= 0.0 else -1.0
            if sign < 0.0 and not _lumen_side_at_rest(rest, i0, i1, i2, u, v, w, p0x, p0y,
                                                      p0z, p1x, p1y, p1z, sp, pn):
                mark[p] = 0
                continue
            normal[p, 0] = sign * dfx / dist
            normal[p, 1] = sign * dfy / dist
            normal[p, 2] = sign * dfz / dist
            anchor[p, 0] = qsx
            anchor[p, 1] = qsy
            anchor[p, 2] = qsz
        else:
            nfx = (by - ay) * (cz - az) - (bz - az) * (cy - ay)
            nfy = (bz - az) * (cx - ax) - (bx - ax) * (cz - az)
            nfz = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            ln = np.sqrt(nfx * nfx + nfy * nfy + nfz * nfz)
            if ln <= 0.0:
                continue
            nx, ny, nz = nfx / ln, nfy / ln, nfz / ln
            h = max((p0x - ax) * nx + (p0y - ay) * ny + (p0z - az) * nz,
                    (p1x - ax) * nx + (p1y - ay) * ny + (p1z - az) * nz, 0.0)
            normal[p, 0] = nx
            normal[p, 1] = ny
            normal[p, 2] = nz
            anchor[p, 0] = qtx + h * nx
            anchor[p, 1] = qty + h * ny
            anchor[p, 2] = qtz + h * nz
    return bary, anchor, normal, mark


@njit(cache=True)
def project_planes(x, inv_mass, faces, pair_face, bary, anchor, normal, mark, radius, dt,
                   impulse, touched):
    """One sweep of the linearised contacts of :func:`linearize_contacts` (in place)."""
    for p in range(pair_face.shape[0]):
        f = pair_face[p]
        i0 = faces[f, 0]
        i1 = faces[f, 1]
        i2 = faces[f, 2]
        u = bary[p, 0]
        v = bary[p, 1]
        w = bary[p, 2]
        nx = normal[p, 0]
        ny = normal[p, 1]
        nz = normal[p, 2]
        qx = u * x[i0, 0] + v * x[i1, 0] + w * x[i2, 0] - anchor[p, 0]
        qy = u * x[i0, 1] + v * x[i1, 1] + w * x[i2, 1] - anchor[p, 1]
        qz = u * x[i0, 2] + v * x[i1, 2] + w * x[i2, 2] - anchor[p, 2]
        cval = radius - (qx * nx + qy * ny + qz * nz)
        if cval <= 0.0 or mark[p] == 0:
            continue
        wsum = inv_mass[i0] * u * u + inv_mass[i1] * v * v + inv_mass[i2] * w * w
        if wsum <= 0.0:
            continue
        corr = min(cval, radius)
        lam = corr / wsum
        for k in range(3):
            idx = i0 if k == 0 else (i1 if k == 1 else i2)
            beta = u if k == 0 else (v if k == 1 else w)
            wk = inv_mass[idx]
            if wk <= 0.0 or beta <= 0.0:
                continue
            step = min(wk * beta * lam, _STEP_CAP * corr)
            x[idx, 0] += step * nx
            x[idx, 1] += step * ny
            x[idx, 2] += step * nz
            imp = step / (wk * dt)
            impulse[idx, 0] += imp * nx
            impulse[idx, 1] += imp * ny
            impulse[idx, 2] += imp * nz
            if touched[idx] < mark[p]:
                touched[idx] = mark[p]

"""Ray casting and closest-point queries against a (possibly deforming) triangle surface.

A bounding-volume hierarchy (BVH) over the wall triangles is built once, from the rest shape
(the topology never changes), and *refit* after every wall step: the tree keeps its structure and
only its boxes are recomputed from the current vertex positions, O(M) for M triangles. For the
small deformations of the beating aorta (mm on a 25 mm lumen) the refit tree stays tight. Cap
triangles (``Anatomy.wall_face_mask == False``) are simply not put in the tree, so they are
transparent to rays and never touched by contacts.

Everything runs in numba (``@njit(cache=True)``); the same tree serves three queries:

* :meth:`WallBVH.raycast` - first hit along many rays (Moeller-Trumbore, both triangle sides);
* :meth:`WallBVH.closest_point` - closest wall point, signed by the angle-weighted pseudo-normal
  (Baerentzen & Aanaes 2005), used for the tip's clearance/penetration;
* :meth:`WallBVH.faces_near_segments` - triangles whose box comes within a distance of a capsule
  chain, the broad phase of the catheter-wall contact.

All lengths are in metres.
"""

from __future__ import annotations

from collections.abc import Sequence
import hashlib
import math
import os
from pathlib import Path
from typing import Any, NamedTuple

from numba import njit
import numpy as np

__all__ = ["BVHArrays", "WallBVH", "closest_kernel", "closest_point_triangle",
           "closest_segment_triangle", "cpt_scalar", "cst_scalar", "drop_stale_numba_cache",
           "faces_near_segments_kernel", "feature_normal_kernel", "raycast_kernel", "refit_tree"]


def drop_stale_numba_cache(module_file: str, dependencies: Sequence[str]) -> None:
    """Delete a module's numba disk cache when a module its kernels call into has changed.

    numba keys the cache of a function on its own source file only, so a kernel that calls a
    kernel of another module keeps running the old callee after that module is edited. Call
    this at import time of every module whose kernels call across modules: it stores a hash of
    the dependencies' sources next to the cache and removes the module's cache files when the
    hash differs. Does nothing when ``NUMBA_CACHE_DIR`` is set or the cache is not writable.
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    here = Path(module_file)
    digest = hashlib.sha256(b"".join(Path(d).read_bytes() for d in dependencies)).hexdigest()
    cache_dir = here.parent / "__pycache__"
    stamp = cache_dir / f"{here.stem}.numba-deps.sha256"
    try:
        if stamp.read_text() == digest:
            return
    except OSError:
        pass
    try:
        for f in cache_dir.glob(f"{here.stem}.*.nb[ic]"):
            f.unlink(missing_ok=True)
        cache_dir.mkdir(exist_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass


_LEAF_SIZE = 4
_STACK = 128
#: Barycentric slack of the ray-triangle test, so rays through a shared edge or vertex hit.
_EPS = 1e-9


# --------------------------------------------------------------------------- tree build / refit
@njit(cache=True)
def _build(tri_min, tri_max, centroids, leaf_size):
    m = centroids.shape[0]
    cap = max(2 * m, 1)
    node_min = np.zeros((cap, 3))
    node_max = np.zeros((cap, 3))
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    start = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
    order = np.arange(m).astype(np.int64)
    st_node = np.zeros(cap, np.int64)
    st_lo = np.zeros(cap, np.int64)
    st_hi = np.zeros(cap, np.int64)
    n_nodes = 1
    sp = 1
    st_node[0] = 0
    st_lo[0] = 0
    st_hi[0] = m
    while sp > 0:
        sp -= 1
        k = st_node[sp]
        lo = st_lo[sp]
        hi = st_hi[sp]
        for a in range(3):
            node_min[k, a] = np.inf
            node_max[k, a] = -np.inf
        cmin = np.full(3, np.inf)
        cmax = np.full(3, -np.inf)
        for i in range(lo, hi):
            f = order[i]
            for a in range(3):
                node_min[k, a] = min(node_min[k, a], tri_min[f, a])
                node_max[k, a] = max(node_max[k, a], tri_max[f, a])
                cmin[a] = min(cmin[a], centroids[f, a])
                cmax[a] = max(cmax[a], centroids[f, a])
        if hi - lo <= leaf_size:
            start[k] = lo
            count[k] = hi - lo
            continue
        axis = 0
        ext = cmax - cmin
        if ext[1] > ext[axis]:
            axis = 1
        if ext[2] > ext[axis]:
            axis = 2
        sub = order[lo:hi].copy()
        keys = np.empty(hi - lo)
        for i in range(hi - lo):
            keys[i] = centroids[sub[i], axis]
        srt = np.argsort(keys, kind="mergesort")
        for i in range(hi - lo):
            order[lo + i] = sub[srt[i]]
        mid = (lo + hi) // 2
        left[k] = n_nodes
        right[k] = n_nodes + 1
        st_node[sp] = n_nodes
        st_lo[sp] = lo
        st_hi[sp] = mid
        sp += 1
        st_node[sp] = n_nodes + 1
        st_lo[sp] = mid
        st_hi[sp] = hi
        sp += 1
        n_nodes += 2
    return node_min, node_max, left, right, start, count, order, n_nodes


@njit(cache=True)
def refit_tree(vertices, faces, order, node_min, node_max, left, right, start, count, n_nodes):
    # Children always have larger indices than their parent: a reverse sweep is bottom-up.
    # The bounds are accumulated in locals and stored once per node (the arrays may alias for
    # the compiler, so updating them in place forced a store per comparison: ~2x slower).
    for k in range(n_nodes - 1, -1, -1):
        if left[k] < 0:
            mn0 = np.inf
            mn1 = np.inf
            mn2 = np.inf
            mx0 = -np.inf
            mx1 = -np.inf
            mx2 = -np.inf
            for i in range(start[k], start[k] + count[k]):
                f = order[i]
                for c in range(3):
                    v = faces[f, c]
                    x0 = vertices[v, 0]
                    x1 = vertices[v, 1]
                    x2 = vertices[v, 2]
                    mn0 = min(mn0, x0)
                    mn1 = min(mn1, x1)
                    mn2 = min(mn2, x2)
                    mx0 = max(mx0, x0)
                    mx1 = max(mx1, x1)
                    mx2 = max(mx2, x2)
            node_min[k, 0] = mn0
            node_min[k, 1] = mn1
            node_min[k, 2] = mn2
            node_max[k, 0] = mx0
            node_max[k, 1] = mx1
            node_max[k, 2] = mx2
        else:
            lc = left[k]
            rc = right[k]
            for a in range(3):
                node_min[k, a] = min(node_min[lc, a], node_min[rc, a])
                node_max[k, a] = max(node_max[lc, a], node_max[rc, a])


# --------------------------------------------------------------------------- ray queries
@njit(cache=True)
def _ray_triangle(ox, oy, oz, dx, dy, dz, vertices, f0, f1, f2):
    """Moeller-Trumbore; returns the ray parameter t (> 0) or inf. Both sides count."""
    ax, ay, az = vertices[f0, 0], vertices[f0, 1], vertices[f0, 2]
    e1x = vertices[f1, 0] - ax
    e1y = vertices[f1, 1] - ay
    e1z = vertices[f1, 2] - az
    e2x = vertices[f2, 0] - ax
    e2y = vertices[f2, 1] - ay
    e2z = vertices[f2, 2] - az
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if abs(det) < 1e-18:
        return np.inf
    inv = 1.0 / det
    tx = ox - ax
    ty = oy - ay
    tz = oz - az
    u = (tx * px + ty * py + tz * pz) * inv
    if u < -_EPS or u > 1.0 + _EPS:
        return np.inf
    qx = ty * e1z - tz * e1y
    qy = tz * e1x - tx * e1z
    qz = tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < -_EPS or u + v > 1.0 + _EPS:
        return np.inf
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    if t <= 0.0:
        return np.inf
    return t


@njit(cache=True)
def raycast_kernel(vertices, faces, order, node_min, node_max, left, right, start, count,
                   origins, directions, max_dist, out):
    """First wall hit along each ray (the kernel of :meth:`WallBVH.raycast`, for kernels that
    cast rays themselves): ``out[r]`` is the distance along ``directions[r]`` from
    ``origins[r]``, ``max_dist`` when nothing is hit. The tree arrays are those of
    :attr:`WallBVH.query_arrays`."""
    stack = np.empty(_STACK, np.int64)
    for r in range(origins.shape[0]):
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        ix = 1.0 / dx if abs(dx) > 1e-300 else 1e300
        iy = 1.0 / dy if abs(dy) > 1e-300 else 1e300
        iz = 1.0 / dz if abs(dz) > 1e-300 else 1e300
        best = max_dist
        sp = 1
        stack[0] = 0
        while sp > 0:
            sp -= 1
            k = stack[sp]
            t1 = (node_min[k, 0] - ox) * ix
            t2 = (node_max[k, 0] - ox) * ix
            tmin = min(t1, t2)
            tmax = max(t1, t2)
            t1 = (node_min[k, 1] - oy) * iy
            t2 = (node_max[k, 1] - oy) * iy
            tmin = max(tmin, min(t1, t2))
            tmax = min(tmax, max(t1, t2))
            t1 = (node_min[k, 2] - oz) * iz
            t2 = (node_max[k, 2] - oz) * iz
            tmin = max(tmin, min(t1, t2))
            tmax = min(tmax, max(t1, t2))
            if tmax < 0.0 or tmin > tmax or tmin > best:
                continue
            if left[k] < 0:
                for i in range(start[k], start[k] + count[k]):
                    f = order[i]
                    t = _ray_triangle(ox, oy, oz, dx, dy, dz, vertices,
                                      faces[f, 0], faces[f, 1], faces[f, 2])
                    if t < best:
                        best = t
            else:
                stack[sp] = left[k]
                stack[sp + 1] = right[k]
                sp += 2
        out[r] = best


# --------------------------------------------------------------------------- closest points
@njit(cache=True, inline="always")
def _dot(ax, ay, az, bx, by, bz):
    return ax * bx + ay * by + az * bz


@njit(cache=True)
def cpt_scalar(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point of triangle abc to p (Ericson, Real-Time Collision Detection 5.1.5).

    Scalar, allocation-free form for the inner loops. Returns ``(qx, qy, qz, u, v, w)`` with
    ``q = u a + v b + w c``.
    """
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    d1 = _dot(abx, aby, abz, px - ax, py - ay, pz - az)
    d2 = _dot(acx, acy, acz, px - ax, py - ay, pz - az)
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, 1.0, 0.0, 0.0
    d3 = _dot(abx, aby, abz, px - bx, py - by, pz - bz)
    d4 = _dot(acx, acy, acz, px - bx, py - by, pz - bz)
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, 0.0, 1.0, 0.0
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return ax + t * abx, ay + t * aby, az + t * abz, 1.0 - t, t, 0.0
    d5 = _dot(abx, aby, abz, px - cx, py - cy, pz - cz)
    d6 = _dot(acx, acy, acz, px - cx, py - cy, pz - cz)
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, 0.0, 0.0, 1.0
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return ax + t * acx, ay + t * acy, az + t * acz, 1.0 - t, 0.0, t
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return (bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz), 0.0, 1.0 - t, t)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return (ax + v * abx + w * acx, ay + v * aby + w * acy, az + v * abz + w * acz,
            1.0 - v - w, v, w)


@njit(cache=True)
def _css_scalar(p1x, p1y, p1z, q1x, q1y, q1z, p2x, p2y, p2z, q2x, q2y, q2z):
    """Closest points of segments p1q1 and p2q2 (Ericson 5.1.9); returns (s, t, dist^2)."""
    d1x, d1y, d1z = q1x - p1x, q1y - p1y, q1z - p1z
    d2x, d2y, d2z = q2x - p2x, q2y - p2y, q2z - p2z
    rx, ry, rz = p1x - p2x, p1y - p2y, p1z - p2z
    a = _dot(d1x, d1y, d1z, d1x, d1y, d1z)
    e = _dot(d2x, d2y, d2z, d2x, d2y, d2z)
    f = _dot(d2x, d2y, d2z, rx, ry, rz)
    eps = 1e-30
    if a <= eps and e <= eps:
        s = 0.0
        t = 0.0
    elif a <= eps:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = _dot(d1x, d1y, d1z, rx, ry, rz)
        if e <= eps:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = _dot(d1x, d1y, d1z, d2x, d2y, d2z)
            denom = a * e - b * b
            s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > eps else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    dx = p1x + s * d1x - (p2x + t * d2x)
    dy = p1y + s * d1y - (p2y + t * d2y)
    dz = p1z + s * d1z - (p2z + t * d2z)
    return s, t, dx * dx + dy * dy + dz * dz


@njit(cache=True)
def cst_scalar(p0x, p0y, p0z, p1x, p1y, p1z, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest points between segment p0p1 and triangle abc (scalar, allocation-free).

    Returns:
        ``(dist, s, u, v, w)``: the distance, the segment parameter of its closest point
        (``p0 + s (p1 - p0)``) and the barycentric weights of the triangle's closest point.
        dist is 0 when the segment pierces the triangle.
    """
    dx, dy, dz = p1x - p0x, p1y - p0y, p1z - p0z
    e1x, e1y, e1z = bx - ax, by - ay, bz - az
    e2x, e2y, e2z = cx - ax, cy - ay, cz - az
    # Piercing test (Moeller-Trumbore with the segment parameter in [0, 1]).
    pvx = dy * e2z - dz * e2y
    pvy = dz * e2x - dx * e2z
    pvz = dx * e2y - dy * e2x
    det = _dot(e1x, e1y, e1z, pvx, pvy, pvz)
    if abs(det) > 1e-24:
        inv = 1.0 / det
        tvx, tvy, tvz = p0x - ax, p0y - ay, p0z - az
        uu = _dot(tvx, tvy, tvz, pvx, pvy, pvz) * inv
        if 0.0 <= uu <= 1.0:
            qvx = tvy * e1z - tvz * e1y
            qvy = tvz * e1x - tvx * e1z
            qvz = tvx * e1y - tvy * e1x
            vv = _dot(dx, dy, dz, qvx, qvy, qvz) * inv
            if vv >= 0.0 and uu + vv <= 1.0:
                tt = _dot(e2x, e2y, e2z, qvx, qvy, qvz) * inv
                if 0.0 <= tt <= 1.0:
                    return 0.0, tt, 1.0 - uu - vv, uu, vv
    # Otherwise the minimum is at a segment end vs the triangle or a segment vs an edge.
    qx, qy, qz, bu, bv, bw = cpt_scalar(p0x, p0y, p0z, ax, ay, az, bx, by, bz, cx, cy, cz)
    best = (qx - p0x) ** 2 + (qy - p0y) ** 2 + (qz - p0z) ** 2
    bs = 0.0
    qx, qy, qz, u, v, w = cpt_scalar(p1x, p1y, p1z, ax, ay, az, bx, by, bz, cx, cy, cz)
    dd = (qx - p1x) ** 2 + (qy - p1y) ** 2 + (qz - p1z) ** 2
    if dd < best:
        best, bs, bu, bv, bw = dd, 1.0, u, v, w
    s, t, dd = _css_scalar(p0x, p0y, p0z, p1x, p1y, p1z, ax, ay, az, bx, by, bz)
    if dd < best:
        best, bs, bu, bv, bw = dd, s, 1.0 - t, t, 0.0
    s, t, dd = _css_scalar(p0x, p0y, p0z, p1x, p1y, p1z, bx, by, bz, cx, cy, cz)
    if dd < best:
        best, bs, bu, bv, bw = dd, s, 0.0, 1.0 - t, t
    s, t, dd = _css_scalar(p0x, p0y, p0z, p1x, p1y, p1z, cx, cy, cz, ax, ay, az)
    if dd < best:
        best, bs, bu, bv, bw = dd, s, t, 0.0, 1.0 - t
    return np.sqrt(best), bs, bu, bv, bw


@njit(cache=True)
def closest_point_triangle(p, a, b, c):
    """Closest point of triangle (a, b, c) to p; returns ``(q, u, v, w)``, q = u a + v b + w c."""
    qx, qy, qz, u, v, w = cpt_scalar(p[0], p[1], p[2], a[0], a[1], a[2], b[0], b[1], b[2],
                                     c[0], c[1], c[2])
    q = np.empty(3)
    q[0] = qx
    q[1] = qy
    q[2] = qz
    return q, u, v, w


@njit(cache=True)
def closest_segment_triangle(p0, p1, a, b, c):
    """Closest points between segment p0p1 and triangle abc.

    Returns:
        (dist, q_seg, q_tri, u, v, w): distance, closest point on the segment, closest point on
        the triangle and its barycentric weights; dist is 0 when the segment pierces it.
    """
    dist, s, u, v, w = cst_scalar(p0[0], p0[1], p0[2], p1[0], p1[1], p1[2], a[0], a[1], a[2],
                                  b[0], b[1], b[2], c[0], c[1], c[2])
    return dist, p0 + s * (p1 - p0), u * a + v * b + w * c, u, v, w


@njit(cache=True)
def _box_dist2(p, bmin, bmax):
    d2 = 0.0
    for a in range(3):
        if p[a] < bmin[a]:
            d2 += (bmin[a] - p[a]) ** 2
        elif p[a] > bmax[a]:
            d2 += (p[a] - bmax[a]) ** 2
    return d2


@njit(cache=True)
def closest_kernel(vertices, faces, order, node_min, node_max, left, right, start, count, p,
                   max_dist):
    """Closest wall triangle to p within max_dist: (dist, face, q, u, v, w); face -1 if none."""
    stack = np.empty(_STACK, np.int64)
    best2 = max_dist * max_dist
    best_f = -1
    best_q = p.copy()
    bu, bv, bw = 0.0, 0.0, 0.0
    sp = 1
    stack[0] = 0
    while sp > 0:
        sp -= 1
        k = stack[sp]
        if _box_dist2(p, node_min[k], node_max[k]) > best2:
            continue
        if left[k] < 0:
            for i in range(start[k], start[k] + count[k]):
                f = order[i]
                i0 = faces[f, 0]
                i1 = faces[f, 1]
                i2 = faces[f, 2]
                qx, qy, qz, u, v, w = cpt_scalar(
                    p[0], p[1], p[2], vertices[i0, 0], vertices[i0, 1], vertices[i0, 2],
                    vertices[i1, 0], vertices[i1, 1], vertices[i1, 2],
                    vertices[i2, 0], vertices[i2, 1], vertices[i2, 2])
                dd = (qx - p[0]) ** 2 + (qy - p[1]) ** 2 + (qz - p[2]) ** 2
                if dd < best2:
                    best2 = dd
                    best_f = f
                    best_q[0] = qx
                    best_q[1] = qy
                    best_q[2] = qz
                    bu, bv, bw = u, v, w
        else:
            lc = left[k]
            rc = right[k]
            dl = _box_dist2(p, node_min[lc], node_max[lc])
            dr = _box_dist2(p, node_min[rc], node_max[rc])
            if dl < dr:  # visit the nearer child first
                stack[sp] = rc
                stack[sp + 1] = lc
            else:
                stack[sp] = lc
                stack[sp + 1] = rc
            sp += 2
    return np.sqrt(best2), best_f, best_q, bu, bv, bw


@njit(cache=True)
def distance_kernel(vertices, faces, order, node_min, node_max, left, right, start, count,
                    points, max_dist, out):
    """``out[i]``: distance from ``points[i]`` to the nearest wall triangle, inf where none is
    within ``max_dist`` (:func:`closest_kernel` per point)."""
    for i in range(points.shape[0]):
        dist, face, _, _, _, _ = closest_kernel(vertices, faces, order, node_min, node_max,
                                                left, right, start, count, points[i], max_dist)
        out[i] = dist if face >= 0 else np.inf


@njit(cache=True)
def faces_near_segments_kernel(node_min, node_max, left, right, start, count, order,
                         points, reach):
    """Broad phase: (face, segment) pairs whose boxes overlap the segment box grown by reach.

    The tree arrays are those of :attr:`WallBVH.tree`; see :meth:`WallBVH.faces_near_segments`.
    """
    n_seg = max(points.shape[0] - 1, 1)
    cap = 256
    pf = np.empty(cap, np.int64)
    ps = np.empty(cap, np.int64)
    n = 0
    stack = np.empty(_STACK, np.int64)
    lo = np.empty(3)
    hi = np.empty(3)
    for s in range(n_seg):
        j = min(s + 1, points.shape[0] - 1)
        for a in range(3):
            lo[a] = min(points[s, a], points[j, a]) - reach
            hi[a] = max(points[s, a], points[j, a]) + reach
        sp = 1
        stack[0] = 0
        while sp > 0:
            sp -= 1
            k = stack[sp]
            if (node_min[k, 0] > hi[0] or node_max[k, 0] < lo[0] or node_min[k, 1] > hi[1]
                    or node_max[k, 1] < lo[1] or node_min[k, 2] > hi[2]
                    or node_max[k, 2] < lo[2]):
                continue
            if left[k] < 0:
                for i in range(start[k], start[k] + count[k]):
                    if n == cap:
                        cap *= 2
                        nf = np.empty(cap, np.int64)
                        ns = np.empty(cap, np.int64)
                        nf[:n] = pf[:n]
                        ns[:n] = ps[:n]
                        pf = nf
                        ps = ns
                    pf[n] = order[i]
                    ps[n] = s
                    n += 1
            else:
                stack[sp] = left[k]
                stack[sp + 1] = right[k]
                sp += 2
    return pf[:n].copy(), ps[:n].copy()


def _csr(owner: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR incidence of the entries ``owner`` (entry a belongs to item ``owner[a]``): returns
    ``(ptr (n+1,), face (A,))`` listing, per item, the faces ``a // 3`` in increasing order."""
    order = np.argsort(owner, kind="stable")
    ptr = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=n))]).astype(np.int64)
    return ptr, np.ascontiguousarray(order // 3, dtype=np.int64)


@njit(cache=True)
def _pseudo_normals(vertices, faces, face_edges, n_edges, n_vertices):
    """Face normals, angle-weighted vertex normals and edge normals of the wall triangles."""
    m = faces.shape[0]
    fn = np.zeros((m, 3))
    vn = np.zeros((n_vertices, 3))
    en = np.zeros((n_edges, 3))
    for f in range(m):
        a = vertices[faces[f, 0]]
        b = vertices[faces[f, 1]]
        c = vertices[faces[f, 2]]
        n = np.cross(b - a, c - a)
        ln = np.sqrt(np.sum(n * n))
        if ln > 0.0:
            n = n / ln
        fn[f] = n
        for k in range(3):
            p = vertices[faces[f, k]]
            e1 = vertices[faces[f, (k + 1) % 3]] - p
            e2 = vertices[faces[f, (k + 2) % 3]] - p
            den = np.sqrt(np.sum(e1 * e1) * np.sum(e2 * e2))
            if den > 0.0:
                cosang = min(max(np.dot(e1, e2) / den, -1.0), 1.0)
                vn[faces[f, k]] += np.arccos(cosang) * n
            en[face_edges[f, k]] += n
    return fn, vn, en


@njit(cache=True)
def _face_unit_normal(vertices, faces, f):
    """Unit normal of triangle f (zero for a degenerate one), as in :func:`_pseudo_normals`."""
    i0 = faces[f, 0]
    i1 = faces[f, 1]
    i2 = faces[f, 2]
    abx = vertices[i1, 0] - vertices[i0, 0]
    aby = vertices[i1, 1] - vertices[i0, 1]
    abz = vertices[i1, 2] - vertices[i0, 2]
    acx = vertices[i2, 0] - vertices[i0, 0]
    acy = vertices[i2, 1] - vertices[i0, 1]
    acz = vertices[i2, 2] - vertices[i0, 2]
    nx = aby * acz - abz * acy
    ny = abz * acx - abx * acz
    nz = abx * acy - aby * acx
    ln = np.sqrt(nx * nx + ny * ny + nz * nz)
    if ln > 0.0:
        nx /= ln
        ny /= ln
        nz /= ln
    return nx, ny, nz


@njit(cache=True)
def feature_normal_kernel(vertices, faces, face_edges, vf_ptr, vf_face, ef_ptr, ef_face, face,
                          u, v, w):
    """Pseudo-normal (unnormalised) of the closest feature of ``face`` at weights (u, v, w).

    The same quantity as the matching entry of :func:`_pseudo_normals` (face normal, edge sum
    of the adjacent face normals, or angle-weighted vertex sum), computed from the few faces
    around the feature only, so a query on a deforming wall does not rebuild all normals.
    """
    nz_count = 0
    zero_k = -1
    keep_k = -1
    for k in range(3):
        b = u if k == 0 else (v if k == 1 else w)
        if b <= 1e-12:
            nz_count += 1
            zero_k = k
        else:
            keep_k = k
    out = np.zeros(3)
    if nz_count == 2:  # a vertex region
        vi = faces[face, keep_k]
        for a in range(vf_ptr[vi], vf_ptr[vi + 1]):
            g = vf_face[a]
            nx, ny, nz = _face_unit_normal(vertices, faces, g)
            k = 0
            while faces[g, k] != vi:
                k += 1
            j1 = faces[g, (k + 1) % 3]
            j2 = faces[g, (k + 2) % 3]
            e1x = vertices[j1, 0] - vertices[vi, 0]
            e1y = vertices[j1, 1] - vertices[vi, 1]
            e1z = vertices[j1, 2] - vertices[vi, 2]
            e2x = vertices[j2, 0] - vertices[vi, 0]
            e2y = vertices[j2, 1] - vertices[vi, 1]
            e2z = vertices[j2, 2] - vertices[vi, 2]
            den = np.sqrt((e1x * e1x + e1y * e1y + e1z * e1z)
                          * (e2x * e2x + e2y * e2y + e2z * e2z))
            if den > 0.0:
                cosang = min(max((e1x * e2x + e1y * e2y + e1z * e2z) / den, -1.0), 1.0)
                ang = np.arccos(cosang)
                out[0] += ang * nx
                out[1] += ang * ny
                out[2] += ang * nz
    elif nz_count == 1:  # an edge region: edge (k+1, k+2) opposite the zero weight k
        e = face_edges[face, (zero_k + 1) % 3]
        for a in range(ef_ptr[e], ef_ptr[e + 1]):
            nx, ny, nz = _face_unit_normal(vertices, faces, ef_face[a])
            out[0] += nx
            out[1] += ny
            out[2] += nz
    else:
        nx, ny, nz = _face_unit_normal(vertices, faces, face)
        out[0] = nx
        out[1] = ny
        out[2] = nz
    return out


class BVHArrays(NamedTuple):
    """The arrays of a :class:`WallBVH` that its query kernels take, in their argument order."""

    vertices: np.ndarray
    faces: np.ndarray
    order: np.ndarray
    node_min: np.ndarray
    node_max: np.ndarray
    left: np.ndarray
    right: np.ndarray
    leaf_start: np.ndarray
    leaf_count: np.ndarray
    face_edges: np.ndarray
    vf_ptr: np.ndarray
    vf_face: np.ndarray
    ef_ptr: np.ndarray
    ef_face: np.ndarray


class WallBVH:
    """BVH over the wall triangles of a surface whose vertices may move (topology fixed).

    Args:
        vertices: (N, 3) rest positions, m.
        faces: (M, 3) int triangles (all of them, caps included).
        wall_face_mask: (M,) bool, True for the wall triangles; only these are in the tree.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, wall_face_mask: np.ndarray):
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        mask = np.asarray(wall_face_mask, dtype=bool)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"vertices must have shape (N, 3), found {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (M, 3), found {faces.shape}")
        if mask.shape != (faces.shape[0],):
            raise ValueError(
                f"wall_face_mask must have shape ({faces.shape[0]},), found {mask.shape}")
        if not mask.any():
            raise ValueError("wall_face_mask must mark at least one wall face, found none")
        self.n_vertices = vertices.shape[0]
        self.faces = np.ascontiguousarray(faces[mask])
        tri = vertices[self.faces]
        (self._nmin, self._nmax, self._left, self._right, self._start, self._count,
         self._order, n_nodes) = _build(tri.min(axis=1), tri.max(axis=1), tri.mean(axis=1),
                                        _LEAF_SIZE)
        self._n_nodes = int(n_nodes)
        # Edge ids per (face, local edge k = (v_k, v_{k+1})) for the edge pseudo-normals.
        e = np.sort(np.stack([self.faces, np.roll(self.faces, -1, axis=1)], axis=2), axis=2)
        uniq, inv = np.unique(e.reshape(-1, 2), axis=0, return_inverse=True)
        self._face_edges = inv.reshape(-1, 3).astype(np.int64)
        self._n_edges = len(uniq)
        # Incidence (CSR, faces in increasing order) of vertices and edges to wall faces, for
        # the pseudo-normal of one feature (:func:`feature_normal_kernel`).
        self._vf_ptr, self._vf_face = _csr(self.faces.ravel(), self.n_vertices)
        self._ef_ptr, self._ef_face = _csr(self._face_edges.ravel(), self._n_edges)
        self._normals: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.vertices = vertices.copy()
        self._fitted = vertices.copy()
        self.refit(vertices)

    def refit(self, vertices: np.ndarray) -> None:
        """Recompute the boxes for new vertex positions (same topology), O(M)."""
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        refit_tree(self.vertices, self.faces, self._order, self._nmin, self._nmax, self._left,
               self._right, self._start, self._count, self._n_nodes)
        if self._fitted.shape != self.vertices.shape:
            self._fitted = self.vertices.copy()
        else:
            np.copyto(self._fitted, self.vertices)
        self._normals = None

    @property
    def query_arrays(self) -> BVHArrays:
        """The arrays the query kernels (:func:`raycast_kernel`, :func:`closest_kernel`,
        :func:`feature_normal_kernel`) take, at the last refit (a deformable wall refits lazily:
        query it once first)."""
        return BVHArrays(self.vertices, self.faces, self._order, self._nmin, self._nmax,
                         self._left, self._right, self._start, self._count, self._face_edges,
                         self._vf_ptr, self._vf_face, self._ef_ptr, self._ef_face)

    @property
    def tree(self) -> tuple[Any, ...]:
        """The tree for kernels that query or refit it directly: ``(node_min, node_max, left,
        right, start, count, order, fitted, n_nodes)``, ``fitted`` (N, 3) the vertex positions
        of the last refit (the boxes bound the wall faces at those positions). A kernel that
        refits the tree in place (:func:`refit_tree`) must copy the positions into ``fitted``
        and then call :meth:`refitted`."""
        return (self._nmin, self._nmax, self._left, self._right, self._start, self._count,
                self._order, self._fitted, self._n_nodes)

    def refitted(self, vertices: np.ndarray) -> None:
        """Record that a kernel refit the tree in place to ``vertices`` (see :attr:`tree`)."""
        self.vertices = vertices
        self._normals = None

    @property
    def face_edges(self) -> np.ndarray:
        """(M, 3) edge id of local edge k = (f_k, f_{k+1}) of every wall triangle."""
        return self._face_edges

    def pseudo_normals(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(face, vertex, edge) normals of the wall at the last refit (unnormalised sums
        for vertices and edges; the sign test only needs their direction)."""
        if self._normals is None:
            self._normals = _pseudo_normals(self.vertices, self.faces, self._face_edges,
                                            self._n_edges, self.n_vertices)
        return self._normals

    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_dist: float) -> np.ndarray:
        """(R,) distance to the first wall hit along each ray, ``max_dist`` when none within it.

        Args:
            origins: (R, 3) ray origins, m.
            directions: (R, 3) unit directions (not re-normalised: distances are in units of
                the direction's length).
            max_dist: ray length, m (> 0).
        """
        origins = np.ascontiguousarray(origins, dtype=np.float64)
        directions = np.ascontiguousarray(directions, dtype=np.float64)
        if origins.ndim != 2 or origins.shape[1] != 3:
            raise ValueError(f"origins must have shape (R, 3), found {origins.shape}")
        if directions.shape != origins.shape:
            raise ValueError(
                f"directions must have the shape of origins {origins.shape}, "
                f"found {directions.shape}")
        if not (np.isfinite(max_dist) and max_dist > 0):
            raise ValueError(f"max_dist must be a finite number > 0, found {max_dist!r}")
        if not (np.isfinite(origins).all() and np.isfinite(directions).all()):
            raise ValueError("origins and directions must be finite, found NaN or inf")
        return self.cast_unchecked(origins, directions, float(max_dist))

    def cast_unchecked(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                       ) -> np.ndarray:
        """:meth:`raycast` without the checks (the hot path of callers whose rays are
        well-formed by construction): C-contiguous float64 (R, 3) arrays, a float > 0."""
        out = np.empty(origins.shape[0])
        raycast_kernel(self.vertices, self.faces, self._order, self._nmin, self._nmax, self._left,
                 self._right, self._start, self._count, origins, directions, max_dist, out)
        return out

    def distance_unchecked(self, points: np.ndarray, max_dist: float) -> np.ndarray:
        """(P,) distance from each of the (P, 3) C-contiguous float64 ``points`` to the nearest
        wall triangle, m; inf where none is within ``max_dist`` (a float > 0). No checks."""
        out = np.empty(points.shape[0])
        distance_kernel(self.vertices, self.faces, self._order, self._nmin, self._nmax,
                        self._left, self._right, self._start, self._count, points, max_dist,
                        out)
        return out

    def closest_point(self, point: np.ndarray, max_dist: float = np.inf
                      ) -> tuple[float, np.ndarray, np.ndarray, int]:
        """Closest wall point to ``point`` with a signed distance.

        Args:
            point: (3,) query point, m.
            max_dist: search radius, m; no wall within it gives ``(inf, point, 0, -1)``.

        Returns:
            (signed_distance, closest_point, outward_normal, face): the distance is negative
            when ``point`` is on the lumen side of the wall (the normals point out of the
            lumen), positive when it is beyond the wall. The normal is the angle-weighted
            pseudo-normal of the closest feature (face, edge or vertex), unit length.
        """
        p = np.ascontiguousarray(point, dtype=np.float64).reshape(3)
        dist, face, q, u, v, w = closest_kernel(
            self.vertices, self.faces, self._order, self._nmin, self._nmax, self._left,
            self._right, self._start, self._count, p, float(max_dist))
        if face < 0:
            return float("inf"), p.copy(), np.zeros(3), -1
        n = feature_normal_kernel(self.vertices, self.faces, self._face_edges, self._vf_ptr,
                            self._vf_face, self._ef_ptr, self._ef_face, face, u, v, w)
        n = n / max(math.sqrt(float(n @ n)), 1e-300)  # (np.linalg.norm: same value, slower)
        sign = 1.0 if float(np.dot(p - q, n)) > 0.0 else -1.0
        return sign * float(dist), q, n, int(face)

    def faces_near_segments(self, points: np.ndarray, reach: float
                            ) -> tuple[np.ndarray, np.ndarray]:
        """Broad phase: candidate (wall face, segment) pairs of a polyline grown by ``reach``.

        Args:
            points: (B, 3) polyline; segment s joins points s and s+1 (one point = a sphere,
                reported as segment 0).
            reach: distance, m, by which each segment's box is grown (radius + margin).

        Returns:
            (faces, segments): int arrays of equal length; faces index :attr:`faces`.
        """
        pts = np.ascontiguousarray(points, dtype=np.float64)
        return faces_near_segments_kernel(self._nmin, self._nmax, self._left, self._right,
                                    self._start, self._count, self._order, pts, float(reach))

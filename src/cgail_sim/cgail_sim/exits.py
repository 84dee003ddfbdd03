"""Where the catheter tip leaves the lumen: through the disc of an open cut, nowhere else.

The lumen surface of an :class:`~cgail_sim.anatomy.Anatomy` is closed at every cut:
the closed aortic valve by a valve plane that is WALL (the tip collides with it), and each open
end (the descending end, the supra-aortic branch and coronary stub ends) by a flat cap
(``wall_face_mask`` False). Caps are transparent to the wall queries, so the open ends are
where the tip can leave. :attr:`Anatomy.exit_discs <cgail_sim.anatomy.Anatomy.
exit_discs>` describes each cap as a disc (centre, unit normal out of the lumen, radius); this
module is the one rule that says when the tip has left through one, used by the env
(:mod:`cgail_sim.env`), the planner's reference rollout
(:meth:`cgail_planner.core.planner.Planner.rollout_reference`) and its numba kernel
(:mod:`cgail_planner.core.rollout_kernel`).

**The rule.** A step that moves the tip from ``p0`` to ``p1`` leaves the lumen through disc
``k`` when the segment ``p0 -> p1`` crosses the disc's plane from the lumen side
(``h0 <= 0 < h1`` with ``h = (p - centre) . normal``) at a point within ``radius +``
:data:`EXIT_MARGIN` of the centre. The test is exact for any step length (a long step cannot
jump over a disc). A tip beyond a disc's plane that did not pass through the disc is not out:
it is in the lumen on the far side of the plane (a cut at the level of the aortic root leaves
the root beyond the descending cut's plane) or it is in the wall, which the collision test
reports. The discs are those of the rest shape: cap vertices are held fixed by the wall model.
The RRT (:mod:`cgail_planner.core.rrt_planner`) checks states, not steps, every
``resolution`` along a motion: for it a state is out when it lies in a disc's slab, beyond the
plane by at most a depth larger than that spacing and within ``radius +`` :data:`EXIT_MARGIN`
of the axis (:func:`in_exit_slab`), which a motion crossing the disc cannot step over.
The bounding-box exit of :func:`cgail_sim.scenarios.episode_bounds` stays beside this
rule (a tip that left by an unmodelled route).

A disc set is a ``(D, 7)`` float64 array, one row ``(cx, cy, cz, nx, ny, nz, radius)`` per
disc (:func:`disc_array`), so the numba kernels take it as one argument.
"""

from __future__ import annotations

from numba import njit
import numpy as np
from numpy.typing import NDArray

__all__ = ["DISC_COLUMNS", "EXIT_MARGIN", "crossed_disc", "crossed_discs", "disc_array",
           "in_exit_slab"]

FloatArray = NDArray[np.float64]

#: Columns of a disc row: centre (3), unit normal out of the lumen (3), radius.
DISC_COLUMNS = 7
#: Added to each disc's radius, m: a cap's rim vertices lie on its measured radius and the
#: crossing point of a step along the rim must still count.
EXIT_MARGIN = 1e-3


def disc_array(centres: FloatArray, normals: FloatArray, radii: FloatArray) -> FloatArray:
    """Pack discs into the ``(D, 7)`` array the exit tests take (read-only).

    Args:
        centres: (D, 3) disc centres, m.
        normals: (D, 3) normals out of the lumen (normalised here).
        radii: (D,) radii, m (> 0).

    Raises:
        ValueError: shapes that disagree, non-finite values, a zero normal or a radius <= 0.
    """
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    if not len(c) == len(n) == len(r):
        raise ValueError(f"expected as many centres, normals and radii, found {len(c)}, "
                         f"{len(n)} and {len(r)}")
    if not (np.isfinite(c).all() and np.isfinite(n).all() and np.isfinite(r).all()):
        raise ValueError("expected finite disc centres, normals and radii, found a non-finite "
                         "value")
    length = np.linalg.norm(n, axis=1)
    if (length < 1e-12).any() or (r <= 0.0).any():
        raise ValueError(f"expected non-zero normals and radii > 0, found normal lengths "
                         f"{length.tolist()} and radii {r.tolist()}")
    out = np.hstack([c, n / length[:, None], r[:, None]])
    out.setflags(write=False)
    return out


@njit(cache=True)
def crossed_disc(x0, y0, z0, x1, y1, z1, discs):
    """Index of the first disc the step ``(x0, y0, z0) -> (x1, y1, z1)`` leaves the lumen
    through (module docstring), or -1."""
    for k in range(discs.shape[0]):
        cx, cy, cz = discs[k, 0], discs[k, 1], discs[k, 2]
        nx, ny, nz = discs[k, 3], discs[k, 4], discs[k, 5]
        h0 = (x0 - cx) * nx + (y0 - cy) * ny + (z0 - cz) * nz
        h1 = (x1 - cx) * nx + (y1 - cy) * ny + (z1 - cz) * nz
        if h0 <= 0.0 < h1:
            t = h0 / (h0 - h1)
            dx = x0 + t * (x1 - x0) - cx
            dy = y0 + t * (y1 - y0) - cy
            dz = z0 + t * (z1 - z0) - cz
            r = discs[k, 6] + EXIT_MARGIN
            if dx * dx + dy * dy + dz * dz <= r * r:
                return k
    return -1


@njit(cache=True)
def crossed_discs(previous, tips, discs):
    """(N,) bool: True where the step ``previous[i] -> tips[i]`` ((N, 3) each) left the lumen
    through a disc (:func:`crossed_disc`)."""
    n = tips.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        out[i] = crossed_disc(previous[i, 0], previous[i, 1], previous[i, 2],
                              tips[i, 0], tips[i, 1], tips[i, 2], discs) >= 0
    return out


@njit(cache=True)
def in_exit_slab(x, y, z, discs, depth):
    """Index of the first disc whose slab holds the point ``(x, y, z)``, or -1: beyond the
    disc's plane by at most ``depth`` (``0 < h <= depth``) and within ``radius +``
    :data:`EXIT_MARGIN` of its axis. The state-wise form of :func:`crossed_disc` for a path
    checked at points less than ``depth`` apart (module docstring)."""
    for k in range(discs.shape[0]):
        cx, cy, cz = discs[k, 0], discs[k, 1], discs[k, 2]
        nx, ny, nz = discs[k, 3], discs[k, 4], discs[k, 5]
        h = (x - cx) * nx + (y - cy) * ny + (z - cz) * nz
        if 0.0 < h <= depth:
            dx = x - cx - h * nx
            dy = y - cy - h * ny
            dz = z - cz - h * nz
            r = discs[k, 6] + EXIT_MARGIN
            if dx * dx + dy * dy + dz * dz <= r * r:
                return k
    return -1

"""The C-GAIL policy rollout as one numba call: rays, observation, policy, kinematics, checks.

:meth:`cgail_planner.core.planner.Planner.rollout_reference` is the specification: a Python loop
that calls the wall's ray cast and contact query and the policy once per step (~60 us of
interpreter work per step on top of the ~10-20 us ray cast). :func:`rollout_kernel` runs the same
loop natively with the numba forms of the catheter model
(:func:`~cgail_sim.ftl_model.observe_nb`, :func:`~cgail_sim.ftl_model.command_nb`,
:func:`~cgail_sim.ftl_model.advance_nb`, :func:`~cgail_sim.ftl_model.
retract_chain`), the BVH query kernels of :mod:`cgail_sim.raycast` and the policy's
:class:`~cgail_planner.core.mlp.MlpProgram` (:func:`~cgail_planner.core.mlp.mlp_forward`), with
the observation and the action rounded to float32 exactly as the Python loop does around its
policy call, so both give the same path (to rounding differences of numpy's 3x3 products,
~1e-16 m per step).

Status codes returned by the kernel (the planner turns them into its errors):
:data:`REACHED`, :data:`COLLIDED`, :data:`BAD_ACTION`, :data:`LEFT_ANATOMY`, :data:`STEP_LIMIT`.
"""

from __future__ import annotations

import math

from numba import njit
import numpy as np

from cgail_planner.core import mlp
from cgail_planner.core.mlp import mlp_forward
from cgail_sim import exits, ftl_model, raycast
from cgail_sim.exits import crossed_disc
from cgail_sim.ftl_model import (
    advance_nb,
    command_nb,
    observe_nb,
    observe_probes_nb,
    PROBE_RANGE,
    retract_chain,
)
from cgail_sim.raycast import (
    closest_kernel,
    drop_stale_numba_cache,
    feature_normal_kernel,
    raycast_kernel,
)

# the kernel calls kernels of other modules: its disk cache must follow their sources
drop_stale_numba_cache(__file__, [__file__, mlp.__file__, raycast.__file__, ftl_model.__file__,
                                  exits.__file__])

__all__ = ["BAD_ACTION", "COLLIDED", "LEFT_ANATOMY", "REACHED", "STEP_LIMIT", "rollout_kernel"]

REACHED = 0
"""The tip came within the goal tolerance; ``steps`` is the step that reached it."""
COLLIDED = 1
"""The tip sphere penetrated the wall at step ``steps``."""
BAD_ACTION = 2
"""The policy returned a non-finite action (in ``action``) at step ``steps``."""
LEFT_ANATOMY = 3
"""The tip left through the disc of an open end (:mod:`cgail_sim.exits`) or left the
bounding box at step ``steps``."""
STEP_LIMIT = 4
"""``max_steps`` steps without reaching the goal."""


@njit(cache=True)
def _penetration(bvh, px, py, pz, radius, tolerance):
    """``(penetration, clearance)`` of the tip sphere vs the wall: the numba form of
    :meth:`cgail_sim.wall.StaticWall.tip_contact` (without the force)."""
    p = np.empty(3)
    p[0], p[1], p[2] = px, py, pz
    dist, face, q, u, v, w = closest_kernel(bvh.vertices, bvh.faces, bvh.order, bvh.node_min,
                                            bvh.node_max, bvh.left, bvh.right, bvh.leaf_start,
                                            bvh.leaf_count, p, np.inf)
    if face < 0:
        return 0.0, np.inf
    n = feature_normal_kernel(bvh.vertices, bvh.faces, bvh.face_edges, bvh.vf_ptr,
                              bvh.vf_face, bvh.ef_ptr, bvh.ef_face, face, u, v, w)
    side = (px - q[0]) * n[0] + (py - q[1]) * n[1] + (pz - q[2]) * n[2]
    depth = radius + (dist if side > 0.0 else -dist)  # signed distance < 0 on the lumen side
    return (depth if depth > tolerance else 0.0), max(-depth, 0.0)


@njit(cache=True)
def rollout_kernel(positions, rotations, arc, n0, goal, rays, probes, paper_code, origin,
                   position_scale, d_max, ray_length, theta_max, segment_length, step_len,
                   forward_only, radius, dt, tolerance, goal_tolerance, exit_discs, low,
                   high, max_steps, bvh, ops, consts, widths, regs, out_reg, action):
    """Roll the policy out from the tip of a seeded body (Planner.rollout_reference).

    Args:
        positions: (K, 3) body node positions, seeded with ``n0`` nodes (the introducer tail
            and the start pose, :func:`~cgail_sim.ftl_model.seed_body`); output: the
            body at the end. K >= max_steps + n0.
        rotations: (K, 3, 3) the nodes' rotations (seeded likewise).
        arc: (K,) the nodes' arc lengths (seeded likewise).
        n0: number of seeded nodes; the last one is the start pose.
        goal: (3,) goal, m.
        rays: (R, 3) ray directions in the tip frame.
        probes: (P, 3) ``paper_code`` probe points in the tip frame, m.
        paper_code: observe the ``paper_code`` way (probes) instead of ours (rays).
        origin: (3,) observation origin, m.
        position_scale, d_max, ray_length: the observation's normalisers, m.
        theta_max, segment_length, step_len: the catheter model (rad, m, m per step).
        forward_only: the catheter's insertion rule (``|a[2]|``).
        radius: catheter radius, m.
        dt: step length, s (unused: the frozen wall has no contact force).
        tolerance: the wall's penetration tolerance, m.
        goal_tolerance: success distance, m.
        exit_discs: (D, 7) the open cuts (:attr:`cgail_sim.anatomy.Anatomy.exit_discs`).
        low, high: (3,) bounding box, m.
        max_steps: step limit.
        bvh: the wall's :class:`~cgail_sim.raycast.BVHArrays`.
        ops, consts, widths, regs, out_reg: the policy's MlpProgram (16 + R inputs, or 11 + P
            for ``paper_code``; 3 outputs).
        action: (3,) output: the last raw action (float32-rounded).

    Returns:
        ``(status, steps, n)``: a status code of this module, the step it refers to, and the
        number of valid body nodes (the last one is the final tip).
    """
    n_rays = rays.shape[0]
    n_probes = probes.shape[0]
    origins = np.empty((n_rays, 3))
    dirs = np.empty((n_rays, 3))
    hits = np.empty(n_rays)
    dists = np.empty(n_probes)
    point = np.empty(3)
    obs = np.empty(11 + n_probes if paper_code else 16 + n_rays)
    p = positions[n0 - 1].copy()
    r = rotations[n0 - 1].copy()
    n = n0
    gx, gy, gz = goal[0], goal[1], goal[2]
    clearance = -np.inf
    for step in range(1, max_steps + 1):
        if paper_code:
            for k in range(n_probes):
                for a in range(3):
                    point[a] = p[a] + (r[a, 0] * probes[k, 0] + r[a, 1] * probes[k, 1]
                                       + r[a, 2] * probes[k, 2])
                dist, face, _, _, _, _ = closest_kernel(
                    bvh.vertices, bvh.faces, bvh.order, bvh.node_min, bvh.node_max, bvh.left,
                    bvh.right, bvh.leaf_start, bvh.leaf_count, point, PROBE_RANGE)
                dists[k] = dist if face >= 0 else np.inf
            observe_probes_nb(obs, p[0], p[1], p[2], r, gx, gy, gz, dists, origin)
        else:
            for k in range(n_rays):
                origins[k, 0] = p[0]
                origins[k, 1] = p[1]
                origins[k, 2] = p[2]
                for a in range(3):
                    dirs[k, a] = (rays[k, 0] * r[a, 0] + rays[k, 1] * r[a, 1]
                                  + rays[k, 2] * r[a, 2])
            raycast_kernel(bvh.vertices, bvh.faces, bvh.order, bvh.node_min, bvh.node_max,
                           bvh.left, bvh.right, bvh.leaf_start, bvh.leaf_count, origins, dirs,
                           ray_length, hits)
            observe_nb(obs, p[0], p[1], p[2], r, gx, gy, gz, hits, origin, position_scale,
                       d_max, ray_length)
        mlp_forward(ops, consts, widths, regs, obs)
        finite = True
        for a in range(3):
            action[a] = np.float32(regs[out_reg, a])
            finite = finite and math.isfinite(action[a])
        if not finite:
            return BAD_ACTION, step, n
        x0, y0, z0 = p[0], p[1], p[2]
        alpha, gamma, dl = command_nb(action[0], action[1], action[2], theta_max,
                                      segment_length, step_len, forward_only)
        travelled = 0.0
        if dl > 0.0:
            advance_nb(p, r, alpha, gamma, dl)
            for a in range(3):
                positions[n, a] = p[a]
                for b in range(3):
                    rotations[n, a, b] = r[a, b]
            arc[n] = arc[n - 1] + dl
            n += 1
            travelled = dl
        elif dl < 0.0:
            n, travelled = retract_chain(positions, arc, n, -dl)
            for a in range(3):
                p[a] = positions[n - 1, a]
                for b in range(3):
                    r[a, b] = rotations[n - 1, a, b]
        # the episode's ending, in its order: collision, exit, success
        clearance -= travelled
        if clearance <= 1e-9:
            pen, clear = _penetration(bvh, p[0], p[1], p[2], radius, tolerance)
            if pen > 0.0:
                return COLLIDED, step, n
            clearance = clear if math.isfinite(clear) else -np.inf
        out = crossed_disc(x0, y0, z0, p[0], p[1], p[2], exit_discs) >= 0
        for a in range(3):
            out = out or p[a] < low[a] or p[a] > high[a]
        if out:
            return LEFT_ANATOMY, step, n
        dx, dy, dz = gx - p[0], gy - p[1], gz - p[2]
        if math.sqrt(dx * dx + dy * dy + dz * dz) < goal_tolerance:
            return REACHED, step, n
    return STEP_LIMIT, max_steps, n

"""The C-GAIL policy rollout as one numba call: rays, observation, policy, kinematics, checks.

:meth:`cgail_planner.core.planner.Planner.rollout_reference` is the specification: a Python loop
that calls the wall's ray cast and the policy once per step (~60 us of interpreter work per step
on top of the ~20 us ray cast). :func:`rollout_kernel` runs the same loop natively, calling the
BVH ray kernel of :mod:`cgail_planner.sim.raycast` and the policy's
:class:`~cgail_planner.core.mlp.MlpProgram` (:func:`~cgail_planner.core.mlp.mlp_forward`)
directly, with the same floating-point operations in the same order: the observation is rounded
to float32 and the action to float32 exactly as the Python loop does around its policy call, so
both give the same path (to rounding differences of numpy's 3x3 products, ~1e-16 m per step).

Status codes returned by the kernel (the planner turns them into its errors):
:data:`REACHED`, :data:`TOUCHED_WALL`, :data:`BAD_ACTION`, :data:`LEFT_ANATOMY`,
:data:`STEP_LIMIT`.
"""

from __future__ import annotations

import math

from numba import njit
import numpy as np

from cgail_planner.core import mlp
from cgail_planner.core.mlp import mlp_forward
from cgail_planner.sim import raycast
from cgail_planner.sim.raycast import _raycast, drop_stale_numba_cache

# the kernel calls kernels of other modules: its disk cache must follow their sources
drop_stale_numba_cache(__file__, [__file__, mlp.__file__, raycast.__file__])

__all__ = ["BAD_ACTION", "LEFT_ANATOMY", "REACHED", "STEP_LIMIT", "TOUCHED_WALL",
           "rollout_kernel"]

REACHED = 0
"""The tip came within the goal tolerance; ``steps`` is the step that reached it."""
TOUCHED_WALL = 1
"""A ray shorter than the catheter radius; ``steps`` is the number of steps taken before."""
BAD_ACTION = 2
"""The policy returned a non-finite action (in ``action``) at step ``steps``."""
LEFT_ANATOMY = 3
"""The tip left the bounding box at step ``steps``."""
STEP_LIMIT = 4
"""``max_steps`` steps without reaching the goal."""


@njit(cache=True)
def rollout_kernel(p0, r0, goal, rays, origin, inv_scale, inv_dmax, inv_ray, ray_length,
                   radius, step_len, per_len, tol2, low, high, max_steps,
                   vertices, faces, order, node_min, node_max, left, right, start, count,
                   ops, consts, widths, regs, out_reg,
                   positions, rotations, action):
    """Roll the policy out from ``[r0 | p0]`` towards ``goal`` (Planner.rollout_reference).

    Args:
        p0, r0, goal: (3,) start position, (3, 3) start rotation, (3,) goal, m.
        rays: (R, 3) ray directions in the tip frame.
        origin: (3,) observation origin, m.
        inv_scale, inv_dmax, inv_ray: 1 / position scale, 1 / d_max, 1 / ray length.
        ray_length: ray length, m.
        radius: catheter radius (contact threshold of the rays), m.
        step_len: insertion per step at full action, m.
        per_len: theta_max / L, rad/m.
        tol2: squared goal tolerance, m^2.
        low, high: (3,) bounding box, m.
        max_steps: step limit.
        vertices ... count: the wall BVH (as :meth:`cgail_planner.sim.raycast.WallBVH.raycast`
            passes it to its kernel).
        ops, consts, widths, regs, out_reg: the policy's MlpProgram (16 + R inputs, 3 outputs).
        positions: (max_steps + 1, 3) output: the rolled-out tip positions.
        rotations: (max_steps + 1, 3, 3) scratch: the tip frames of the body.
        action: (3,) output: the last raw action (float32-rounded).

    Returns:
        ``(status, steps, n_points)``: a status code of this module, the step count it refers
        to, and the number of valid rows of ``positions`` (the last one is the final tip).
    """
    n_rays = rays.shape[0]
    origins = np.empty((n_rays, 3))
    dirs = np.empty((n_rays, 3))
    hits = np.empty(n_rays)
    obs = np.empty(16 + n_rays)
    for a in range(3):
        positions[0, a] = p0[a]
        for b in range(3):
            rotations[0, a, b] = r0[a, b]
    n = 1
    px, py, pz = p0[0], p0[1], p0[2]
    r = r0.copy()
    gx, gy, gz = goal[0], goal[1], goal[2]
    for step in range(1, max_steps + 1):
        for k in range(n_rays):
            origins[k, 0] = px
            origins[k, 1] = py
            origins[k, 2] = pz
            for a in range(3):
                dirs[k, a] = rays[k, 0] * r[a, 0] + rays[k, 1] * r[a, 1] + rays[k, 2] * r[a, 2]
        _raycast(vertices, faces, order, node_min, node_max, left, right, start, count,
                 origins, dirs, ray_length, hits)
        if step > 1:
            shortest = hits[0]
            for k in range(1, n_rays):
                shortest = min(shortest, hits[k])
            if shortest < radius:
                return TOUCHED_WALL, step - 1, n
        # the observation, rounded to float32 as the environment's is
        obs[0] = np.float32((px - origin[0]) * inv_scale)
        obs[1] = np.float32((py - origin[1]) * inv_scale)
        obs[2] = np.float32((pz - origin[2]) * inv_scale)
        for i in range(3):
            for j in range(3):
                obs[3 + 3 * i + j] = np.float32(r[j, i])
        vx = (gx - px) * inv_dmax
        vy = (gy - py) * inv_dmax
        vz = (gz - pz) * inv_dmax
        obs[12] = np.float32(math.sqrt(vx * vx + vy * vy + vz * vz))
        obs[13] = np.float32(vx)
        obs[14] = np.float32(vy)
        obs[15] = np.float32(vz)
        for k in range(n_rays):
            h = min(max(hits[k] * inv_ray, 0.0), 1.0)
            obs[16 + k] = np.float32(h)
        mlp_forward(ops, consts, widths, regs, obs)
        finite = True
        for a in range(3):
            action[a] = np.float32(regs[out_reg, a])
            finite = finite and math.isfinite(action[a])
        if not finite:
            return BAD_ACTION, step, n
        a0 = min(max(action[0], -1.0), 1.0)
        a1 = min(max(action[1], -1.0), 1.0)
        a2 = min(max(action[2], -1.0), 1.0)
        dl = a2 * step_len
        if dl > 0.0:
            limit = per_len * dl
            alpha = a0 * limit
            gamma = a1 * limit
            ca, sa, cg, sg = math.cos(alpha), math.sin(alpha), math.cos(gamma), math.sin(gamma)
            # r <- r @ [[cg, -sg, 0], [ca sg, ca cg, -sa], [sa sg, sa cg, ca]]
            for a in range(3):
                r0a, r1a, r2a = r[a, 0], r[a, 1], r[a, 2]
                r[a, 0] = r0a * cg + r1a * (ca * sg) + r2a * (sa * sg)
                r[a, 1] = r0a * (-sg) + r1a * (ca * cg) + r2a * (sa * cg)
                r[a, 2] = r0a * 0.0 + r1a * (-sa) + r2a * ca
            px = px + dl * r[0, 1]
            py = py + dl * r[1, 1]
            pz = pz + dl * r[2, 1]
            positions[n, 0] = px
            positions[n, 1] = py
            positions[n, 2] = pz
            for a in range(3):
                for b in range(3):
                    rotations[n, a, b] = r[a, b]
            n += 1
        elif dl < 0.0 and n > 1:
            back = -dl
            while back > 0.0 and n > 1:
                sx = positions[n - 1, 0] - positions[n - 2, 0]
                sy = positions[n - 1, 1] - positions[n - 2, 1]
                sz = positions[n - 1, 2] - positions[n - 2, 2]
                seg = math.sqrt(sx * sx + sy * sy + sz * sz)
                if seg <= back + 1e-12:
                    n -= 1
                    back -= seg
                else:
                    frac = back / seg
                    for a in range(3):
                        positions[n - 1, a] = positions[n - 1, a] + frac * (
                            positions[n - 2, a] - positions[n - 1, a])
                    back = 0.0
            px, py, pz = positions[n - 1, 0], positions[n - 1, 1], positions[n - 1, 2]
            for a in range(3):
                for b in range(3):
                    r[a, b] = rotations[n - 1, a, b]
        if (gx - px) ** 2 + (gy - py) ** 2 + (gz - pz) ** 2 < tol2:
            return REACHED, step, n
        if not (low[0] <= px <= high[0] and low[1] <= py <= high[1]
                and low[2] <= pz <= high[2]):
            return LEFT_ANATOMY, step, n
    return STEP_LIMIT, max_steps, n

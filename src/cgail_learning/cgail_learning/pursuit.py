"""Pure pursuit of a polyline: the one owner of the carrot rule and its predicted rollouts.

The rule (the centerline follower's, :class:`~cgail_learning.evaluate.
CenterlineFollower`, and the one the scripted expert predicts with, :mod:`cgail_planner.
learning.expert`):

* ``progress`` is the furthest waypoint index the tip has come nearest to (it never goes back);
* the carrot is the waypoint ``lookahead`` past it (clamped to the last one);
* the carrot is the target instead once the tip is within ``approach`` of the target, or the
  carrot index has reached the polyline's last two waypoints;
* the action turns the heading as far as the step's bend limit allows towards the carrot
  (:func:`~cgail_sim.ftl_model.steer_towards`), at full insertion.

:func:`rollout` predicts K action sequences (each a constant action held for some steps, then
the pursuit) with the catheter's follow-the-leader kinematics in one numba kernel: the expert
rolls out 51 sequences of 128 steps at every re-plan, which in numpy was two thirds of its
time (a per-step Python loop over tiny arrays). The kernel uses the catheter model's own numba
forms (:func:`~cgail_sim.ftl_model.command_nb`, :func:`~cgail_sim.ftl_model.
advance_nb`, :func:`~cgail_sim.ftl_model.steer_nb`).
"""

from __future__ import annotations

import math
from typing import Any

from numba import njit
import numpy as np

from cgail_sim.ftl_model import advance_nb, command_nb, steer_nb


@njit(cache=True)
def _nearest_index(p, points):
    """Index of the point of ``points`` (N, 3) nearest ``p`` (3,) (the first on a tie)."""
    best, k = np.inf, 0
    for i in range(points.shape[0]):
        d0 = p[0] - points[i, 0]
        d1 = p[1] - points[i, 1]
        d2 = p[2] - points[i, 2]
        d = d0 * d0 + d1 * d1 + d2 * d2
        if d < best:
            best, k = d, i
    return k


@njit(cache=True)
def carrot_nb(p, points, progress, lookahead, target, approach, carrot):
    """The carrot rule for the tip at ``p``: writes the carrot into ``carrot`` (3,) and returns
    ``(progress, final)`` (the updated progress; whether the carrot is the target)."""
    progress = max(progress, _nearest_index(p, points))
    last = points.shape[0] - 1
    k = min(progress + lookahead, last)
    d0, d1, d2 = p[0] - target[0], p[1] - target[1], p[2] - target[2]
    final = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) < approach or k >= last - 1
    for j in range(3):
        carrot[j] = target[j] if final else points[k, j]
    return progress, final


def carrot(p: np.ndarray, points: np.ndarray, progress: int, lookahead: int,
           target: np.ndarray, approach: float) -> tuple[np.ndarray, int, bool]:
    """:func:`carrot_nb` from Python: ``(carrot, progress, final)``."""
    out = np.empty(3)
    prog, final = carrot_nb(np.ascontiguousarray(p, np.float64),
                            np.ascontiguousarray(points, np.float64), int(progress),
                            int(lookahead), np.ascontiguousarray(target, np.float64),
                            float(approach), out)
    return out, int(prog), bool(final)


@njit(cache=True)
def _rollout_kernel(p0, r0, first, hold, points, progress0, lookahead, target, approach,
                    theta_max, segment_length, max_step, forward_only, steps, scored,
                    pts_out, acts_out):
    limit = theta_max * max_step / segment_length  # (the steering's bend limit at full insertion)
    goal = np.empty(3)
    p = np.empty(3)
    r = np.empty((3, 3))
    for k in range(first.shape[0]):
        p[:] = p0
        r[:, :] = r0
        progress = progress0
        for t in range(steps):
            progress, _ = carrot_nb(p, points, progress, lookahead, target, approach, goal)
            if t < hold[k]:
                a0, a1, a2 = first[k, 0], first[k, 1], first[k, 2]
            else:
                a0, a1 = steer_nb(p, r, goal, limit)
                a2 = 1.0
            al, ga, dl = command_nb(a0, a1, a2, theta_max, segment_length, max_step,
                                    forward_only)
            advance_nb(p, r, al, ga, dl)
            pts_out[k, t, 0], pts_out[k, t, 1], pts_out[k, t, 2] = p[0], p[1], p[2]
            if t < scored:
                acts_out[k, t, 0], acts_out[k, t, 1], acts_out[k, t, 2] = a0, a1, a2


def rollout(p: np.ndarray, R: np.ndarray, first: np.ndarray, hold: np.ndarray,
            points: np.ndarray, progress: int, lookahead: int, target: np.ndarray,
            approach: float, catheter: Any, theta_max: float, steps: int, scored: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """Predict K sequences from the tip pose ``(p, R)``: sequence k holds ``first[k]`` for
    ``hold[k]`` steps, then pursues ``points`` (the rule above, from ``progress``).

    Args:
        p, R: (3,) tip position, m, and (3, 3) rotation.
        first: (K, 3) normalised actions held first; hold: (K,) steps each is held.
        points: (W, 3) the polyline pursued; target: (3,) the target, m.
        catheter: the :class:`~cgail_sim.config.CatheterConfig` (its segment length,
            per-step insertion and ``forward_only``); theta_max: its current maximal bend, rad.
        steps: steps predicted; scored: leading steps whose actions are returned.

    Returns:
        ``(tips, actions)``: (K, steps, 3) predicted tip positions after each step, m, and
        (K, scored, 3) the normalised actions of the first ``scored`` steps.
    """
    first = np.ascontiguousarray(first, np.float64).reshape(-1, 3)
    tips = np.empty((len(first), steps, 3))
    acts = np.empty((len(first), scored, 3))
    _rollout_kernel(np.ascontiguousarray(p, np.float64), np.ascontiguousarray(R, np.float64),
                    first, np.ascontiguousarray(hold, np.int64),
                    np.ascontiguousarray(points, np.float64), int(progress), int(lookahead),
                    np.ascontiguousarray(target, np.float64), float(approach),
                    float(theta_max), float(catheter.segment_length),
                    float(catheter.max_step_insertion), bool(catheter.forward_only),
                    int(steps), int(scored), tips, acts)
    return tips, acts

"""Follow-the-leader (FTL) steerable catheter: the moving agent of the paper (section III-A).

Conventions (SI units; the paper's numbers are quoted in mm/deg for readability):

* **Tip frame F_A.** The tip pose is ``q_t = [R | p]`` with ``R`` a 3x3 rotation matrix whose
  columns are the tip axes ``x_A, y_A, z_A`` expressed in the world frame ``phantom`` and ``p``
  the tip position. The catheter inserts along ``y_A`` (the heading).
* **Bend.** One action ``[alpha, gamma, delta_l]`` bends the tip by ``alpha`` about ``x_A`` and
  by ``gamma`` about ``z_A`` (intrinsic rotations, x first), then inserts by ``delta_l`` along the
  new heading::

      R_{t+1} = R_t @ Rx(alpha) @ Rz(gamma)
      p_{t+1} = p_t + delta_l * R_{t+1}[:, 1]

  so the paper's ``R(alpha, 0, gamma)`` (Euler x-y-z with zero y) is the per-step increment and
  the tip orientation is the running product of those increments from the start pose.
* **Bend limit.** Each bend angle lies in ``[-theta_max^t, theta_max^t]`` with
  ``theta_max^t = theta_max * |delta_l| / L`` (paper eq. 2), ``theta_max = 90 deg`` and the
  steerable segment ``L = 50 mm``: zero insertion gives zero bend, and the tightest path the tip
  can follow about one axis has radius ``L / theta_max = 31.8 mm``.
* **Time step.** ``dt = 0.1 s`` by default with the maximal insertion speed ``5 mm/s``, so
  ``|delta_l| <= 0.5 mm`` and ``|alpha|, |gamma| <= 0.9 deg`` per step. The aortic path from the
  descending aorta to a coronary ostium is ~250-350 mm, i.e. >= 500-700 steps, the order of the
  paper's reported T_s (thousands of steps).
* **Normalised actions.** Policies act in ``a in [-1, 1]^3`` (out-of-range values are clipped)::

      delta_l = a[2] * v_max * dt
      alpha   = a[0] * theta_max^t(|delta_l|)
      gamma   = a[1] * theta_max^t(|delta_l|)

* **Body.** The body is the chain of previous tip poses (nodes). Every inserting step appends the
  new tip pose. At reset the chain holds an *introducer*: a straight segment from just outside the
  open descending end of the aorta to the start pose, so that retraction can pull the tip back
  out of the lumen (which is what the r_exit event is about).
* **Retraction** (``delta_l < 0``): the tip slides back along its own body by ``|delta_l|``
  (follow-the-leader in reverse): nodes passed are popped, the tip is interpolated on the body
  segment it stops on and takes the orientation of that segment's distal node. The bend angles
  are ignored while retracting (the body constrains the tip; the applied bend is reported as 0).
  The tip cannot retract beyond the first introducer node.
* **Curriculum.** ``theta_max`` is a run-time argument of the kinematics, so an environment can
  lower it between episodes (``CatheterNavEnv.set_theta_max``).

Everything here is batched over a leading environment axis (``N``) and pure numpy, so the single
environment (``N = 1``) and the vectorised environment share one implementation.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Default maximal bending angle theta_max (paper: 90 deg).
THETA_MAX_DEFAULT = math.pi / 2.0


@dataclass(frozen=True)
class CatheterConfig:
    """Geometric and kinematic constraints of the steerable catheter (paper, section III-A)."""

    theta_max: float = THETA_MAX_DEFAULT
    """Maximal bending angle of the steerable segment, rad (paper: 90 deg); in (0, pi]."""
    segment_length: float = 0.050
    """Length L of the steerable distal segment, m (paper: 50 mm); in [1 mm, 0.5 m]."""
    outer_diameter: float = 0.007
    """Outer diameter of the catheter, m (paper: 7 mm); in [0.5 mm, 20 mm]."""
    max_insertion_speed: float = 0.005
    """Maximal insertion/retraction speed v_max, m/s (paper: 5 mm/s); in (0, 0.1]."""
    dt: float = 0.1
    """Control time step, s: ``|delta_l| <= v_max * dt`` (0.5 mm by default); in [1 ms, 2 s]."""

    def __post_init__(self) -> None:
        _check_range("theta_max", self.theta_max, 0.0, math.pi, low_open=True)
        _check_range("segment_length", self.segment_length, 1e-3, 0.5)
        _check_range("outer_diameter", self.outer_diameter, 5e-4, 0.02)
        _check_range("max_insertion_speed", self.max_insertion_speed, 0.0, 0.1, low_open=True)
        _check_range("dt", self.dt, 1e-3, 2.0)

    @property
    def radius(self) -> float:
        """Catheter (and tip sphere) radius, m."""
        return 0.5 * self.outer_diameter

    @property
    def max_step_insertion(self) -> float:
        """Largest insertion (or retraction) per step ``v_max * dt``, m."""
        return self.max_insertion_speed * self.dt


def _check_range(
    name: str, value: float, low: float, high: float, *, low_open: bool = False
) -> None:
    """Raise ValueError unless ``low <= value <= high`` (``low < value`` when ``low_open``)."""
    ok = math.isfinite(value) and (value > low if low_open else value >= low) and value <= high
    if not ok:
        bracket = "(" if low_open else "["
        raise ValueError(f"{name} must be in {bracket}{low}, {high}], found {value!r}")


def bend_limit(delta_l: FloatArray | float, theta_max: float, segment_length: float) -> FloatArray:
    """Per-step bend limit ``theta_max^t = theta_max * |delta_l| / L`` (paper eq. 2), rad."""
    return theta_max * np.abs(np.asarray(delta_l, dtype=np.float64)) / segment_length


def action_to_command(
    action: FloatArray, theta_max: float, segment_length: float, max_step_insertion: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Map normalised actions ``a in [-1, 1]^3`` to ``(alpha, gamma, delta_l)``.

    Args:
        action: ``(..., 3)`` normalised actions; values outside [-1, 1] are clipped.
        theta_max: maximal bending angle, rad.
        segment_length: steerable segment length L, m.
        max_step_insertion: ``v_max * dt``, m.

    Returns:
        ``alpha`` and ``gamma`` (rad) and ``delta_l`` (m), each of shape ``action.shape[:-1]``.
    """
    a = np.minimum(np.maximum(np.asarray(action, dtype=np.float64), -1.0), 1.0)  # (as np.clip)
    delta_l = a[..., 2] * max_step_insertion
    limit = bend_limit(delta_l, theta_max, segment_length)
    return a[..., 0] * limit, a[..., 1] * limit, delta_l


def command_to_action(
    alpha: FloatArray | float,
    gamma: FloatArray | float,
    delta_l: FloatArray | float,
    theta_max: float,
    segment_length: float,
    max_step_insertion: float,
) -> FloatArray:
    """Inverse of :func:`action_to_command` (for experts and demonstrations).

    Bends beyond ``theta_max^t`` saturate at +-1; with ``delta_l == 0`` the bend entries are 0.
    """
    dl = np.clip(np.asarray(delta_l, dtype=np.float64), -max_step_insertion, max_step_insertion)
    limit = bend_limit(dl, theta_max, segment_length)
    safe = np.where(limit > 0.0, limit, 1.0)
    a0 = np.where(limit > 0.0, np.asarray(alpha, dtype=np.float64) / safe, 0.0)
    a1 = np.where(limit > 0.0, np.asarray(gamma, dtype=np.float64) / safe, 0.0)
    out = np.stack(np.broadcast_arrays(a0, a1, dl / max_step_insertion), axis=-1)
    return np.clip(out, -1.0, 1.0)


def steer_towards(tip_position: FloatArray, tip_rotation: FloatArray, goal: FloatArray,
                  config: CatheterConfig, theta_max: float | None = None,
                  insertion: float = 1.0) -> FloatArray:
    """Normalised action that turns the heading as far as allowed towards ``goal``.

    One-step inverse kinematics of the bend: with ``d = R^T (goal - p)`` in the tip frame,
    ``Rx(alpha) Rz(gamma) e_y = (-sin g, cos g cos a, cos g sin a)`` points along ``d`` for
    ``alpha = atan2(d_z, d_y)`` and ``gamma = atan2(-d_x, hypot(d_y, d_z))``. The returned
    ``a[0], a[1]`` are those angles over the step's bend limit ``theta_max^t``, saturated at +-1,
    and ``a[2] = insertion``. Batched over a leading axis.

    Args:
        tip_position: (..., 3) tip positions.
        tip_rotation: (..., 3, 3) tip rotations.
        goal: (..., 3) points to aim at.
        config: catheter constraints.
        theta_max: current maximal bend (default ``config.theta_max``).
        insertion: normalised insertion ``a[2]`` in (0, 1].

    Returns:
        (..., 3) normalised actions for :func:`action_to_command`.
    """
    th = config.theta_max if theta_max is None else theta_max
    d = np.einsum("...ji,...j->...i", tip_rotation, np.asarray(goal) - tip_position)
    alpha = np.arctan2(d[..., 2], d[..., 1])
    gamma = np.arctan2(-d[..., 0], np.hypot(d[..., 1], d[..., 2]))
    limit = float(bend_limit(insertion * config.max_step_insertion, th, config.segment_length))
    a0 = np.clip(alpha / limit, -1.0, 1.0)
    a1 = np.clip(gamma / limit, -1.0, 1.0)
    return np.stack(np.broadcast_arrays(a0, a1, np.full_like(a0, insertion)), axis=-1)


def bend_rotation(alpha: FloatArray, gamma: FloatArray) -> FloatArray:
    """Batched ``Rx(alpha) @ Rz(gamma)``: ``(...,)`` angles -> ``(..., 3, 3)`` rotations."""
    ca, sa = np.cos(alpha), np.sin(alpha)
    cg, sg = np.cos(gamma), np.sin(gamma)
    # Rx(a) @ Rz(g) = [[cg, -sg, 0], [ca*sg, ca*cg, -sa], [sa*sg, sa*cg, ca]]
    out = np.empty((*np.broadcast(ca, cg).shape, 3, 3))
    out[..., 0, 0] = cg
    out[..., 0, 1] = -sg
    out[..., 0, 2] = 0.0
    out[..., 1, 0] = ca * sg
    out[..., 1, 1] = ca * cg
    out[..., 1, 2] = -sa
    out[..., 2, 0] = sa * sg
    out[..., 2, 1] = sa * cg
    out[..., 2, 2] = ca
    return out


def frame_from_heading(heading: FloatArray, up_hint: FloatArray | None = None) -> FloatArray:
    """A tip rotation whose y axis is ``heading``; x is chosen perpendicular to ``up_hint``.

    Args:
        heading: (3,) direction (normalised here).
        up_hint: (3,) vector the tip z axis should lean towards (default world +x, or +y when the
            heading is nearly parallel to x).

    Returns:
        (3, 3) rotation with columns ``x_A, y_A, z_A``.
    """
    y = np.asarray(heading, dtype=np.float64)
    norm = float(np.linalg.norm(y))
    if not math.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"heading must be a finite non-zero vector, found {heading!r}")
    y = y / norm
    hint = np.array([1.0, 0.0, 0.0]) if up_hint is None else np.asarray(up_hint, dtype=float)
    if abs(float(np.dot(hint, y))) > 0.95 * float(np.linalg.norm(hint)):
        hint = np.array([0.0, 1.0, 0.0]) if abs(y[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(y, hint)
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=1)


class CatheterBatch:
    """N follow-the-leader catheters; each body is a chain of tip poses (nodes).

    Node ``k`` of environment ``i`` has position ``positions[i, k]``, rotation
    ``rotations[i, k]`` and arc length ``arc[i, k]`` (m, measured from the first introducer node).
    ``n_nodes[i]`` nodes are valid; the last one is the tip.
    """

    def __init__(self, n_envs: int, config: CatheterConfig, capacity: int = 256) -> None:
        if n_envs < 1:
            raise ValueError(f"n_envs must be >= 1, found {n_envs}")
        self.config = config
        self.n_envs = n_envs
        self.theta_max = config.theta_max
        cap = max(int(capacity), 4)
        self.positions = np.zeros((n_envs, cap, 3))
        self.rotations = np.tile(np.eye(3), (n_envs, cap, 1, 1))
        self.arc = np.zeros((n_envs, cap))
        self.n_nodes = np.zeros(n_envs, dtype=np.int64)
        self._rows = np.arange(n_envs)

    # ------------------------------------------------------------------ state
    @property
    def capacity(self) -> int:
        """Number of nodes each chain can hold before the arrays grow."""
        return int(self.positions.shape[1])

    @property
    def tip_index(self) -> NDArray[np.int64]:
        """(N,) index of each tip node."""
        return self.n_nodes - 1

    @property
    def tip_position(self) -> FloatArray:
        """(N, 3) tip positions, m."""
        return self.positions[self._rows, self.tip_index]

    @property
    def tip_rotation(self) -> FloatArray:
        """(N, 3, 3) tip rotations (columns x_A, y_A, z_A)."""
        return self.rotations[self._rows, self.tip_index]

    @property
    def inserted_length(self) -> FloatArray:
        """(N,) arc length of the body from the first introducer node to the tip, m."""
        return self.arc[self._rows, self.tip_index]

    def set_theta_max(self, theta_max: float) -> None:
        """Change the maximal bending angle (curriculum), rad, in (0, pi]."""
        _check_range("theta_max", theta_max, 0.0, math.pi, low_open=True)
        self.theta_max = float(theta_max)

    def reset_env(self, i: int, start_position: FloatArray, start_rotation: FloatArray,
                  introducer_tail: FloatArray) -> None:
        """Put catheter ``i`` at its start pose with a straight introducer behind it.

        Args:
            i: environment index.
            start_position: (3,) tip position, m.
            start_rotation: (3, 3) tip rotation.
            introducer_tail: (3,) position of the proximal end of the introducer (outside the
                lumen, behind the start pose along ``-y_A``).
        """
        p0 = np.asarray(introducer_tail, dtype=np.float64)
        p1 = np.asarray(start_position, dtype=np.float64)
        self.positions[i, 0] = p0
        self.positions[i, 1] = p1
        self.rotations[i, 0] = start_rotation
        self.rotations[i, 1] = start_rotation
        self.arc[i, 0] = 0.0
        self.arc[i, 1] = float(np.linalg.norm(p1 - p0))
        self.n_nodes[i] = 2

    def _grow(self) -> None:
        cap = self.capacity
        self.positions = np.concatenate([self.positions, np.zeros_like(self.positions)], axis=1)
        self.rotations = np.concatenate([self.rotations, np.zeros_like(self.rotations)], axis=1)
        self.arc = np.concatenate([self.arc, np.zeros_like(self.arc)], axis=1)
        self.rotations[:, cap:] = np.eye(3)

    # ------------------------------------------------------------------ motion
    def step(
        self, alpha: FloatArray, gamma: FloatArray, delta_l: FloatArray,
        active: NDArray[np.bool_] | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Advance every catheter by one command (already within the limits, see module doc).

        Args:
            alpha: (N,) bend about x_A, rad; clipped to +-theta_max^t.
            gamma: (N,) bend about z_A, rad; clipped to +-theta_max^t.
            delta_l: (N,) insertion (>0) or retraction (<0), m; clipped to +-v_max*dt.
            active: (N,) bool, environments to move (default all).

        Returns:
            The applied ``(alpha, gamma, delta_l)``: bends are 0 while retracting and
            ``delta_l`` is the signed distance the tip actually travelled along the body.
        """
        cfg = self.config
        # (np.minimum/np.maximum: the same values as np.clip for finite input, a third of the
        # cost on the tiny arrays of a single environment)
        m = cfg.max_step_insertion
        dl = np.minimum(np.maximum(np.asarray(delta_l, dtype=np.float64), -m), m)
        limit = bend_limit(dl, self.theta_max, cfg.segment_length)
        al = np.minimum(np.maximum(np.asarray(alpha, dtype=np.float64), -limit), limit)
        ga = np.minimum(np.maximum(np.asarray(gamma, dtype=np.float64), -limit), limit)
        fwd = dl > 0.0
        back = dl < 0.0
        if active is not None:
            act = np.asarray(active, bool)
            fwd &= act
            back &= act
        applied_dl = np.zeros(self.n_envs)

        if fwd.any():
            idx = np.flatnonzero(fwd)
            tip = self.n_nodes[idx] - 1
            if int(tip.max()) + 1 >= self.capacity:
                self._grow()
            r_new = self.rotations[idx, tip] @ bend_rotation(al[idx], ga[idx])
            p_new = self.positions[idx, tip] + dl[idx, None] * r_new[:, :, 1]
            self.positions[idx, tip + 1] = p_new
            self.rotations[idx, tip + 1] = r_new
            self.arc[idx, tip + 1] = self.arc[idx, tip] + dl[idx]
            self.n_nodes[idx] += 1
            applied_dl[idx] = dl[idx]

        for i in np.flatnonzero(back):
            applied_dl[i] = -self._retract(int(i), float(-dl[i]))
        applied_al = np.where(fwd, al, 0.0)
        applied_ga = np.where(fwd, ga, 0.0)
        return applied_al, applied_ga, applied_dl

    def _retract(self, i: int, distance: float) -> float:
        """Slide tip ``i`` back along its body by ``distance``; returns the distance travelled."""
        n = int(self.n_nodes[i])
        arc = self.arc[i, :n]
        s_tip = float(arc[-1])
        s_new = max(s_tip - distance, 0.0)
        k = int(np.searchsorted(arc, s_new, side="right")) - 1  # node at or below s_new
        k = min(max(k, 0), n - 1)
        if s_new - float(arc[k]) <= 1e-12 or k == n - 1:
            self.n_nodes[i] = k + 1
        else:
            frac = (s_new - float(arc[k])) / (float(arc[k + 1]) - float(arc[k]))
            self.positions[i, k + 1] = self.positions[i, k] + frac * (
                self.positions[i, k + 1] - self.positions[i, k]
            )
            self.arc[i, k + 1] = s_new
            self.n_nodes[i] = k + 2
        return s_tip - s_new

    # ------------------------------------------------------------------ body
    def body_points(self, i: int, spacing: float) -> FloatArray:
        """Body nodes of catheter ``i`` resampled every ``spacing`` m of arc, tip included.

        Returns:
            (B, 3) points from the proximal end to the tip (a capsule chain for the wall).
        """
        n = int(self.n_nodes[i])
        arc = self.arc[i, :n]
        marks = np.arange(0.0, float(arc[-1]), spacing)
        # sorted node indices (marks increase), duplicates dropped, the tip appended
        idx = np.minimum(np.searchsorted(arc, marks, side="left"), n - 1)
        keep = np.empty(idx.size + 1, dtype=bool)
        keep[0] = True
        np.not_equal(idx[1:], idx[:-1], out=keep[1:idx.size])
        idx = np.append(idx, n - 1)
        keep[-1] = idx.size == 1 or idx[-2] != n - 1
        return self.positions[i, idx[keep]]

    def body(self, i: int) -> FloatArray:
        """(n, 3) copy of all body nodes of catheter ``i``, proximal end first."""
        return self.positions[i, : int(self.n_nodes[i])].copy()

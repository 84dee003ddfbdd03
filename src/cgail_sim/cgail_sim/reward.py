"""Reward of the catheter navigation task: the paper's table (section III-C, Table I) exactly.

``r_t = r_end + r_in`` with

================  ========  ==========================================================
term              value     event
================  ========  ==========================================================
``r_obst``        -1        non-minor tip-wall collision (ends the episode)
``r_exit``        -1        the tip leaves the lumen through an open end: the step
                            crosses the disc of a cut (``Anatomy.exit_discs``: the
                            descending end, a branch or coronary stub end;
                            :mod:`cgail_sim.exits`), or the tip leaves the
                            bounding box (ends the episode)
``r_target``      +1        ``||p_t - p_g|| < epsilon`` (epsilon 10 mm; ends the episode)
``r_step``        -1e-5     every step
``r_centerline``  +0.05     per centerline waypoint newly reached in this episode
``r_bending``     +1e-5     the bend magnitude exceeds ``bend_threshold * theta_max^t``
================  ========  ==========================================================

Details (documented choices where the paper is silent):

* ``r_end`` takes at most one value per step, by priority ``r_obst`` > ``r_exit`` >
  ``r_target``; ``r_in`` is added on every step, the terminal one included.
* **Collision classes** (paper, section V-A): a contact is *minor* when the collision force is
  below 0.8 N and the tip does not penetrate the wall; minor contacts cost nothing. Anything else
  is non-minor: ``r_obst`` and termination.
* **Waypoints**: the ~100 waypoints of the Voronoi centerline leading to the ostium on the
  target's side (left or right coronary). A waypoint is reached when the tip is within
  ``waypoint_radius`` (6 mm) of it; each waypoint pays once per episode.
* **Bend magnitude**: ``max(|alpha|, |gamma|)`` of the applied bend. ``r_bending`` is paid when it
  exceeds ``bend_threshold`` (0.9) times the current per-step limit ``theta_max^t`` and the
  limit is positive (an inserting step; retraction and zero insertion never bend).

**The authors' code** (:data:`PAPER_CODE_REWARD`, the ``paper_code`` option set of
:mod:`cgail_sim.config`; ``docs/fidelity.md``), per 0.1 s env step, which is one decision of
theirs (``DecisionRequester.DecisionPeriod`` 5 at their 0.02 s physics step,
``shared/design/AUTHORS_SCENE.md``):

* ``r_step = -5e-5`` and ``r_bending = +5e-5``: ``Planner.cs`` pays -1e-5 in ``FixedUpdate``
  and +1e-5 in ``OnActionReceived``, both once per physics step
  (``TakeActionsBetweenDecisions`` repeats the action on the 4 steps between decisions), so
  5 times per decision. ``r_bending`` is paid on the *action* (``bend_rule='action'``) when
  ``|a0|`` or ``|a1|`` (clipped to [-1, 1]) exceeds ``bend_threshold`` 0.5, whatever the
  insertion;
* ``r_centerline = +0.005`` per waypoint reached within 3.5 mm (their 1 mm waypoint sphere,
  ``Centerline.prefab``, plus their 2.5 mm tip collider, radius 0.5 x scale 5);
* ``r_target`` when ``||p_t - p_g|| < 6.5 mm`` (their 4 mm target collider, radius 0.5 x scale
  8, plus the 2.5 mm tip collider);
* the rest of the table as above. Our collision trigger stays; where the code's collision
  *replaces* that step's other terms (``SetReward``), ours adds them (at most +0.005 + 5e-5).

All functions are pure and batched over a leading environment axis.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class RewardConfig:
    """Reward values (paper Table I) and the thresholds that trigger them."""

    r_obst: float = -1.0
    """Non-minor collision reward (paper: -1); in [-1, 0]."""
    r_exit: float = -1.0
    """Exit through the open descending end (paper: -1); in [-1, 0]."""
    r_target: float = 1.0
    """Target reached (paper: +1); in [0, 1]."""
    r_step: float = -1e-5
    """Per-step reward (paper: -1e-5); in [-1, 0]."""
    r_centerline: float = 0.05
    """Per newly reached centerline waypoint (paper: +0.05); in [0, 1]."""
    r_bending: float = 1e-5
    """Bending above the threshold (paper: +1e-5); in [0, 1]."""
    epsilon: float = 0.010
    """Success distance ||p_t - p_g||, m (paper: 10 mm); in (0, 0.1]."""
    waypoint_radius: float = 0.006
    """Distance within which a centerline waypoint counts as reached, m; in (0, 0.05]."""
    bend_threshold: float = 0.9
    """``bend_rule='applied'``: fraction of theta_max^t above which r_bending is paid;
    ``'action'``: the normalised bend action above which it is paid; in (0, 1]."""
    bend_rule: str = "applied"
    """When r_bending is paid: ``applied`` (ours: the applied bend of an inserting step above
    ``bend_threshold * theta_max^t``) or ``action`` (the authors' code: ``|a0|`` or ``|a1|``
    above ``bend_threshold``, whatever the insertion)."""
    minor_force: float = 0.8
    """Largest collision force of a minor contact, N (paper: 0.8 N in the aorta); in (0, 100]."""

    def __post_init__(self) -> None:
        for name, low, high in (
            ("r_obst", -1.0, 0.0), ("r_exit", -1.0, 0.0), ("r_target", 0.0, 1.0),
            ("r_step", -1.0, 0.0), ("r_centerline", 0.0, 1.0), ("r_bending", 0.0, 1.0),
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and low <= value <= high):
                raise ValueError(f"{name} must be in [{low}, {high}], found {value!r}")
        for name, high in (("epsilon", 0.1), ("waypoint_radius", 0.05), ("bend_threshold", 1.0),
                           ("minor_force", 100.0)):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 < value <= high):
                raise ValueError(f"{name} must be in (0, {high}], found {value!r}")
        if self.bend_rule not in BEND_RULES:
            raise ValueError(f"bend_rule must be one of {BEND_RULES}, found {self.bend_rule!r}")


#: The r_bending rules of :attr:`RewardConfig.bend_rule`.
BEND_RULES = ("applied", "action")

#: Physics steps per decision in the authors' scene (``DecisionRequester.DecisionPeriod``):
#: their per-physics-step rewards are paid this many times per 0.1 s decision, our env step.
PAPER_CODE_PHYSICS_STEPS_PER_DECISION = 5

#: The authors' reward values and triggers per decision (module docstring;
#: ``docs/fidelity.md``, "Numbers the option set needs" 4): the ``paper_code`` option set's
#: reward.
PAPER_CODE_REWARD = RewardConfig(
    r_step=-5e-5, r_bending=5e-5,  # their 1e-5 per physics step, 5 physics steps a decision
    r_centerline=0.005, epsilon=0.0065, waypoint_radius=0.0035,
    bend_rule="action", bend_threshold=0.5)


class StepEvents(NamedTuple):
    """What happened in one step, batched over environments (all arrays of shape (N,))."""

    collision: BoolArray
    """Non-minor tip-wall collision."""
    exited: BoolArray
    """The tip left the lumen through an open end (:mod:`cgail_sim.exits`)."""
    success: BoolArray
    """``||p_t - p_g|| < epsilon``."""
    new_waypoints: NDArray[np.int64]
    """Number of centerline waypoints reached for the first time this step."""
    bending: BoolArray
    """The applied bend exceeded the threshold."""


class RewardTerms(NamedTuple):
    """The reward of one step split into its table entries (each (N,))."""

    end: FloatArray
    step: FloatArray
    centerline: FloatArray
    bending: FloatArray

    @property
    def total(self) -> FloatArray:
        """``r_t = r_end + r_step + r_centerline + r_bending``."""
        return self.end + self.step + self.centerline + self.bending


def non_minor_collision(force: FloatArray, penetration: FloatArray,
                        config: RewardConfig) -> BoolArray:
    """True where a contact is non-minor: ``force >= minor_force`` or ``penetration > 0``."""
    f = np.asarray(force, dtype=np.float64)
    pen = np.asarray(penetration, dtype=np.float64)
    return (f >= config.minor_force) | (pen > 0.0)


def reached_target(tip: FloatArray, target: FloatArray, config: RewardConfig) -> BoolArray:
    """True where ``||p_t - p_g|| < epsilon``; ``tip`` and ``target`` are (N, 3)."""
    return np.asarray(np.linalg.norm(np.asarray(tip) - target, axis=-1) < config.epsilon)


def update_waypoints(tip: FloatArray, waypoints: FloatArray, reached: BoolArray,
                     config: RewardConfig) -> NDArray[np.int64]:
    """Mark waypoints within ``waypoint_radius`` of the tip; return how many are new.

    Args:
        tip: (N, 3) tip positions.
        waypoints: (N, W, 3) waypoints of each environment's centerline.
        reached: (N, W) bool, updated in place.
        config: reward configuration.

    Returns:
        (N,) number of waypoints reached for the first time.
    """
    d2 = np.sum((waypoints - np.asarray(tip)[:, None, :]) ** 2, axis=-1)
    near = d2 < config.waypoint_radius**2
    new = near & ~reached
    reached |= near
    return new.sum(axis=1).astype(np.int64)


def bending_event(alpha: FloatArray, gamma: FloatArray, limit: FloatArray,
                  config: RewardConfig, action: FloatArray | None = None) -> BoolArray:
    """Where r_bending is paid (:attr:`RewardConfig.bend_rule`).

    ``applied``: ``max(|alpha|, |gamma|) > bend_threshold * limit`` and ``limit > 0``.
    ``action``: ``max(|a0|, |a1|) > bend_threshold`` of the (N, 3) ``action`` clipped to
    [-1, 1] (required then).
    """
    if config.bend_rule == "action":
        if action is None:
            raise ValueError("bend_rule 'action' needs the actions, found None")
        a = np.minimum(np.abs(np.asarray(action, dtype=np.float64)[..., :2]), 1.0)
        return np.asarray(a.max(axis=-1) > config.bend_threshold)
    mag = np.maximum(np.abs(alpha), np.abs(gamma))
    lim = np.asarray(limit, dtype=np.float64)
    return np.asarray((lim > 0.0) & (mag > config.bend_threshold * lim))


def compute_reward(events: StepEvents, config: RewardConfig) -> tuple[RewardTerms, BoolArray]:
    """Reward terms and termination flags of one step.

    Returns:
        ``(terms, terminated)``; ``terms.total`` is the step reward and ``terminated`` is true on
        a non-minor collision, an exit or success.
    """
    collision = np.asarray(events.collision, dtype=bool)
    exited = np.asarray(events.exited, dtype=bool) & ~collision
    success = np.asarray(events.success, dtype=bool) & ~collision & ~exited
    end = np.where(collision, config.r_obst,
                   np.where(exited, config.r_exit, np.where(success, config.r_target, 0.0)))
    n = collision.shape[0]
    terms = RewardTerms(
        end=end.astype(np.float64),
        step=np.full(n, config.r_step),
        centerline=config.r_centerline * np.asarray(events.new_waypoints, dtype=np.float64),
        bending=np.where(np.asarray(events.bending, dtype=bool), config.r_bending, 0.0),
    )
    return terms, collision | exited | success

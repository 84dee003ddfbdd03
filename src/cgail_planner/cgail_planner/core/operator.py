"""A scripted operator that follows the planner's guidance with a gamepad, like a person.

Pure python/numpy; :mod:`cgail_planner.nodes.operator_node` turns its stick deflections into
``sensor_msgs/Joy`` for ``teleop_node`` (bend axes in ``position`` mode).

Model (documented assumptions, in simulated seconds):

* **Perception with a reaction delay.** The operator acts on what was shown ``reaction_delay_s``
  ago (0.25 s, the order of a human visuo-motor reaction): the suggested bend, and the distance to
  the target from the tip pose of the EM tracker.
* **Sticks.** The bend sticks aim at the suggested bend over ``bend_scale`` (teleop position
  mode); the insertion stick at ``max_insertion_fraction`` of full speed, scaled down by
  ``cos(heading error)`` (the tip is turning: go slower) and near the target linearly from
  ``slow_down_distance`` to ``min_insertion_fraction``. Every stick moves at most
  ``max_stick_rate`` full deflections per second and gets Gaussian noise ``stick_noise``.
* **Protocol** (paper section IV-B): stop when the tip is within ``stop_distance`` of the target,
  or, once within ``epsilon``, when the distance grows again by ``overshoot`` (the closest
  approach has passed); or at ``time_limit_s`` (3 minutes). Stopping releases the deadman.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math

import numpy as np

#: Largest combined bend stick deflection hypot(alpha, gamma) the operator uses.
MAX_BEND_DEFLECTION = 0.99


@dataclass(frozen=True)
class OperatorConfig:
    """Behaviour of the scripted operator."""

    reaction_delay_s: float = 0.25
    """Delay between what is shown and the operator's action, s; [0, 2]."""
    max_stick_rate: float = 4.0
    """Largest stick speed, full deflections per second; (0, 100]."""
    stick_noise: float = 0.02
    """Standard deviation of the stick noise, deflection units; [0, 0.5]."""
    max_insertion_fraction: float = 1.0
    """Largest insertion stick deflection (1 = teleop's full speed, 5 mm/s); (0, 1]."""
    min_insertion_fraction: float = 0.15
    """Insertion deflection close to the target; (0, 1]."""
    slow_down_distance: float = 0.030
    """Distance to the target below which the operator slows down, m; (0, 0.2]."""
    bend_scale: float = math.pi / 2.0
    """Bend at full stick deflection, rad (teleop position-mode scale_bend); (0, pi/2]."""
    stop_distance: float = 0.002
    """Stop within this distance of the target, m; (0, 0.05]."""
    epsilon: float = 0.010
    """Success radius, m (paper 10 mm); >= stop_distance."""
    overshoot: float = 0.002
    """Within epsilon, stop once the distance grew this much above its minimum, m; (0, 0.05]."""
    time_limit_s: float = 180.0
    """Trial time limit, s (paper: 3 minutes); (0, 3600]."""

    def __post_init__(self) -> None:
        for name, low, high, low_open in (
                ("reaction_delay_s", 0.0, 2.0, False), ("max_stick_rate", 0.0, 100.0, True),
                ("stick_noise", 0.0, 0.5, False), ("max_insertion_fraction", 0.0, 1.0, True),
                ("min_insertion_fraction", 0.0, 1.0, True),
                ("slow_down_distance", 0.0, 0.2, True), ("bend_scale", 0.0, math.pi / 2, True),
                ("stop_distance", 0.0, 0.05, True), ("epsilon", 0.0, 0.1, True),
                ("overshoot", 0.0, 0.05, True), ("time_limit_s", 0.0, 3600.0, True)):
            value = getattr(self, name)
            ok = (isinstance(value, (int, float)) and math.isfinite(value)
                  and (value > low if low_open else value >= low) and value <= high + 1e-12)
            if not ok:
                raise ValueError(f"{name} must be in {'(' if low_open else '['}{low}, {high}], "
                                 f"found {value!r}")
        if self.epsilon < self.stop_distance:
            raise ValueError(f"epsilon must be >= stop_distance ({self.stop_distance}), found "
                             f"{self.epsilon}")


@dataclass(frozen=True)
class Sticks:
    """Stick deflections in [-1, 1] and whether the deadman is held."""

    insertion: float
    alpha: float
    gamma: float
    deadman: bool


@dataclass(frozen=True)
class Percept:
    """What the operator sees at one instant."""

    t: float
    bend: tuple[float, float]
    heading_error: float
    distance: float


class ScriptedOperator:
    """State machine ``idle -> running -> done`` (module docstring).

    Args:
        config: behaviour.
        seed: seed of the stick noise.
    """

    def __init__(self, config: OperatorConfig | None = None, seed: int = 0) -> None:
        self.config = config or OperatorConfig()
        self.rng = np.random.default_rng(seed)
        self.reset()

    def reset(self) -> None:
        """Back to idle, sticks centred."""
        self.state = "idle"
        self.reason = ""
        self.t_start = 0.0
        self.t_last: float | None = None
        self.min_distance = math.inf
        self.sticks = np.zeros(3)
        self._percepts: deque[Percept] = deque()

    def start(self, t: float) -> None:
        """Begin a trial at time ``t`` (s)."""
        self.reset()
        self.state = "running"
        self.t_start = t

    def perceive(self, percept: Percept) -> None:
        """Record what is shown now (acted on ``reaction_delay_s`` later)."""
        self._percepts.append(percept)

    def _delayed(self, t: float) -> Percept | None:
        cutoff = t - self.config.reaction_delay_s
        seen = None
        while self._percepts and self._percepts[0].t <= cutoff:
            seen = self._percepts.popleft()
        if seen is not None:
            self._percepts.appendleft(seen)  # keep the latest visible one
        return seen

    def step(self, t: float) -> Sticks:
        """Stick deflections at time ``t`` (s)."""
        cfg = self.config
        dt = 0.0 if self.t_last is None else max(t - self.t_last, 0.0)
        self.t_last = t
        if self.state != "running":
            self.sticks[:] = 0.0
            return Sticks(0.0, 0.0, 0.0, False)
        if t - self.t_start >= cfg.time_limit_s:
            return self._stop(f"time limit {cfg.time_limit_s:.0f} s reached")
        seen = self._delayed(t)
        if seen is None:
            target = np.zeros(3)
        else:
            d = seen.distance
            self.min_distance = min(self.min_distance, d)
            if d <= cfg.stop_distance:
                return self._stop(f"at the target ({d * 1e3:.1f} mm)")
            if self.min_distance <= cfg.epsilon and d > self.min_distance + cfg.overshoot:
                return self._stop(f"closest approach passed ({self.min_distance * 1e3:.1f} mm)")
            speed = cfg.max_insertion_fraction * max(math.cos(seen.heading_error), 0.3)
            if d < cfg.slow_down_distance:
                frac = d / cfg.slow_down_distance
                speed *= cfg.min_insertion_fraction + (1 - cfg.min_insertion_fraction) * frac
            target = np.array([speed, seen.bend[0] / cfg.bend_scale,
                               seen.bend[1] / cfg.bend_scale])
        step = cfg.max_stick_rate * dt
        self.sticks += np.clip(target - self.sticks, -step, step)
        noisy = self.sticks + self.rng.normal(0.0, cfg.stick_noise, 3) * (dt > 0.0)
        noisy[0] = min(noisy[0], cfg.max_insertion_fraction)
        bend = noisy[1:]
        norm = float(np.hypot(*bend))
        if norm > MAX_BEND_DEFLECTION:  # stay inside the teleop/PAM bend cap despite rounding
            bend = bend * (MAX_BEND_DEFLECTION / norm)
        return Sticks(float(np.clip(noisy[0], -1.0, 1.0)), float(bend[0]), float(bend[1]), True)

    def _stop(self, reason: str) -> Sticks:
        self.state = "done"
        self.reason = reason
        self.sticks[:] = 0.0
        return Sticks(0.0, 0.0, 0.0, False)

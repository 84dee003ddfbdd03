"""A scripted operator that follows the planner's guidance with a gamepad, like a person.

Pure python/numpy; :mod:`cgail_planner.nodes.operator_node` turns its stick deflections into
``sensor_msgs/Joy`` for ``teleop_node`` (bend axes in ``position`` mode).

Model (documented assumptions, in simulated seconds; values and their sources at the fields of
:class:`OperatorConfig`):

* **Perception with a reaction delay.** The operator acts on what was shown ``reaction_delay_s``
  ago: the bend it aims at, and the distance to the target from the tip pose of the EM tracker.
* **Look-ahead.** People steering along a previewed path look beyond the nearest guidance
  (drivers' "far point", Donges 1978; Land & Lee 1994). The operator aims at the path point
  ``look_ahead`` m of arc beyond the displayed next waypoint, with the bend that curves the tip
  onto it by the guidance's own rule (:func:`~cgail_planner.core.guidance.suggested_bend`, the
  nominal catheter): :func:`aimed_bend`. On a bend of the path it turns early (cuts the
  corner); ``look_ahead = 0`` aims at the suggested bend as shown.
* **Correction gain.** The bend stick aims at ``K * bend / bend_scale`` (teleop position mode)
  with ``K = correction_gain`` below 1: aimed movements undershoot their target (the primary
  submovement falls short and a later correction follows, Elliott et al. 2001), so the
  operator under-corrects and the closed loop (the guidance is recomputed from the tip) keeps a
  residual error on curves.
* **Stick response with overshoot.** Each bend stick follows its aim as the second-order system
  ``x'' + 2 zeta omega x' + omega^2 x = omega^2 u`` (``zeta = stick_damping``, ``omega =
  stick_frequency``), discretised exactly for a target held over each step: a step of the aim
  overshoots by :func:`step_overshoot` ``= exp(-pi zeta / sqrt(1 - zeta^2))`` of the step, so a
  large correction over-corrects by more. It stands for the closed loop of a quasi-linear
  operator (McRuer & Jex 1967): around crossover the operator and the controlled element act as
  ``omega_c exp(-tau s) / s``, and a loop with a phase margin of 40-60 deg has a dominant pair
  with ``zeta`` about 0.4-0.6 (the rule of thumb ``zeta ~ phase margin / 100 deg``; the margin
  is an estimate, the crossover model leaves it to the task). The insertion stick moves at
  most ``max_stick_rate`` towards its aim (no overshoot). Every stick moves at most
  ``max_stick_rate`` full deflections per second and gets Gaussian noise ``stick_noise``.
* **Insertion.** At ``max_insertion_fraction`` of full speed, scaled down by
  ``cos(heading error)`` (the tip is turning: go slower) and near the target linearly from
  ``slow_down_distance`` to ``min_insertion_fraction``.
* **Learning curve.** ``skill`` in [0, 1] blends the first-trial (``novice_*``) values of the
  reaction delay, stick noise, correction gain and stick damping into the practised ones (the
  fields without the prefix). After ``n`` practice trials, :func:`skill_after` gives
  ``skill = 1 - (1 + n)^-beta``, so every blended value follows the power law of practice
  ``v(n) = v_inf + (v_0 - v_inf) (n + 1)^-beta`` (Newell & Rosenbloom 1981, with one trial of
  prior experience so that the first trial is finite), ``beta = PRACTICE_EXPONENT``.
* **Protocol** (paper section IV-B): stop when the tip is within ``stop_distance`` of the target,
  or, once within ``epsilon``, when the distance grows again by ``overshoot`` (the closest
  approach has passed); or at ``time_limit_s`` (3 minutes). Stopping releases the deadman.
* **Supervising** (:class:`SupervisingOperator`, shared autonomy): the person holds the deadman
  from the start and leaves the driving to the autonomy. Assumptions: the thumbs rest off the
  sticks (centred exactly, no stick noise) while the tip stays within ``threshold`` of the
  displayed path; beyond it, seen after the same reaction delay, the person steers back with
  the bend they would aim at when driving (:func:`aimed_bend`), ``K * bend / bend_scale``
  (the autonomy adds ``bend_scale`` rad at full deflection), through the same second-order
  stick response, and never touches the insertion stick (the autonomy inserts and stops at
  the target; the person keeps only the time limit).

References: E. R. Donges, "A two-level model of driver steering behavior", Human Factors 20(6),
1978. M. F. Land, D. N. Lee, "Where we look when we steer", Nature 369, 1994. D. Elliott,
W. F. Helsen, R. Chua, "A century later: Woodworth's (1899) two-component model of goal-directed
aiming", Psychological Bulletin 127(3), 2001. D. T. McRuer, H. R. Jex, "A review of quasi-linear
pilot models", IEEE Trans. Human Factors in Electronics HFE-8(3), 1967. A. Newell,
P. S. Rosenbloom, "Mechanisms of skill acquisition and the law of practice", in Cognitive Skills
and Their Acquisition, 1981. A. Heathcote, S. Brown, D. J. K. Mewhort, "The power law repealed:
the case for an exponential law of practice", Psychonomic Bulletin & Review 7(2), 2000.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from cgail_planner.core.guidance import GuidanceConfig, PathFollower, suggested_bend

#: Largest combined bend stick deflection hypot(alpha, gamma) the operator uses.
MAX_BEND_DEFLECTION = 0.99
#: Exponent ``beta`` of the learning curve (:func:`skill_after`). An estimate, pinned by the
#: paper's protocol: its operator was pre-trained until the learning curve reached a plateau,
#: within 10 trials (section IV-B). With ``beta = 1`` the improvement still to come after ``n``
#: practice trials is ``1 / (n + 1)`` of the whole: 9 % at the first measured trial (n = 10),
#: 5 % at the last (n = 19), while the first pre-training trials improve quickly. (Exponents
#: fitted to averaged practice curves are often lower; those curves run over hundreds of trials
#: and mix learners, Heathcote et al. 2000.)
PRACTICE_EXPONENT = 1.0


def skill_after(practice: int, exponent: float = PRACTICE_EXPONENT) -> float:
    """Skill level after ``practice`` trials: ``1 - (1 + practice)^-exponent``, in [0, 1).

    0 for the first trial ever; the gap to the practised values shrinks by the power law of
    practice (module docstring). A function of the number of trials only, so a trial's skill
    does not depend on how (or whether) earlier trials were run.

    Raises:
        ValueError: a negative ``practice`` or a non-positive ``exponent``.
    """
    if isinstance(practice, bool) or not isinstance(practice, int) or practice < 0:
        raise ValueError(f"practice must be an integer >= 0, found {practice!r}")
    if not (math.isfinite(exponent) and exponent > 0.0):
        raise ValueError(f"exponent must be > 0, found {exponent!r}")
    return 1.0 - (1.0 + practice) ** -exponent


def step_overshoot(damping: float) -> float:
    """Overshoot of a second-order step response, as a fraction of the step:
    ``exp(-pi zeta / sqrt(1 - zeta^2))`` for the damping ratio ``zeta`` in (0, 1)."""
    if not 0.0 < damping < 1.0:
        raise ValueError(f"damping must be in (0, 1), found {damping!r}")
    return math.exp(-math.pi * damping / math.sqrt(1.0 - damping * damping))


class Proficiency(NamedTuple):
    """The skill-dependent values in effect for one trial (:meth:`OperatorConfig.proficiency`)."""

    reaction_delay_s: float
    stick_noise: float
    correction_gain: float
    stick_damping: float


@dataclass(frozen=True)
class OperatorConfig:
    """Behaviour of the scripted operator (module docstring).

    The skill-dependent fields come in pairs: the practised value (no prefix) and the value of
    the first trial (``novice_``); ``skill`` blends them linearly (:meth:`proficiency`).
    """

    reaction_delay_s: float = 0.25
    """Practised delay between what is shown and the operator's action, s; [0, 2]. The order of
    a human visuo-motor reaction (simple reaction times 0.2-0.25 s) and of the effective time
    delay of the quasi-linear operator models (McRuer & Jex 1967)."""
    novice_reaction_delay_s: float = 0.40
    """First-trial reaction delay, s; [0, 2]. An estimate: an unfamiliar stick-to-display
    mapping is a choice reaction (0.35-0.5 s), the kind of latency the law of practice was
    first fitted to (Newell & Rosenbloom 1981)."""
    max_stick_rate: float = 4.0
    """Largest stick speed, full deflections per second; (0, 100]."""
    stick_noise: float = 0.02
    """Practised standard deviation of the stick noise, deflection units; [0, 0.5]."""
    novice_stick_noise: float = 0.05
    """First-trial stick noise, deflection units; [0, 0.5]. An estimate: motor variability
    shrinks with practice; 2.5 times the practised value."""
    look_ahead: float = 0.005
    """Arc length beyond the displayed next waypoint that the operator aims at, m; [0, 0.1].
    About 1 s of preview at the full insertion speed (5 mm/s): drivers steer by a far point
    some 1-2 s ahead (Donges 1978; Land & Lee 1994); the lower end, as the operator sees the
    path on a 2D monitor and the planner's waypoint is already 25 mm ahead. 0: the suggested
    bend as shown."""
    correction_gain: float = 0.9
    """Practised fraction of the aimed bend the stick goes for; [0, 2]. Practised aimed
    movements undershoot by several percent (Elliott et al. 2001): 0.9."""
    novice_correction_gain: float = 0.7
    """First-trial correction gain; [0, 2]. An estimate: a first-time operator bends the
    catheter cautiously (a larger undershoot, corrected later)."""
    stick_frequency: float = 8.0
    """Natural frequency ``omega`` of the bend stick response, rad/s; [0, 100] (0: no
    second-order response, the stick goes straight to its aim at ``max_stick_rate``). An
    estimate: with ``stick_damping`` 0.6 a step peaks after ``pi / omega_d`` = 0.49 s, the time
    of a quick small aimed thumb movement (Fitts-law movement times of a few hundred ms)."""
    stick_damping: float = 0.6
    """Practised damping ratio ``zeta`` of the bend stick response; (0, 0.99]. 0.6: a 9.5 %
    overshoot (:func:`step_overshoot`), a crossover-model loop with a phase margin of about
    60 deg (module docstring); an estimate."""
    novice_stick_damping: float = 0.35
    """First-trial damping ratio; (0, 0.99]. An estimate: 31 % overshoot, a phase margin of
    about 35 deg (a first-time operator over-corrects, then learns to lead less aggressively)."""
    skill: float = 1.0
    """Skill level in [0, 1]: 0 uses the ``novice_`` values, 1 the practised ones
    (:func:`skill_after` for a number of practice trials)."""
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
                ("reaction_delay_s", 0.0, 2.0, False),
                ("novice_reaction_delay_s", 0.0, 2.0, False),
                ("max_stick_rate", 0.0, 100.0, True),
                ("stick_noise", 0.0, 0.5, False), ("novice_stick_noise", 0.0, 0.5, False),
                ("look_ahead", 0.0, 0.1, False), ("correction_gain", 0.0, 2.0, False),
                ("novice_correction_gain", 0.0, 2.0, False),
                ("stick_frequency", 0.0, 100.0, False), ("stick_damping", 0.0, 0.99, True),
                ("novice_stick_damping", 0.0, 0.99, True), ("skill", 0.0, 1.0, False),
                ("max_insertion_fraction", 0.0, 1.0, True),
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

    def proficiency(self) -> Proficiency:
        """The values in effect at ``skill``: ``novice + skill * (practised - novice)``."""
        s = self.skill

        def blend(novice: float, practised: float) -> float:
            return novice + s * (practised - novice)

        return Proficiency(blend(self.novice_reaction_delay_s, self.reaction_delay_s),
                           blend(self.novice_stick_noise, self.stick_noise),
                           blend(self.novice_correction_gain, self.correction_gain),
                           blend(self.novice_stick_damping, self.stick_damping))


def arrival(distance: float, min_distance: float, stop_distance: float, epsilon: float,
            overshoot: float) -> str | None:
    """Why a run towards the target ends now (the protocol, paper section IV-B), or None.

    Args:
        distance: the tip's distance to the target now, m.
        min_distance: the closest it has been (``distance`` included), m.
        stop_distance: at the target within this, m.
        epsilon: the success radius, m.
        overshoot: within ``epsilon``, the closest approach has passed when the distance grew
            by this much, m.
    """
    if distance <= stop_distance:
        return f"at the target ({distance * 1e3:.1f} mm)"
    if min_distance <= epsilon and distance > min_distance + overshoot:
        return f"closest approach passed ({min_distance * 1e3:.1f} mm)"
    return None


#: The bend rule of the nominal catheter (built once: :func:`aimed_bend` runs per suggested bend).
_NOMINAL_GUIDANCE = GuidanceConfig()


def aimed_bend(follower: PathFollower, position: NDArray[np.float64],
               rotation: NDArray[np.float64], waypoint: NDArray[np.float64],
               shown_bend: tuple[float, float], look_ahead: float,
               guidance: GuidanceConfig | None = None) -> tuple[float, float]:
    """The bend the operator aims at: towards the path point ``look_ahead`` m of arc beyond the
    displayed ``waypoint`` (module docstring, look-ahead).

    Args:
        follower: the displayed path (its last projection is updated).
        position: (3,) tip position, m.
        rotation: (3, 3) tip rotation (columns x_A, y_A, z_A).
        waypoint: (3,) the displayed next waypoint, m.
        shown_bend: the displayed suggested bend ``(alpha, gamma)``, rad.
        look_ahead: arc length beyond the waypoint, m; 0 returns ``shown_bend``.
        guidance: segment length and bend cap of the bend rule (default: the nominal
            catheter's).

    Returns:
        ``(alpha, gamma)``, rad.
    """
    if look_ahead <= 0.0:
        return shown_bend
    g = guidance or _NOMINAL_GUIDANCE
    _, arc, _ = follower.project(waypoint)
    aim = follower.point_at(arc + look_ahead)
    alpha, gamma, _ = suggested_bend(position, rotation, aim, g.segment_length, g.max_bend)
    return alpha, gamma


def _second_order_step(x: NDArray[np.float64], v: NDArray[np.float64], u: NDArray[np.float64],
                       omega: float, zeta: float, dt: float) -> None:
    """Advance ``x'' + 2 zeta omega x' + omega^2 x = omega^2 u`` by ``dt`` in place, exactly for
    ``u`` held over the step (underdamped: ``0 < zeta < 1``)."""
    sigma = zeta * omega
    omega_d = omega * math.sqrt(1.0 - zeta * zeta)
    decay = math.exp(-sigma * dt)
    c, s = math.cos(omega_d * dt), math.sin(omega_d * dt)
    e = x - u
    e_next = decay * (e * c + (v + sigma * e) / omega_d * s)
    v[:] = decay * (v * c - (sigma * v + omega * omega * e) / omega_d * s)
    x[:] = u + e_next


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
    deviation: float = 0.0
    """Distance of the tip from the displayed path, m (what a supervising person watches)."""


def _capped_bend(bend: NDArray[np.float64]) -> NDArray[np.float64]:
    """The two bend sticks scaled into :data:`MAX_BEND_DEFLECTION` (the teleop/PAM bend cap,
    which rounding could pass), direction kept."""
    norm = float(np.hypot(*bend))
    if norm > MAX_BEND_DEFLECTION:
        return bend * (MAX_BEND_DEFLECTION / norm)
    return bend


class ScriptedOperator:
    """State machine ``idle -> running -> done`` (module docstring).

    Args:
        config: behaviour.
        seed: seed of the stick noise.
    """

    def __init__(self, config: OperatorConfig | None = None, seed: int = 0) -> None:
        self.config = config or OperatorConfig()
        self.proficiency = self.config.proficiency()
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
        self._bend_rate = np.zeros(2)
        self._percepts: deque[Percept] = deque()

    def start(self, t: float) -> None:
        """Begin a trial at time ``t`` (s)."""
        self.reset()
        self.state = "running"
        self.t_start = t

    def perceive(self, percept: Percept) -> None:
        """Record what is shown now (acted on after the reaction delay)."""
        self._percepts.append(percept)

    def _delayed(self, t: float) -> Percept | None:
        cutoff = t - self.proficiency.reaction_delay_s
        seen = None
        while self._percepts and self._percepts[0].t <= cutoff:
            seen = self._percepts.popleft()
        if seen is not None:
            self._percepts.appendleft(seen)  # keep the latest visible one
        return seen

    def _advance(self, t: float) -> tuple[float, Sticks | None]:
        """The step ``dt`` to time ``t`` (s), and the sticks when the step ends here: released
        when not running, the stop at the time limit; None while the trial goes on."""
        cfg = self.config
        dt = 0.0 if self.t_last is None else max(t - self.t_last, 0.0)
        self.t_last = t
        if self.state != "running":
            self.sticks[:] = 0.0
            self._bend_rate[:] = 0.0
            return dt, Sticks(0.0, 0.0, 0.0, False)
        if t - self.t_start >= cfg.time_limit_s:
            return dt, self._stop(f"time limit {cfg.time_limit_s:.0f} s reached")
        return dt, None

    def step(self, t: float) -> Sticks:
        """Stick deflections at time ``t`` (s)."""
        cfg, skill = self.config, self.proficiency
        dt, ended = self._advance(t)
        if ended is not None:
            return ended
        seen = self._delayed(t)
        if seen is None:
            target = np.zeros(3)
        else:
            d = seen.distance
            self.min_distance = min(self.min_distance, d)
            arrived = arrival(d, self.min_distance, cfg.stop_distance, cfg.epsilon,
                              cfg.overshoot)
            if arrived is not None:
                return self._stop(arrived)
            speed = cfg.max_insertion_fraction * max(math.cos(seen.heading_error), 0.3)
            if d < cfg.slow_down_distance:
                frac = d / cfg.slow_down_distance
                speed *= cfg.min_insertion_fraction + (1 - cfg.min_insertion_fraction) * frac
            gain = skill.correction_gain / cfg.bend_scale
            target = np.array([speed, gain * seen.bend[0], gain * seen.bend[1]])
        self._move_sticks(target, dt)
        noisy = self.sticks + self.rng.normal(0.0, skill.stick_noise, 3) * (dt > 0.0)
        noisy[0] = min(noisy[0], cfg.max_insertion_fraction)
        bend = _capped_bend(noisy[1:])
        return Sticks(float(noisy[0].clip(-1.0, 1.0)), float(bend[0]), float(bend[1]), True)

    def _move_sticks(self, target: NDArray[np.float64], dt: float) -> None:
        """Sticks towards ``target`` over ``dt``: insertion rate-limited, bend second-order
        (module docstring), every stick at most ``max_stick_rate * dt`` per step."""
        cfg = self.config
        step = cfg.max_stick_rate * dt
        before = self.sticks.copy()
        if cfg.stick_frequency > 0.0 and dt > 0.0:
            bend = self.sticks[1:]  # a view: updated in place
            _second_order_step(bend, self._bend_rate, target[1:], cfg.stick_frequency,
                               self.proficiency.stick_damping, dt)
            self._bend_rate.clip(-cfg.max_stick_rate, cfg.max_stick_rate, out=self._bend_rate)
            self.sticks[0] = target[0]
        else:
            self.sticks[:] = target
        # (ndarray.clip: np.clip's ufunc without its wrapper, at 40 Hz)
        self.sticks[:] = before + (self.sticks - before).clip(-step, step)

    def _stop(self, reason: str) -> Sticks:
        self.state = "done"
        self.reason = reason
        self.sticks[:] = 0.0
        self._bend_rate[:] = 0.0
        return Sticks(0.0, 0.0, 0.0, False)


class SupervisingOperator(ScriptedOperator):
    """The person of shared autonomy (module docstring, *Supervising*): deadman held, sticks
    centred until the tip strays more than ``threshold`` from the path, then a bend correction.

    Args:
        config: behaviour (reaction delay, stick response, correction gain, time limit).
        threshold: deviation from the path beyond which the person corrects, m; (0, 0.05].
        bend_scale: bend the autonomy adds at full deflection, rad (its
            ``shared_scale_bend``); (0, pi/2].
        seed: unused (no stick noise); kept for the driving operator's signature.
    """

    def __init__(self, config: OperatorConfig | None = None, threshold: float = 0.005,
                 bend_scale: float = 0.5, seed: int = 0) -> None:
        for name, value, high in (('threshold', threshold, 0.05),
                                  ('bend_scale', bend_scale, math.pi / 2)):
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and 0.0 < value <= high):
                raise ValueError(f'{name}: expected a number in (0, {high:g}], found {value!r}')
        super().__init__(config, seed)
        self.threshold = float(threshold)
        self.bend_scale = float(bend_scale)
        self.corrections = 0
        """Steps in which the person aimed a bend stick away from centre."""

    def step(self, t: float) -> Sticks:
        """Stick deflections at time ``t`` (s): insertion 0, deadman held while running."""
        skill = self.proficiency
        dt, ended = self._advance(t)
        if ended is not None:
            return ended
        seen = self._delayed(t)
        target = np.zeros(3)
        if seen is not None and seen.deviation > self.threshold:
            gain = skill.correction_gain / self.bend_scale
            target[1:] = gain * seen.bend[0], gain * seen.bend[1]
        self._move_sticks(target, dt)
        bend = _capped_bend(self.sticks[1:].copy())
        if target[1] != 0.0 or target[2] != 0.0:
            self.corrections += 1
        return Sticks(0.0, float(bend[0]), float(bend[1]), True)

"""Demonstrations from teleoperated session bags (``make_demos --from-bags``).

A trial bag of the simulated in-vitro session (:mod:`cgail_rig.session`) or of a
real rig holds the tip as tracked (``em_tracker/tip_pose``, 40 Hz, noisy; in simulation also
the phantom's true tip ``phantom/tip_pose``, 10 Hz) and the goal (``planner/goal``). This module
turns the operator's motion into episodes of the demonstration bag format
(:mod:`cgail_learning.demo_bags`), which ``train --demos`` replays in the simulator:

1. **Read** the tip positions (header stamps; a zero stamp falls back to the log time) and the
   goals, in frame ``phantom``. ``tip_topic='auto'`` takes ``phantom/tip_pose`` where recorded
   (the simulator's truth) and ``em_tracker/tip_pose`` otherwise (a rig). The session does not
   record the teleop commands (``catheter/insertion_command``, ``catheter/bend_command``; they
   are setpoints, not the motion); the actions are inferred from the tip motion alone.
2. **Episodes.** Each goal is matched to the nearest target of the anatomy's scenario set
   (within ``target_tolerance_m``); an episode runs from a goal to the next goal naming another
   target (the dynamic session re-publishes its moving target every second: one episode), to
   a tracking gap longer than ``max_gap_s`` or to the end of the bag. Its first tip position
   is matched to the nearest scenario start (within ``start_tolerance_m``): the format replays
   every episode from a scenario start, so an episode that starts elsewhere cannot be converted
   and is reported. The operator's reaction time is dropped: the leading steps before the tip
   leaves ``idle_radius_m`` of its first position, but for the last
   ``ceil(idle_radius_m / (v_max dt)) + 1`` (it may have set off in those).
3. **Resample** the positions at the env's ``dt`` (:class:`~cgail_sim.config.EnvConfig`)
   from the goal on: linear interpolation, or with ``smooth_s > 0`` a local linear fit over
   +-``smooth_s`` (EM noise, 0.5 mm RMS, falls by about the square root of the samples in the
   window; the default is 0.4 s for the EM tracker's 40 Hz, none for the truth). A position
   within ``deadband_m`` of the simulated tip is a pause (zero action): 0.2 mm for the EM
   tracker, whose smoothed noise would otherwise turn a pause into small insertions and
   retractions.
4. **Actions by closed-loop inverse kinematics.** The env (static mode, the episode's start and
   target) is stepped along the resampled positions: at each step, from the *simulated* tip
   pose ``[R | p]`` (not the recorded one), the normalised action ``a`` in the env's action
   space whose step (:func:`~cgail_sim.ftl_model.action_to_command`,
   :func:`~cgail_sim.ftl_model.advance_pose`) lands nearest the next recorded position
   ``q``. Unconstrained, the constant-curvature step that reaches ``q`` exactly inserts
   ``|d|`` along ``d = R^T (q - p)`` with the bends of
   :func:`~cgail_sim.ftl_model.steer_towards`; where that breaks the model (insertion
   beyond ``v_max dt``, a bend beyond ``theta_max |delta_l| / L``: lateral motion without
   insertion, a wall sliding the phantom's tip) the bounded least-squares solution over
   ``a in [-1, 1]^2 x [0, 1]`` is taken (scipy). A point behind the tip plane (``d_y < 0``)
   is a retraction by ``min(-d_y, v_max dt)`` (bends are ignored while retracting; not with a
   ``forward_only`` option set). A step counts as *clipped* when its tip lands more than
   :data:`CLIP_M` (or ``deadband_m``) from ``q``: of kind *insertion* when the insertion is at
   its bound, else *bend* (a bend at its bound, or a lateral offset while retracting).
5. **Ends.** The env ends the episode where the recording reaches the target (within the
   env's 10 mm ``epsilon``: ``success``), collides or exits; or it ends with the recording
   (``success`` False); an episode whose simulated tip strays more than ``max_deviation_m``
   from the recorded one is cut there (its rest is not the operator's motion).

**Why closed loop.** An open-loop conversion (each action from two consecutive *recorded*
poses) would re-simulate into a tip that drifts from the recording by every clipped step,
unboundedly over a 200 mm episode, and ``train`` holds a replay to 1 mm
(:data:`~cgail_learning.demo_bags.POSE_TOLERANCE_M`). Computing each action from the
simulated pose re-anchors every step on the recording: the deviation stays bounded by what one
step cannot follow, and it is measured, reported and capped (``max_deviation_m``). The bag's
``demo/tip_pose`` holds the simulated poses, so the loader's replay follows them to rounding,
under the same 1 mm tolerance as the scripted expert's bags (no looser tolerance is needed or
recorded); the recorded motion's distance from them is the conversion's deviation, stored with
the clipping figures in the bag's custom data (``source``).

Measured on two 70 s centerline trials of the session (1287 steps): from the true tip, no
step clipped and the simulated tip within 0.6 um of it; from the EM tracker, 22 % of the steps
clipped (2 % insertion, 20 % bend: the noise left after smoothing), the simulated tip 0.18 mm
(mean) and 0.95 mm (max) from the smoothed EM positions and 0.15-0.26 mm (mean) from the true
tip, which the raw EM positions miss by 0.47 mm.

Problems with an input (unreadable or corrupt bag, a missing topic, no goal, a goal or start
that is no scenario's, an episode shorter than ``min_steps``) are reported one line each
(:attr:`ConversionReport.skipped`); the other bags and episodes are converted.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cgail_learning.demo_bags import DemoEpisode
from cgail_learning.errors import DemoError

#: Tip topics, in the order ``tip_topic='auto'`` prefers them.
TIP_TOPICS = ('phantom/tip_pose', 'em_tracker/tip_pose')
GOAL_TOPIC = 'planner/goal'
#: The teleop node's command topics (catheter_driver ``teleop_node``): noted when recorded.
COMMAND_TOPICS = ('catheter/insertion_command', 'catheter/bend_command')
FRAME = 'phantom'
CLIP_M = 1e-6
"""A step whose simulated tip lands farther than this from the recorded position (m) counts as
clipped: 1 um, far above the rounding of a reachable step (~1e-16 m) and far below the EM
tracker's noise."""
#: Defaults per tip topic of ``(smooth_s, deadband_m)``: the truth is taken as it is; the EM
#: tracker's 0.5 mm noise is smoothed, and what is left of it in a pause is no motion.
SOURCE_DEFAULTS = {'phantom/tip_pose': (0.0, CLIP_M), 'em_tracker/tip_pose': (0.4, 2e-4)}


@dataclass(frozen=True)
class ConversionConfig:
    """How session bags are converted (module docstring)."""

    tip_topic: str = 'auto'
    """Tip topic: ``auto`` (``phantom/tip_pose`` when recorded, else ``em_tracker/tip_pose``)
    or a topic name (geometry_msgs/msg/PoseStamped in frame ``phantom``)."""
    smooth_s: float | None = None
    """Half-window of the local linear fit, s; 0: linear interpolation; None: 0.4 s for
    ``em_tracker/tip_pose``, 0 for ``phantom/tip_pose``; in [0, 2]."""
    deadband_m: float | None = None
    """A resampled position nearer than this to the simulated tip is no motion (a zero
    action: a pause, not noise followed back and forth), m; None: 0.2 mm for
    ``em_tracker/tip_pose``, 1 um (:data:`CLIP_M`) for ``phantom/tip_pose``; in [0, 1 mm]."""
    start_tolerance_m: float = 0.003
    """Largest distance of an episode's first tip position from a scenario start, m; (0, 0.05]."""
    target_tolerance_m: float = 0.005
    """Largest distance of a goal from a scenario target, m; (0, 0.05]."""
    idle_radius_m: float = 0.001
    """Leading samples within this distance of the first are dropped, m; [0, 0.02]."""
    max_deviation_m: float = 0.005
    """An episode is cut where its simulated tip is farther than this from the recording, m;
    (0, 0.05]."""
    max_gap_s: float = 0.5
    """A longer gap between tip samples ends the episode, s; (0, 10]."""
    min_steps: int = 10
    """Shorter episodes are not written (reported); in [1, 100000]."""

    def __post_init__(self) -> None:
        for name, low, high, low_open in (
                ('start_tolerance_m', 0.0, 0.05, True), ('target_tolerance_m', 0.0, 0.05, True),
                ('idle_radius_m', 0.0, 0.02, False), ('max_deviation_m', 0.0, 0.05, True),
                ('max_gap_s', 0.0, 10.0, True)):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and (value > low if low_open else value >= low) and value <= high):
                raise ValueError(f"{name} must be in {'(' if low_open else '['}{low}, {high}], "
                                 f'found {value!r}')
        if self.smooth_s is not None and not (isinstance(self.smooth_s, (int, float))
                                              and 0.0 <= self.smooth_s <= 2.0):
            raise ValueError(f'smooth_s must be None or in [0, 2] s, found {self.smooth_s!r}')
        if self.deadband_m is not None and not (isinstance(self.deadband_m, (int, float))
                                                and 0.0 <= self.deadband_m <= 1e-3):
            raise ValueError(f'deadband_m must be None or in [0, 0.001] m, found '
                             f'{self.deadband_m!r}')
        if not isinstance(self.min_steps, int) or not 1 <= self.min_steps <= 100_000:
            raise ValueError(f'min_steps must be an int in [1, 100000], found '
                             f'{self.min_steps!r}')
        if not isinstance(self.tip_topic, str) or not self.tip_topic.strip('/'):
            raise ValueError(f"tip_topic must be 'auto' or a topic name, found "
                             f'{self.tip_topic!r}')


    def for_topic(self, topic: str) -> tuple[float, float]:
        """``(smooth_s, deadband_m)`` for tip positions from ``topic`` (the given values, or
        :data:`SOURCE_DEFAULTS`; an unknown topic takes the EM tracker's)."""
        smooth, deadband = SOURCE_DEFAULTS.get(topic, SOURCE_DEFAULTS['em_tracker/tip_pose'])
        return (smooth if self.smooth_s is None else float(self.smooth_s),
                deadband if self.deadband_m is None else float(self.deadband_m))


class SessionRecording(NamedTuple):
    """What a trial bag holds for the conversion (:func:`read_session_bag`)."""

    tip_topic: str
    """The tip topic read (as recorded)."""
    tip_t: np.ndarray
    """(N,) tip stamps, s, increasing."""
    tip_p: np.ndarray
    """(N, 3) tip positions, m."""
    goal_t: np.ndarray
    """(G,) goal stamps, s, increasing."""
    goal_p: np.ndarray
    """(G, 3) goal positions, m."""
    commands: tuple[str, ...]
    """Teleop command topics recorded (:data:`COMMAND_TOPICS`; not used)."""
    custom: dict[str, str]
    """The bag's ``metadata.yaml`` custom_data (``condition``...)."""


@dataclass(frozen=True)
class EpisodeReport:
    """How one episode converted."""

    bag: str
    start: int
    target: int
    steps: int
    """Steps written."""
    success: bool
    """The simulated tip reached the target (the loader replays only these)."""
    end: str
    """Why it ended: ``target reached``, ``collision``, ``exited``, ``end of recording``,
    ``next goal``, ``tracking gap``, ``deviation``, ``step limit``."""
    idle_steps: int
    """Leading idle steps dropped."""
    clipped_insertion: int
    """Clipped steps with the insertion at its bound (``v_max dt``)."""
    clipped_bend: int
    """Other clipped steps: a bend at its bound, or a lateral offset while retracting."""
    retractions: int
    """Retracting steps."""
    start_offset_m: float
    """Distance of the first recorded position from the scenario start, m."""
    deviation_max_m: float
    """Largest distance of the simulated tip from the recorded position, m."""
    deviation_mean_m: float
    """Mean of that distance over the steps, m."""
    final_distance_m: float
    """Distance of the simulated tip from the target at the end, m."""

    @property
    def clipped(self) -> int:
        """Steps clipped (either kind)."""
        return self.clipped_insertion + self.clipped_bend

    def line(self) -> str:
        """One line for the console."""
        return (f'{self.bag}: start {self.start} target {self.target}: {self.steps} steps, '
                f'{self.end}{" (success)" if self.success else ""}, clipped '
                f'{self.clipped}/{self.steps} (insertion {self.clipped_insertion}, bend '
                f'{self.clipped_bend}), deviation max {self.deviation_max_m * 1e3:.2f} mm mean '
                f'{self.deviation_mean_m * 1e3:.2f} mm, {self.final_distance_m * 1e3:.1f} mm '
                f'from the target')

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields (lengths in mm)."""
        return {'bag': self.bag, 'start': self.start, 'target': self.target,
                'steps': self.steps, 'success': self.success, 'end': self.end,
                'idle_steps': self.idle_steps, 'clipped_insertion': self.clipped_insertion,
                'clipped_bend': self.clipped_bend, 'retractions': self.retractions,
                'start_offset_mm': round(self.start_offset_m * 1e3, 4),
                'deviation_max_mm': round(self.deviation_max_m * 1e3, 4),
                'deviation_mean_mm': round(self.deviation_mean_m * 1e3, 4),
                'final_distance_mm': round(self.final_distance_m * 1e3, 3)}


@dataclass
class ConversionReport:
    """What a conversion produced and what it could not convert."""

    bags: int = 0
    """Input bags."""
    episodes: list[EpisodeReport] = field(default_factory=list)
    """Episodes written, in bag order."""
    skipped: list[str] = field(default_factory=list)
    """One line per bag or episode not converted: ``<bag>: <why>``."""
    notes: list[str] = field(default_factory=list)
    """One line per remark that lost nothing (the tip topic read, commands not used)."""

    @property
    def steps(self) -> int:
        """Steps written."""
        return sum(e.steps for e in self.episodes)

    def to_dict(self) -> dict[str, Any]:
        """Totals (clipped fractions over the steps, deviations in mm) and the per-episode
        entries, skipped inputs and notes."""
        steps = max(self.steps, 1)
        eps = self.episodes
        return {
            'bags': self.bags, 'episodes': len(eps),
            'successful': sum(e.success for e in eps), 'steps': self.steps,
            'clipped_fraction': round(sum(e.clipped for e in eps) / steps, 4),
            'clipped_insertion_fraction': round(sum(e.clipped_insertion for e in eps) / steps,
                                                4),
            'clipped_bend_fraction': round(sum(e.clipped_bend for e in eps) / steps, 4),
            'retraction_fraction': round(sum(e.retractions for e in eps) / steps, 4),
            'deviation_max_mm': round(max((e.deviation_max_m for e in eps), default=0.0) * 1e3,
                                      4),
            'deviation_mean_mm': round(sum(e.deviation_mean_m * e.steps for e in eps) / steps
                                       * 1e3, 4),
            'per_episode': [e.to_dict() for e in eps],
            'skipped': list(self.skipped), 'notes': list(self.notes)}


# ---------------------------------------------------------------------- reading
def read_session_bag(path: Path, tip_topic: str = 'auto') -> SessionRecording:
    """The tip positions and goals of a trial bag (module docstring, step 1).

    Raises:
        DemoError: one line naming the bag and what is wrong: unreadable or corrupt, no tip
            topic or no goal topic (listing the topics found), a frame other than ``phantom``.
    """
    from cgail_bags.bagio import bag_custom_data, iter_raw, open_bag, TYPESTORE
    from cgail_bags.errors import BagError
    from cgail_bags.reader import topic_matches

    wanted = TIP_TOPICS if tip_topic == 'auto' else (tip_topic,)
    rows: dict[str, list[tuple[float, float, float, float]]] = {}
    frames: dict[str, str] = {}
    try:  # (open_bag turns any ValueError inside into "corrupt bag": no DemoError in here)
        with open_bag(path) as reader:
            custom = bag_custom_data(reader)
            found = sorted(c.topic for c in reader.connections)
            tip = next((c.topic for w in wanted for c in reader.connections
                        if topic_matches(c.topic, w)), None)
            goal = next((c.topic for c in reader.connections
                         if topic_matches(c.topic, GOAL_TOPIC)), None)
            for conn, log_ns, raw in iter_raw(reader, topics=[t for t in (tip, goal) if t]):
                if conn.msgtype != 'geometry_msgs/msg/PoseStamped':
                    frames[conn.topic] = f'a {conn.msgtype}'
                    break
                msg: Any = TYPESTORE.deserialize_cdr(raw, conn.msgtype)
                frame = msg.header.frame_id.lstrip('/')
                if frame != FRAME:
                    frames[conn.topic] = f'frame {frame!r}'
                    break
                stamp = msg.header.stamp
                t = (stamp.sec + stamp.nanosec * 1e-9 if stamp.sec or stamp.nanosec
                     else log_ns * 1e-9)
                q = msg.pose.position
                rows.setdefault(conn.topic, []).append((t, q.x, q.y, q.z))
    except BagError as exc:
        raise DemoError(str(exc)) from None
    missing = [t for t, c in ((' or '.join(wanted), tip), (GOAL_TOPIC, goal))
               if c is None or not rows.get(c)]
    if missing or tip is None or goal is None:
        raise DemoError(f'{path}: expected topics {missing} with messages, found {found}')
    if frames:
        topic, what = next(iter(frames.items()))
        raise DemoError(f'{path}: {topic}: expected geometry_msgs/msg/PoseStamped in frame '
                        f'{FRAME}, found {what}')
    commands = tuple(w for w in COMMAND_TOPICS if any(topic_matches(t, w) for t in found))
    tips = _sorted(rows[tip])
    goals = _sorted(rows[goal])
    return SessionRecording(tip.lstrip('/'), tips[:, 0], tips[:, 1:], goals[:, 0], goals[:, 1:],
                            commands, custom)


def _sorted(rows: list[tuple[float, float, float, float]]) -> np.ndarray:
    """(N, 4) rows ``t, x, y, z`` by time, one per stamp (the last of equal stamps)."""
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
    a = a[np.argsort(a[:, 0], kind='stable')]
    keep = np.append(np.diff(a[:, 0]) > 0.0, True)
    return a[keep]


# ---------------------------------------------------------------------- resampling
def resample(t: np.ndarray, p: np.ndarray, t_new: np.ndarray, smooth_s: float) -> np.ndarray:
    """Positions ``p`` (N, 3) at stamps ``t`` (N,) evaluated at ``t_new`` (K,) within
    ``[t[0], t[-1]]``: linear interpolation (``smooth_s == 0``), or a least-squares line
    through the samples within +-``smooth_s`` of each new time (interpolation where the
    window holds fewer than 3)."""
    out = np.stack([np.interp(t_new, t, p[:, i]) for i in range(3)], axis=1)
    if smooth_s <= 0.0:
        return out
    lo = np.searchsorted(t, t_new - smooth_s, side='left')
    hi = np.searchsorted(t, t_new + smooth_s, side='right')
    for k in range(len(t_new)):
        if hi[k] - lo[k] < 3:
            continue
        dt = t[lo[k]:hi[k]] - t_new[k]
        a = np.stack([np.ones_like(dt), dt], axis=1)
        coef = np.linalg.lstsq(a, p[lo[k]:hi[k]], rcond=None)[0]
        out[k] = coef[0]
    return out


# ---------------------------------------------------------------------- one step
def fit_step(p: np.ndarray, r: np.ndarray, q: np.ndarray, catheter: Any, theta_max: float,
             deadband_m: float = CLIP_M) -> np.ndarray:
    """The normalised action whose step from the tip pose ``[r | p]`` lands nearest ``q``
    (module docstring, step 4).

    Args:
        p: (3,) tip position, m.
        r: (3, 3) tip rotation.
        q: (3,) the position to reach, m.
        catheter: the env's :class:`~cgail_sim.ftl_model.CatheterConfig`.
        theta_max: the current maximal bend, rad.
        deadband_m: a ``q`` nearer than this is no motion (zero action), m.

    Returns:
        (3,) action in ``[-1, 1]^3``: exact where the step can reach ``q``, else the bounded
        least-squares one (a retraction when ``q`` lies behind the tip plane).
    """
    from cgail_sim.ftl_model import action_to_command, advance_pose, steer_towards

    m = catheter.max_step_insertion
    length = catheter.segment_length
    d = r.T @ (np.asarray(q, dtype=np.float64) - p)
    dist = float(np.linalg.norm(d))
    if dist <= deadband_m:
        return np.zeros(3)
    if d[1] < 0.0 and not catheter.forward_only:
        return np.array([0.0, 0.0, -min(-float(d[1]), m) / m])
    a2 = min(dist / m, 1.0)
    exact = steer_towards(p, r, q, catheter, theta_max, insertion=a2)
    ideal = np.array([math.atan2(d[2], d[1]), math.atan2(-d[0], math.hypot(d[1], d[2]))])
    if dist <= m and (np.abs(ideal) <= theta_max * dist / length).all():
        return exact

    def residual(a: np.ndarray) -> np.ndarray:
        al, ga, dl = action_to_command(a, theta_max, length, m)
        return advance_pose(p, r, float(al), float(ga), float(dl))[0] - q

    from scipy.optimize import least_squares

    x0 = np.clip(exact, [-1.0, -1.0, 1e-6], [1.0, 1.0, 1.0])
    fit = least_squares(residual, x0, bounds=([-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]),
                        xtol=1e-12, ftol=1e-12, gtol=1e-12)
    if np.linalg.norm(fit.fun) < np.linalg.norm(residual(x0)):
        return np.asarray(fit.x, dtype=np.float64)
    return x0


# ---------------------------------------------------------------------- episodes
class _Segment(NamedTuple):
    start: int
    target: int
    points: np.ndarray   # (K, 3) resampled positions, the first at the start
    idle: int            # leading idle steps dropped
    start_offset_m: float
    end: str             # why the recording of this segment ends


def nearest(points: Sequence[np.ndarray], p: np.ndarray) -> tuple[int, float]:
    """Index of the point of ``points`` nearest ``p`` and its distance, m."""
    dist = [float(np.linalg.norm(np.asarray(x) - p)) for x in points]
    k = int(np.argmin(dist))
    return k, dist[k]


def _segments(name: str, rec: SessionRecording, scenarios: Any, dt: float, max_step: float,
              cfg: ConversionConfig, skipped: list[str]) -> list[_Segment]:
    """The recording cut at its goals and gaps, matched to scenario starts and targets;
    ``max_step`` is the catheter's ``v_max dt``, m."""
    smooth = cfg.for_topic(rec.tip_topic)[0]
    targets = [t.position for t in scenarios.targets]
    ids = []
    for t, g in zip(rec.goal_t, rec.goal_p, strict=True):
        k, dist = nearest(targets, g)
        if dist > cfg.target_tolerance_m:
            skipped.append(f'{name}: goal at {t:.3f} s lies {dist * 1e3:.1f} mm from the nearest '
                           f'scenario target ({k}; expected within '
                           f'{cfg.target_tolerance_m * 1e3:g} mm): not converted')
            k = -1
        ids.append(k)
    # an episode per run of goals naming the same target
    starts = [i for i in range(len(ids)) if i == 0 or ids[i] != ids[i - 1]]
    out = []
    for n, i in enumerate(starts):
        if ids[i] < 0:
            continue
        t0 = float(rec.goal_t[i])
        t1 = float(rec.goal_t[starts[n + 1]]) if n + 1 < len(starts) else math.inf
        end = 'next goal' if n + 1 < len(starts) else 'end of recording'
        where = f'{name}: episode at {t0:.3f} s (target {ids[i]})'
        sel = (rec.tip_t >= t0 - cfg.max_gap_s) & (rec.tip_t < t1)
        t, p = rec.tip_t[sel], rec.tip_p[sel]
        if int(np.sum(t >= t0)) < 2:
            skipped.append(f'{where}: expected tip poses after the goal, found '
                           f'{int(np.sum(t >= t0))}')
            continue
        gaps = np.flatnonzero(np.diff(t) > cfg.max_gap_s)
        if len(gaps):
            last = int(gaps[0])
            skipped.append(f'{where}: tip poses stop for {t[last + 1] - t[last]:.2f} s at '
                           f'{t[last]:.3f} s (over max_gap_s {cfg.max_gap_s:g} s): the episode '
                           f'ends there, the rest is not converted')
            t, p = t[:last + 1], p[:last + 1]
            end = 'tracking gap'
        t_lo = max(t0, float(t[0]))
        k_n = math.floor((float(t[-1]) - t_lo) / dt + 1e-9) + 1
        if k_n - 1 < cfg.min_steps:
            skipped.append(f'{where}: expected at least {cfg.min_steps} steps after the goal, '
                           f'found {max(k_n - 1, 0)}')
            continue
        pts = resample(t, p, t_lo + dt * np.arange(k_n), smooth)
        # the tip left the idle radius at ``moved``: it set off at most ``back`` steps before
        moved = np.flatnonzero(np.linalg.norm(pts - pts[0], axis=1) > cfg.idle_radius_m)
        back = math.ceil(cfg.idle_radius_m / max_step) + 1
        idle = max(int(moved[0]) - back, 0) if len(moved) else len(pts) - 1
        pts = pts[idle:]
        s, offset = nearest([st.position for st in scenarios.starts], pts[0])
        if offset > cfg.start_tolerance_m:
            skipped.append(f'{where}: expected it to start within '
                           f'{cfg.start_tolerance_m * 1e3:g} mm of a scenario start, found '
                           f'{offset * 1e3:.1f} mm from start {s}: not convertible (demo bags '
                           f'replay from a scenario start)')
            continue
        if len(pts) - 1 < cfg.min_steps:
            skipped.append(f'{where}: expected at least {cfg.min_steps} steps of motion, found '
                           f'{len(pts) - 1}')
            continue
        out.append(_Segment(s, ids[i], pts, idle, offset, end))
    return out


def track(env: Any, seg: _Segment, cfg: ConversionConfig, name: str, deadband_m: float
          ) -> tuple[DemoEpisode, EpisodeReport]:
    """Step ``env`` along the segment's positions by closed-loop inverse kinematics (module
    docstring, step 4); the episode as the demo bag stores it and its report."""
    from cgail_planner.core.rotations import matrix_to_quaternion

    eng = env.unwrapped.engine
    cat = eng.config.catheter
    env.reset(options={'start': seg.start, 'target': seg.target})
    rows: dict[str, list[Any]] = {'al': [], 'ga': [], 'dl': [], 'p': [], 'q': [], 'g': []}
    kinds = {'insertion': 0, 'bend': 0, 'retraction': 0}
    dev_max, dev_sum = 0.0, 0.0
    end, success, info = seg.end, False, None
    for k in range(1, len(seg.points)):
        q = seg.points[k]
        act = fit_step(eng.catheter.tip_position[0].copy(), eng.catheter.tip_rotation[0].copy(),
                       q, cat, eng.catheter.theta_max, deadband_m)
        _, _, te, tr, info = env.step(act.astype(np.float32))
        tip = eng.catheter.tip_position[0]
        dev = float(np.linalg.norm(tip - q))
        kinds['retraction'] += bool(act[2] < 0.0)
        if dev > max(CLIP_M, deadband_m):
            # a bound was active: the insertion's, else a bend's (or a lateral offset while
            # retracting, which ignores the bends)
            kinds['insertion' if abs(act[2]) >= 1.0 - 1e-9 else 'bend'] += 1
        dev_max, dev_sum = max(dev_max, dev), dev_sum + dev
        rows['al'].append(info['bend'][0])
        rows['ga'].append(info['bend'][1])
        rows['dl'].append(info['insertion'])
        rows['p'].append(tip.copy())
        rows['q'].append(matrix_to_quaternion(eng.catheter.tip_rotation[0]))
        rows['g'].append(np.asarray(info['target_position'], float))
        if te or tr:
            success = bool(info['success'])
            end = ('target reached' if success else 'collision' if info['collision']
                   else 'exited' if info['exited'] else 'step limit')
            break
        if dev > cfg.max_deviation_m:
            end = 'deviation'
            break
    steps = len(rows['al'])
    final = float(np.linalg.norm(eng.catheter.tip_position[0] - eng.target[0]))
    ep = DemoEpisode(seg.start, seg.target, np.asarray(rows['al']), np.asarray(rows['ga']),
                     np.asarray(rows['dl']), np.asarray(rows['p']), np.asarray(rows['q']),
                     np.asarray(rows['g']), success)
    report = EpisodeReport(name, seg.start, seg.target, steps, success, end, seg.idle,
                           kinds['insertion'], kinds['bend'], kinds['retraction'],
                           seg.start_offset_m, dev_max, dev_sum / max(steps, 1), final)
    return ep, report


def convert_bags(paths: Sequence[Path], env: Any, config: ConversionConfig | None = None,
                 log: Callable[[str], None] | None = None
                 ) -> tuple[list[DemoEpisode], ConversionReport]:
    """Convert the trial bags ``paths`` into episodes of ``env`` (a static
    :class:`~cgail_sim.env.CatheterNavEnv` of the anatomy they were recorded in).

    Never raises for an input: every bag or episode that cannot be converted is a line of
    :attr:`ConversionReport.skipped`. ``log`` sees each episode's and skip's line as it comes.
    """
    cfg = config or ConversionConfig()
    report = ConversionReport(bags=len(paths))
    episodes: list[DemoEpisode] = []
    say = log or (lambda _line: None)
    sc = env.unwrapped.engine.scenarios
    dt = env.unwrapped.engine.config.dt
    max_step = env.unwrapped.engine.config.catheter.max_step_insertion
    topics_used: dict[str, int] = {}
    commands_seen = 0
    for path in paths:
        name = str(path)
        try:
            rec = read_session_bag(Path(path), cfg.tip_topic)
        except DemoError as exc:
            report.skipped.append(str(exc))
            say(str(exc))
            continue
        topics_used[rec.tip_topic] = topics_used.get(rec.tip_topic, 0) + 1
        commands_seen += bool(rec.commands)
        before = len(report.skipped)
        for seg in _segments(name, rec, sc, dt, max_step, cfg, report.skipped):
            ep, ep_report = track(env, seg, cfg, name, cfg.for_topic(rec.tip_topic)[1])
            episodes.append(ep)
            report.episodes.append(ep_report)
            say(ep_report.line())
        for line in report.skipped[before:]:
            say(line)
    for topic, n in sorted(topics_used.items()):
        report.notes.append(f'tip positions from {topic} ({n} bag(s))')
    if commands_seen:
        report.notes.append(f'{commands_seen} bag(s) record teleop commands '
                            f'({", ".join(COMMAND_TOPICS)}): not used, the actions are '
                            'inferred from the tip motion')
    return episodes, report

"""The safety supervisor of autonomous navigation: pure logic, an explicit clock, no ROS.

Every command the autonomy sends to the catheter passes through :meth:`Supervisor.tick`, which
caps it and, on any stop condition, replaces it by the safe command. The clock is explicit:
every method takes ``now`` (s, the caller's monotonic or simulated time).

**States.** ``idle`` (not engaged: the output is the safe command, and a node publishes
nothing), ``running`` (the capped controller command goes out), ``stopped`` (latched with a
:class:`Stop`: reason code, message, time). :meth:`Supervisor.resume` is the only way from
``idle`` or ``stopped`` to ``running``; it is refused, with every condition named, while any
stop condition still holds (:meth:`Supervisor.holding`). After a resume only a command computed
at or after the resume (``Command.stamp >= resumed_at``) moves the catheter: no command that
was computed before it (a queue, a held-over controller output) is ever replayed; until a fresh
one comes the output is the hold (insertion 0, bend where it is).

**Stop conditions** (reason codes, :data:`STOP_REASONS`; limits: :class:`SafetyConfig`):

============================  ==================================================================
``tracking_lost``             no valid EM pose for ``tracking_timeout_s``
``pose_jump``                 the tip moved between two valid poses faster than a catheter can
                              (:meth:`SafetyConfig.max_tip_speed`); holds until two
                              consecutive poses agree again
``path_deviation``            the tip is more than ``max_path_deviation`` from the planned path
``stall``                     insertion commanded but the tip not advancing along the path:
                              over ``stall_window_s`` the tip's progress along the path is below
                              ``stall_min_ratio`` of the insertion the path allows (the commanded
                              insertion, capped by the path left beyond the tip at the window's
                              start; at least ``stall_min_commanded``): contact or buckling
                              (:meth:`Supervisor._check_stall` says why). An estimate from
                              the past window: once stopped nothing is commanded, so it does not
                              hold and a resume (after the person has looked) starts a new window
``left_lumen``                the tip centre is more than ``lumen_margin`` beyond the wall of
                              the registered lumen (the wall's ``tip_contact`` query,
                              :class:`cgail_sim.wall.StaticWall`)
``stale_command``             no fresh, finite controller command for ``command_timeout_s``
``stale_planner``             no planner output (a path or its guidance) for
                              ``planner_timeout_s``
``watchdog``                  the supervisor's own tick came later than ``tick_timeout_s``
                              after the previous one (the host stalled); the device nodes' own
                              watchdogs (``pam_controller`` vents after 0.5 s, ``sleeve_driver``
                              stops after 0.2 s without a command) cover a supervisor that
                              stops ticking altogether
``device_fault``              a device node of the rig (``pam_controller``, ``sleeve_driver``,
                              ``aurora``) reports an error (:meth:`Supervisor.on_device`: its
                              ``/diagnostics`` at level ERROR, e.g. the regulator bank's
                              ``FAULT_STUCK``, a chamber that does not follow its setpoint);
                              holds until that device reports no error
``deadman_released``          the operator's deadman not held (or its Joy stream older than
                              ``joy_timeout_s``), when ``deadman_required``
``estop``                     the e-stop is engaged (:meth:`Supervisor.set_estop`)
============================  ==================================================================

**Safe command** (:meth:`Supervisor.tick` while not running): insertion velocity 0 and the bend
ramped to straight (0, 0) at ``max_bend_rate``: the PAMs go to their vented, straight state
without whipping the tip. **Caps** (every output, whatever the input, NaN/inf/huge included):
``|v| <= max_insertion_speed``, ``hypot(alpha, gamma) <= max_bend`` (the direction kept), the
bend moves at most ``max_bend_rate * dt`` per tick; a non-finite velocity becomes 0 and a
non-finite bend keeps the last output bend. Chamber pressures are capped by
``pam_controller`` itself (``max_pressure_pa``) for any bend it accepts.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, fields
import math
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from cgail_planner.core.guidance import PathFollower

FloatArray = NDArray[np.float64]

#: Reason codes of a stop, in the order the conditions are checked.
STOP_REASONS = ('estop', 'deadman_released', 'watchdog', 'device_fault', 'tracking_lost',
                'pose_jump', 'left_lumen', 'path_deviation', 'stall', 'stale_planner',
                'stale_command')
#: Supervisor states.
STATES = ('idle', 'running', 'stopped')


class Command(NamedTuple):
    """A catheter command, in the units of ``catheter/insertion_command`` and
    ``catheter/bend_command``."""

    insertion_velocity: float
    """Sleeve insertion velocity, m/s (positive inserts)."""
    bend: tuple[float, float]
    """Segment bend ``(bend_alpha, bend_gamma)``, rad."""
    stamp: float
    """When the controller computed it, s (the caller's clock)."""


class Stop(NamedTuple):
    """A latched stop."""

    reason: str
    """Reason code (:data:`STOP_REASONS`)."""
    message: str
    """What happened, with the measured value and the limit."""
    at: float
    """When it was detected, s."""


class WallQuery(Protocol):
    """The lumen query the supervisor uses (:class:`cgail_sim.wall.StaticWall`)."""

    def tip_contact(self, tip: np.ndarray, radius: float, dt: float) -> Any:
        """The tip sphere vs the wall: an object with ``penetration`` (m, > 0 when the sphere
        crosses the wall)."""


@dataclass(frozen=True)
class SafetyConfig:
    """Every limit of the supervisor (the ``autonomy`` node's read-only parameters of the same
    names; docs/guides/autonomy.md says why each value)."""

    tracking_timeout_s: float = 0.25
    """Stop when no valid EM pose came for this long, s: 10 frames of the 40 Hz Aurora (its
    own diagnostics go STALE after 0.5 s); (0, 10]."""
    max_insertion_speed: float = 0.005
    """Cap of the commanded insertion speed, m/s: the sleeve driver's (and the catheter
    model's) 5 mm/s; (0, 0.005]."""
    max_bend: float = math.pi / 2
    """Cap of the commanded bend magnitude hypot(alpha, gamma), rad: the PAM controller's
    ``max_bend_rad``; (0, pi/2]."""
    max_bend_rate: float = 1.0
    """Cap of the commanded bend's rate of change, rad/s: straight to full bend in 1.6 s
    (the teleop's rate mode: 0.5 rad/s at full deflection); also the ramp to straight on a
    stop; (0, 10]."""
    segment_length: float = 0.05
    """Steerable segment length L, m (the catheter model's): how far a bend change moves the
    tip (:meth:`max_tip_speed`); [0.001, 0.5]."""
    max_wall_speed: float = 0.1
    """Fastest the beating wall can carry the tip, m/s: the aortic root's systolic excursion of
    about 10 mm (Plonek et al. 2018, the heartbeat model's amplitude) within ~0.15 s, rounded
    up; [0, 1]."""
    pose_jump_slack: float = 0.003
    """Distance added to the speed bound between two poses, m: the Aurora's position noise
    (0.5 mm RMS, both poses, 3 sigma) and registration jitter; (0, 0.05]."""
    max_path_deviation: float = 0.010
    """Stop when the tip is further than this from the planned path, m: beyond the planner's
    re-plan corridor (8 mm) and half an aortic lumen radius; (0, 0.05]."""
    stall_window_s: float = 6.0
    """Window of the stall (contact/buckling) estimate, s: long enough that a relay pause of
    the sleeve driver (return stroke 1.5 s plus two handovers, 2.1-2.5 s at the tip) leaves a
    healthy tip at least ~0.45 of the insertion in any window (4 s left it ~0.3, next to
    ``stall_min_ratio``: :meth:`Supervisor._check_stall`), short enough that a slipping
    sleeve is stopped within (1 - ``stall_min_ratio``) of it, 4.5 s, inside its 6.5 s bound
    (``cgail_rig.core.faults.DETECTION_BOUNDS_S``); (0, 30]."""
    stall_min_commanded: float = 0.0075
    """Insertion the path allows over the window (the commanded insertion, capped by the path
    left beyond the tip at the window's start) below which the stall test does not apply, m:
    a mean commanded speed of 1.25 mm/s over the 6 s window, as 5 mm was over the earlier 4 s
    one, and a quarter of it (1.9 mm) is ~2.7 times the noise of the advance measured between
    two EM poses (0.7 mm RMS); (0, 0.1]."""
    stall_min_ratio: float = 0.25
    """Stop when the tip's progress along the path is below this share of the insertion the
    path allows over the window (a relay pause alone leaves ~0.6 of a 6 s window); (0, 1)."""
    lumen_margin: float = 0.002
    """Stop when the tip centre is further than this beyond the wall, m: EM noise (0.5 mm RMS)
    plus a registration error of about 1 mm; [0, 0.02]."""
    catheter_radius: float = 0.0035
    """Radius of the tip sphere the wall query uses, m (the catheter model's 7 mm diameter);
    (0, 0.01]."""
    command_timeout_s: float = 0.5
    """Stop when no fresh finite controller command came for this long, s; (0, 10]."""
    planner_timeout_s: float = 1.0
    """Stop when no planner output (path or guidance) came for this long, s: 40 guidance
    updates at the tracker rate; (0, 60]."""
    tick_timeout_s: float = 0.25
    """Stop when the supervisor's tick comes later than this after the previous one, s
    (several periods of the 40 Hz tick; the sleeve driver's watchdog is 0.2 s); (0, 10]."""
    deadman_required: bool = True
    """Run only while the operator holds the deadman (Joy enable button); ``False`` for a
    fully autonomous run supervised by the e-stop alone (a simulated session)."""
    joy_timeout_s: float = 0.5
    """A deadman whose Joy stream is older than this counts as released, s (teleop's
    ``joy_timeout_s``); (0, 10]."""

    def __post_init__(self) -> None:
        ranges = {
            'tracking_timeout_s': (0.0, 10.0, True), 'max_insertion_speed': (0.0, 0.005, True),
            'max_bend': (0.0, math.pi / 2, True), 'max_bend_rate': (0.0, 10.0, True),
            'segment_length': (0.001, 0.5, False), 'max_wall_speed': (0.0, 1.0, False),
            'pose_jump_slack': (0.0, 0.05, True), 'max_path_deviation': (0.0, 0.05, True),
            'stall_window_s': (0.0, 30.0, True), 'stall_min_commanded': (0.0, 0.1, True),
            'stall_min_ratio': (0.0, 1.0, True), 'lumen_margin': (0.0, 0.02, False),
            'catheter_radius': (0.0, 0.01, True), 'command_timeout_s': (0.0, 10.0, True),
            'planner_timeout_s': (0.0, 60.0, True), 'tick_timeout_s': (0.0, 10.0, True),
            'joy_timeout_s': (0.0, 10.0, True)}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == 'deadman_required':
                if not isinstance(value, bool):
                    raise ValueError(f'deadman_required: expected a bool, found {value!r}')
                continue
            low, high, low_open = ranges[f.name]
            ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
                  and math.isfinite(value) and (value > low if low_open else value >= low)
                  and value <= high + 1e-12)
            if not ok:
                raise ValueError(f"{f.name}: expected a number in {'(' if low_open else '['}"
                                 f'{low:g}, {high:g}], found {value!r}')
        if self.stall_min_ratio >= 1.0:
            raise ValueError(f'stall_min_ratio: expected a number in (0, 1), found '
                             f'{self.stall_min_ratio!r}')

    def max_tip_speed(self) -> float:
        """The fastest a catheter tip can move, m/s: the sleeve's insertion cap, plus a bend
        change moving the tip of the steerable segment (at most ``L`` per rad of bend, the
        constant-curvature arc's bound) at ``max_bend_rate``, plus the beating wall carrying
        it: ``max_insertion_speed + segment_length * max_bend_rate + max_wall_speed``."""
        return (self.max_insertion_speed + self.segment_length * self.max_bend_rate
                + self.max_wall_speed)

    def max_pose_step(self, dt: float) -> float:
        """Largest plausible distance between two valid poses ``dt`` s apart, m."""
        return self.max_tip_speed() * max(dt, 0.0) + self.pose_jump_slack


def cap_bend(bend: tuple[float, float], max_bend: float) -> tuple[float, float]:
    """``bend`` scaled so that ``hypot(alpha, gamma) <= max_bend`` (direction kept)."""
    total = math.hypot(bend[0], bend[1])
    if total <= max_bend:
        return float(bend[0]), float(bend[1])
    k = max_bend / total
    return float(bend[0]) * k, float(bend[1]) * k


class Supervisor:
    """The supervisor (module docstring).

    Args:
        config: the limits.
        wall: the registered lumen's wall (``None``: the ``left_lumen`` condition is off, for
            a bench without an anatomy).
    """

    def __init__(self, config: SafetyConfig | None = None, wall: WallQuery | None = None
                 ) -> None:
        self.config = config or SafetyConfig()
        self.wall = wall
        self.stops = 0
        """Stops since construction."""
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to ``idle`` with nothing known (a new trial); the e-stop stays as it is."""
        self.state = 'idle'
        self.stop: Stop | None = None
        self.resumed_at = -math.inf
        self.path: PathFollower | None = None
        self.estop = getattr(self, 'estop', False)
        self._pose: FloatArray | None = None
        self._pose_t: float | None = None
        self._jump: str | None = None
        self._deviation = 0.0
        self._outside = 0.0
        self._arc = 0.0
        self._planner_t: float | None = None
        self._command_t: float | None = None
        self._deadman = False
        self._joy_t: float | None = None
        self._tick_t: float | None = None
        self._tick_gap = 0.0
        self._bend = (0.0, 0.0)
        self._window: deque[tuple[float, float, float]] = deque()
        self._device_errors: dict[str, str] = {}

    @property
    def output_bend(self) -> tuple[float, float]:
        """The bend of the last output, rad."""
        return self._bend

    # ------------------------------------------------------------------ inputs
    def on_pose(self, now: float, position: FloatArray | None) -> None:
        """A tip position from the tracker at ``now`` (``None`` or non-finite: not valid)."""
        if position is None:
            return
        p = np.asarray(position, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or not np.isfinite(p).all():
            return
        cfg = self.config
        if self._pose is not None and self._pose_t is not None:
            dt = now - self._pose_t
            step = float(np.linalg.norm(p - self._pose))
            bound = cfg.max_pose_step(dt)
            self._jump = (f'the tip moved {step * 1e3:.1f} mm in {dt:.3f} s, more than the '
                          f'{bound * 1e3:.1f} mm a catheter can ({cfg.max_tip_speed() * 1e3:.0f}'
                          f' mm/s + {cfg.pose_jump_slack * 1e3:.1f} mm)') if step > bound \
                else None
        self._pose, self._pose_t = p, now
        if self.path is not None:
            _, self._arc, closest = self.path.project(p)
            self._deviation = float(np.linalg.norm(closest - p))
        if self.wall is not None:
            contact = self.wall.tip_contact(p, cfg.catheter_radius, 0.1)
            pen = float(contact.penetration)
            self._outside = pen - cfg.catheter_radius if pen > 0.0 else -math.inf
        self._check_events(now)

    def on_path(self, now: float, points: FloatArray) -> None:
        """A new planned path (N, 3) at ``now``: the deviation is measured from it.

        Raises:
            ValueError: a path that is not (N >= 2, 3), finite and of positive length.
        """
        self.path = PathFollower(points)
        self._planner_t = now
        if self._pose is not None:
            _, self._arc, closest = self.path.project(self._pose)
            self._deviation = float(np.linalg.norm(closest - self._pose))
        self._window.clear()  # progress is measured along one path

    def on_planner_output(self, now: float) -> None:
        """The planner gave guidance at ``now`` (it is alive and has a path)."""
        self._planner_t = now

    def on_deadman(self, now: float, held: bool) -> None:
        """The operator's deadman at ``now`` (a Joy message)."""
        self._deadman = bool(held)
        self._joy_t = now
        self._check_events(now)

    def on_device(self, now: float, device: str, error: str | None) -> None:
        """A device node's health at ``now``: ``error`` is its error message, or None when it
        reports none (clears that device's error)."""
        if error is None:
            self._device_errors.pop(device, None)
        else:
            self._device_errors[device] = error
        self._check_events(now)

    def set_estop(self, now: float, engaged: bool) -> None:
        """Engage (stop at once, latched) or release the e-stop (releasing does not resume)."""
        self.estop = bool(engaged)
        if self.estop:
            self._trip(now, 'estop', 'e-stop engaged')

    def resume(self, now: float) -> tuple[bool, str]:
        """Engage from ``idle`` or resume from ``stopped``.

        Returns:
            ``(accepted, message)``: refused (with every condition that still holds) unless
            nothing holds; accepted, the state is ``running`` and only commands computed from
            now on move the catheter.
        """
        if self.state == 'running':
            return True, 'already running'
        holding = self.holding(now)
        if holding:
            return False, 'resume refused: ' + '; '.join(f'{r}: {m}' for r, m in holding)
        self.state = 'running'
        self.stop = None
        self.resumed_at = now
        self._window.clear()
        self._jump = None
        return True, 'running'

    # ------------------------------------------------------------------ conditions
    def holding(self, now: float) -> list[tuple[str, str]]:
        """Every stop condition that holds at ``now``, as ``(reason, message)``, in
        :data:`STOP_REASONS` order (``stall`` is an event of the running window: never)."""
        cfg = self.config
        out: list[tuple[str, str]] = []
        if self.estop:
            out.append(('estop', 'e-stop engaged'))
        if cfg.deadman_required:
            if self._joy_t is None or now - self._joy_t > cfg.joy_timeout_s:
                out.append(('deadman_released', 'no deadman (Joy) for '
                            f'{_age(now, self._joy_t)} (limit {cfg.joy_timeout_s} s)'))
            elif not self._deadman:
                out.append(('deadman_released', 'deadman released'))
        gap = 0.0 if self._tick_t is None else max(self._tick_gap, now - self._tick_t)
        if gap > cfg.tick_timeout_s:
            out.append(('watchdog', f'supervisor ticks {gap:.3f} s apart (limit '
                        f'{cfg.tick_timeout_s} s)'))
        if self._device_errors:
            out.append(('device_fault', '; '.join(f'{d}: {m}' for d, m in
                                                  sorted(self._device_errors.items()))))
        if self._pose_t is None or now - self._pose_t > cfg.tracking_timeout_s:
            out.append(('tracking_lost', f'no valid EM pose for {_age(now, self._pose_t)} '
                        f'(limit {cfg.tracking_timeout_s} s)'))
        if self._jump is not None:
            out.append(('pose_jump', self._jump))
        if self._outside > cfg.lumen_margin:
            out.append(('left_lumen', f'tip {self._outside * 1e3:.1f} mm beyond the wall '
                        f'(limit {cfg.lumen_margin * 1e3:.1f} mm)'))
        if self.path is not None and self._deviation > cfg.max_path_deviation:
            out.append(('path_deviation', f'tip {self._deviation * 1e3:.1f} mm from the '
                        f'planned path (limit {cfg.max_path_deviation * 1e3:.1f} mm)'))
        if self.path is None or self._planner_t is None \
                or now - self._planner_t > cfg.planner_timeout_s:
            what = 'no planned path' if self.path is None else \
                f'no planner output for {_age(now, self._planner_t)}'
            out.append(('stale_planner', f'{what} (limit {cfg.planner_timeout_s} s)'))
        if self._command_t is None or now - self._command_t > cfg.command_timeout_s:
            out.append(('stale_command', f'no fresh controller command for '
                        f'{_age(now, self._command_t)} (limit {cfg.command_timeout_s} s)'))
        return out

    def _check_events(self, now: float) -> None:
        """Trip on the first condition that holds (running only)."""
        if self.state != 'running':
            return
        holding = self.holding(now)
        if holding:
            self._trip(now, *holding[0])

    def _trip(self, now: float, reason: str, message: str) -> None:
        if self.state == 'stopped':
            return  # the first reason stays latched
        self.state = 'stopped'
        self.stop = Stop(reason, message, now)
        self.stops += 1
        self._window.clear()

    # ------------------------------------------------------------------ output
    def tick(self, now: float, proposed: Command | None) -> Command:
        """One supervisor tick at ``now``: check every condition, then the capped output.

        Args:
            now: the time, s.
            proposed: the controller's latest command (``None``: none this tick). A finite
                one refreshes the command watchdog; one computed before the last resume is
                never sent.

        Returns:
            What to send: the capped command while running, else the safe command.
        """
        cfg = self.config
        dt = 0.0 if self._tick_t is None else max(now - self._tick_t, 0.0)
        self._tick_gap = dt
        self._tick_t = now
        fresh = None
        if proposed is not None and math.isfinite(proposed.stamp) \
                and proposed.stamp >= self.resumed_at and _finite(proposed):
            self._command_t = max(self._command_t or -math.inf, proposed.stamp)
            fresh = proposed
        self._check_events(now)
        if self.state == 'running' and fresh is not None:
            velocity = min(max(fresh.insertion_velocity, -cfg.max_insertion_speed),
                           cfg.max_insertion_speed)
            target = cap_bend(fresh.bend, cfg.max_bend)
        else:  # stopped or idle: halt and straighten; running without a fresh command: hold
            velocity = 0.0
            target = self._bend if self.state == 'running' else (0.0, 0.0)
        self._bend = _slew(self._bend, target, cfg.max_bend_rate * dt)
        if self.state == 'running':
            self._window.append((now, max(velocity, 0.0), self._arc))
            self._check_stall(now)
        return Command(velocity, self._bend, now)

    def _check_stall(self, now: float) -> None:
        """Trip ``stall`` when, over the last ``stall_window_s``, the tip advanced along the
        path less than ``stall_min_ratio`` of the insertion the path allowed.

        The window holds ``(t, output insertion velocity, tip arc)`` per tick. The insertion
        the path allows is ``min(commanded, left)``: ``commanded`` the integral of the output
        velocity over the window, ``left`` the arc length of the path beyond the tip at the
        window's start. However much is inserted, the tip cannot advance along the path by
        more than the path has left; near the target the controller aims at the path's end
        and a tip that reaches it from the side, or has no path left, is not stalled. Below
        ``stall_min_commanded`` allowed (the last few millimetres of the path) the test does
        not apply: there the arrival rule ends the run.

        The ratio a healthy tip keeps is set by the sleeve driver's relay pause, 2.1-2.5 s
        during which the sleeve returns and the catheter stands still while the insertion
        command goes on, times the grip's slip (the tip moves ~0.8-0.9 of the sleeve) and,
        near the target, the heading turning off the path. In a 4 s window that left a
        healthy tip ~0.3 of the command (true poses of the issue-36 sessions: 0.26-0.35),
        next to the 0.25 limit, and the EM poses' noise (0.5 mm RMS each, the difference of
        two poses ~0.7 mm) on the few millimetres commanded near the target, where the
        insertion slows to 30-50 %, pushed it below: every one of the 24 stall stops of the
        30-trial sessions came 4.3-10.0 mm from the target, on tips the phantom's true pose
        showed advancing. A replay of their recorded EM poses with the path tracker's
        commands found the lowest ratio of a healthy window 0.45-0.53 with a 6 s window
        (``stall_window_s``). A longer window holds more insertion at the same speed, so
        ``stall_min_commanded`` grew with it (5 -> 7.5 mm): at 5 mm over 6 s the test reached
        the slowest final approaches (0.85 mm/s, a quarter of it within the EM noise) and
        tripped 5 of the first 30 static path-tracker trials. A tip that stops is caught once
        less than ``stall_min_ratio`` of the window's insertion came before it stopped:
        (1 - 0.25) * 6 = 4.5 s at most.
        """
        cfg, w = self.config, self._window
        while len(w) > 2 and now - w[1][0] >= cfg.stall_window_s:
            w.popleft()
        if len(w) < 2 or now - w[0][0] < cfg.stall_window_s or self.path is None:
            return
        commanded = sum(v * (w[k + 1][0] - w[k][0]) for k, (_, v, _) in
                        enumerate(list(w)[:-1]))
        left = max(self.path.length - w[0][2], 0.0)
        allowed = min(commanded, left)
        advance = w[-1][2] - w[0][2]
        if allowed >= cfg.stall_min_commanded and advance < cfg.stall_min_ratio * allowed:
            capped = '' if commanded <= left else \
                f' ({left * 1e3:.1f} mm of path left)'
            self._trip(now, 'stall', f'{commanded * 1e3:.1f} mm inserted in '
                       f'{now - w[0][0]:.1f} s{capped} but the tip advanced '
                       f'{advance * 1e3:.1f} mm along the path (limit '
                       f'{cfg.stall_min_ratio:.0%}): contact or buckling')


def _finite(command: Command) -> bool:
    try:
        values = (float(command.insertion_velocity), float(command.bend[0]),
                  float(command.bend[1]))
    except (TypeError, ValueError, IndexError):
        return False
    return all(math.isfinite(v) for v in values)


def _slew(current: tuple[float, float], target: tuple[float, float], step: float
          ) -> tuple[float, float]:
    """``current`` moved towards ``target`` by at most ``step`` (Euclidean), rad."""
    da, dg = target[0] - current[0], target[1] - current[1]
    d = math.hypot(da, dg)
    if d <= step:
        return target
    k = step / d
    return current[0] + da * k, current[1] + dg * k


def _age(now: float, since: float | None) -> str:
    return 'ever' if since is None else f'{now - since:.3f} s'

"""Sleeve-based relay insertion: the host-side state machine.

The driver (paper section IV-B, Omar et al. 2023) has a sleeve on a linear axis carrying the
*moving* gripper and a *fixed* gripper at the front of the frame. Both are pneumatic and grasp
the catheter alternately, so the catheter can be inserted (or retracted) over any length with a
sleeve of short stroke:

========== ================= ================= ===============================================
phase      moving gripper    fixed gripper     sleeve
========== ================= ================= ===============================================
DRIVE      closed (holds)    open              follows the command, |v| <= ``max_speed``;
                                               the catheter moves with it
CLOSE_FIXED closed (holds)   closing           still
OPEN_MOVING opening          closed (holds)    still
RETURN     open              closed (holds)    back to the start of the next stroke at
                                               ``return_speed``; the catheter stays put
CLOSE_MOVING closing         closed (holds)    still
OPEN_FIXED closed (holds)    opening           still
========== ================= ================= ===============================================

Safety invariants, enforced here and checked by the property tests against
:class:`~catheter_driver.core.mechanism.SleeveMechanism`:

* **Never ungripped.** A gripper is only told to open when the *measured* state of the other
  one is ``CLOSED`` and it is commanded closed, so at every instant at least one gripper holds
  the catheter (a gripper that is closing or opening is counted as not holding).
* **Speed cap.** While the moving gripper may touch the catheter the sleeve command is capped to
  ``max_speed`` (5 mm/s, insertion and retraction), and to what keeps the sleeve inside its
  stroke and the catheter inside ``[position_min, position_max]`` over the next ``dt``.
* The sleeve is only commanded to move with both grippers in a steady state and exactly one
  closed (DRIVE or RETURN).

Insertion is continuous in the sense that it goes on past the sleeve stroke without operator
action; the catheter pauses during a relay (two handovers and the return stroke), so the mean
rate is below the commanded one. The catheter position is tracked here by integrating sleeve
displacement measured while the moving gripper holds and the fixed one is open.
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
import math


class GripperState(enum.IntEnum):
    """Measured state of one pneumatic gripper (also its 2-bit code on the CAN bus)."""

    OPEN = 0
    CLOSING = 1
    CLOSED = 2
    OPENING = 3


class Phase(enum.IntEnum):
    """Phase of the relay cycle (see the module docstring)."""

    DRIVE = 0
    CLOSE_FIXED = 1
    OPEN_MOVING = 2
    RETURN = 3
    CLOSE_MOVING = 4
    OPEN_FIXED = 5


@dataclass(frozen=True)
class RelayConfig:
    """Limits and geometry of the sleeve driver (SI units)."""

    max_speed: float = 0.005
    """Catheter speed cap for insertion and retraction, m/s (paper: 5 mm/s)."""
    return_speed: float = 0.02
    """Sleeve speed during the return stroke (catheter held by the fixed gripper), m/s."""
    stroke_min: float = 0.0
    """Sleeve position at the back end of its stroke, m."""
    stroke_max: float = 0.03
    """Sleeve position at the front end of its stroke, m."""
    position_min: float = 0.0
    """Smallest catheter insertion the driver will retract to, m (0 = homed)."""
    position_max: float = 1.0
    """Largest catheter insertion the driver will insert to, m (working length)."""
    gripper_close_time: float = 0.15
    """Nominal time for a gripper to close, s (used by the simulated mechanism)."""
    gripper_open_time: float = 0.15
    """Nominal time for a gripper to open, s (used by the simulated mechanism)."""
    gripper_timeout: float = 1.0
    """A handover step that takes longer than this is reported as a gripper fault, s."""
    arrival_tolerance: float = 1e-5
    """Sleeve position tolerance for reaching a stroke end, m."""

    def __post_init__(self) -> None:
        positive = ('max_speed', 'return_speed', 'gripper_close_time', 'gripper_open_time',
                    'gripper_timeout', 'arrival_tolerance')
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'{name} must be a finite number > 0, found {value!r}')
        if self.max_speed > 0.005:
            raise ValueError(
                f'max_speed must be <= 0.005 m/s (the rig cap), found {self.max_speed!r}')
        for name in ('stroke_min', 'stroke_max', 'position_min', 'position_max'):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ValueError(f'{name} must be finite, found {value!r}')
        if self.stroke_max - self.stroke_min <= 10 * self.arrival_tolerance:
            raise ValueError(
                f'stroke_max must exceed stroke_min by more than 10 * arrival_tolerance, '
                f'found stroke_min={self.stroke_min!r}, stroke_max={self.stroke_max!r}')
        if self.position_max <= self.position_min:
            raise ValueError(
                f'position_max must be > position_min, found position_min='
                f'{self.position_min!r}, position_max={self.position_max!r}')
        if self.gripper_timeout <= max(self.gripper_close_time, self.gripper_open_time):
            raise ValueError(
                f'gripper_timeout must exceed the gripper open/close times, found '
                f'{self.gripper_timeout!r}')


@dataclass(frozen=True)
class SleeveFeedback:
    """What the device reports: sleeve position and the two gripper states."""

    sleeve_position: float
    """Sleeve position along its stroke, m."""
    moving: GripperState
    """State of the gripper on the sleeve."""
    fixed: GripperState
    """State of the gripper on the frame."""


@dataclass(frozen=True)
class ActuatorCommand:
    """What the host sends: sleeve velocity and the two valve commands."""

    sleeve_velocity: float
    """Sleeve velocity setpoint, m/s."""
    moving_close: bool
    """True to close (pressurise) the moving gripper."""
    fixed_close: bool
    """True to close (pressurise) the fixed gripper."""


def clamp_velocity(velocity: float, max_speed: float) -> float:
    """Clamp a velocity to ``[-max_speed, max_speed]``.

    Raises:
        ValueError: if ``velocity`` is NaN (a NaN cannot be clamped to anything safe).
    """
    if math.isnan(velocity):
        raise ValueError(f'expected a finite velocity, found {velocity!r}')
    return max(-max_speed, min(max_speed, velocity))


def catheter_velocity(feedback: SleeveFeedback, sleeve_velocity: float) -> float:
    """Catheter velocity implied by a measured sleeve velocity (m/s): the sleeve's while the
    moving gripper holds and the fixed one is open, else 0."""
    coupled = feedback.moving == GripperState.CLOSED and feedback.fixed == GripperState.OPEN
    return float(sleeve_velocity) if coupled else 0.0


class RelayController:
    """Turns a catheter velocity command and device feedback into actuator commands.

    Call :meth:`step` once per control period with the newest feedback. The controller starts
    in ``CLOSE_MOVING`` (both valves closed), so it first makes sure the catheter is held.
    """

    def __init__(self, config: RelayConfig, feedback: SleeveFeedback,
                 catheter_position: float = 0.0) -> None:
        """Create a controller.

        Args:
            config: limits and geometry.
            feedback: the device state at start-up.
            catheter_position: the catheter insertion at start-up, m.
        """
        self.config = config
        self._phase = Phase.CLOSE_MOVING
        self._feedback = feedback
        self._position = float(catheter_position)
        self._velocity = 0.0
        self._direction = 1.0
        self._phase_time = 0.0
        self._estop = False

    @property
    def phase(self) -> Phase:
        """The current relay phase."""
        return self._phase

    @property
    def position(self) -> float:
        """Tracked catheter insertion, m."""
        return self._position

    @property
    def velocity(self) -> float:
        """Catheter velocity over the last step, m/s."""
        return self._velocity

    @property
    def estop(self) -> bool:
        """True while the e-stop holds the sleeve still."""
        return self._estop

    @property
    def fault(self) -> str | None:
        """A description of a handover that takes too long, else None."""
        if self._phase in (Phase.DRIVE, Phase.RETURN):
            return None
        if self._phase_time > self.config.gripper_timeout:
            return (f'expected phase {self._phase.name} to finish within '
                    f'{self.config.gripper_timeout:.3f} s, found {self._phase_time:.3f} s '
                    f'(moving {self._feedback.moving.name}, fixed {self._feedback.fixed.name})')
        return None

    def set_estop(self, engaged: bool) -> None:
        """Engage or release the e-stop: while engaged the sleeve is commanded still and the
        relay does not advance (valves keep their state, so the catheter stays held)."""
        self._estop = bool(engaged)

    def step(self, velocity: float, feedback: SleeveFeedback, dt: float) -> ActuatorCommand:
        """Advance one control period.

        Args:
            velocity: desired catheter velocity, m/s (clamped to ``max_speed``).
            feedback: the newest device state.
            dt: time until the next call, s (> 0).

        Returns:
            The actuator command to send now.

        Raises:
            ValueError: if ``velocity`` is NaN or ``dt`` is not a finite positive number.
        """
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f'dt must be a finite number > 0, found {dt!r}')
        cfg = self.config
        v_cmd = clamp_velocity(velocity, cfg.max_speed)
        if self._estop:
            v_cmd = 0.0
        prev = self._feedback
        self._track(prev, feedback, dt)
        self._feedback = feedback
        if v_cmd != 0.0:
            self._direction = math.copysign(1.0, v_cmd)
        self._phase_time += dt
        if not self._estop:
            self._advance(v_cmd, feedback)
        return self._command(v_cmd, feedback, dt)

    # -- internals ---------------------------------------------------------------------------

    def _track(self, prev: SleeveFeedback, new: SleeveFeedback, dt: float) -> None:
        coupled = prev.moving == GripperState.CLOSED and prev.fixed == GripperState.OPEN
        delta = new.sleeve_position - prev.sleeve_position if coupled else 0.0
        self._position += delta
        self._velocity = delta / dt

    def _set_phase(self, phase: Phase) -> None:
        self._phase = phase
        self._phase_time = 0.0

    def _needs_relay(self, v_cmd: float, sleeve: float) -> bool:
        """True when the sleeve is at the end of its stroke in the commanded direction and
        the catheter still has travel left that way."""
        cfg = self.config
        tol = cfg.arrival_tolerance
        if v_cmd > 0.0:
            return sleeve >= cfg.stroke_max - tol and self._position < cfg.position_max - tol
        if v_cmd < 0.0:
            return sleeve <= cfg.stroke_min + tol and self._position > cfg.position_min + tol
        return False

    def _return_target(self) -> float:
        return self.config.stroke_min if self._direction > 0 else self.config.stroke_max

    def _advance(self, v_cmd: float, fb: SleeveFeedback) -> None:
        cfg = self.config
        closed, opened = GripperState.CLOSED, GripperState.OPEN
        phase = self._phase
        if phase == Phase.DRIVE:
            if fb.moving != closed or fb.fixed != opened:
                # The device disagrees with the drive phase: hold with both, then resume.
                self._set_phase(Phase.CLOSE_MOVING)
            elif self._needs_relay(v_cmd, fb.sleeve_position):
                self._set_phase(Phase.CLOSE_FIXED)
        elif phase == Phase.CLOSE_FIXED:
            if fb.fixed == closed and fb.moving == closed:
                self._set_phase(Phase.OPEN_MOVING)
        elif phase == Phase.OPEN_MOVING:
            if fb.fixed != closed:
                self._set_phase(Phase.CLOSE_FIXED)
            elif fb.moving == opened:
                self._set_phase(Phase.RETURN)
        elif phase == Phase.RETURN:
            if fb.fixed != closed or fb.moving != opened:
                self._set_phase(Phase.CLOSE_FIXED)
            elif abs(fb.sleeve_position - self._return_target()) <= cfg.arrival_tolerance:
                self._set_phase(Phase.CLOSE_MOVING)
        elif phase == Phase.CLOSE_MOVING:
            if fb.moving == closed and fb.fixed == closed:
                self._set_phase(Phase.OPEN_FIXED)
        elif phase == Phase.OPEN_FIXED:
            if fb.moving != closed:
                self._set_phase(Phase.CLOSE_MOVING)
            elif fb.fixed == opened:
                self._set_phase(Phase.DRIVE)

    def _command(self, v_cmd: float, fb: SleeveFeedback, dt: float) -> ActuatorCommand:
        cfg = self.config
        closed = GripperState.CLOSED
        phase = self._phase
        velocity = 0.0
        if phase == Phase.DRIVE:
            moving_close, fixed_close = True, False
            velocity = self._limit_drive(v_cmd, fb.sleeve_position, dt)
        elif phase == Phase.CLOSE_FIXED:
            moving_close, fixed_close = True, True
        elif phase == Phase.OPEN_MOVING:
            # Only open the moving gripper while the fixed one is measured closed.
            moving_close, fixed_close = fb.fixed != closed, True
        elif phase == Phase.RETURN:
            moving_close, fixed_close = False, True
            if not self._estop:
                error = self._return_target() - fb.sleeve_position
                velocity = math.copysign(min(cfg.return_speed, abs(error) / dt), error)
        elif phase == Phase.CLOSE_MOVING:
            moving_close, fixed_close = True, True
        else:  # OPEN_FIXED: only open the fixed gripper while the moving one is measured closed.
            moving_close, fixed_close = True, fb.moving != closed
        return ActuatorCommand(velocity, moving_close, fixed_close)

    def _limit_drive(self, v_cmd: float, sleeve: float, dt: float) -> float:
        cfg = self.config
        if v_cmd > 0.0:
            room = min(cfg.stroke_max - sleeve, cfg.position_max - self._position)
            return max(0.0, min(v_cmd, room / dt))
        if v_cmd < 0.0:
            room = min(sleeve - cfg.stroke_min, self._position - cfg.position_min)
            return min(0.0, max(v_cmd, -room / dt))
        return 0.0

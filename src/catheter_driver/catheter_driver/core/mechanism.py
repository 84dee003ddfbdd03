"""A kinematic model of the sleeve driver mechanism (the plant the relay controller drives).

Used by the simulated CAN driver (:mod:`catheter_driver.hw.sim_driver`) and by the property
tests. It is deliberately *not* protected by the host's speed cap: the sleeve follows whatever
velocity it is told up to the motor limit, and the catheter moves with the sleeve whenever the
moving gripper is closed, so the tests measure what the controller really commands.

Model:

* each gripper is a valve plus a timed transition: commanding "close" on an open (or opening)
  gripper makes it ``CLOSING`` for ``gripper_close_time`` then ``CLOSED``; "open" likewise with
  ``gripper_open_time``. Only ``CLOSED`` holds the catheter.
* device interlock: the sleeve only moves when both grippers are steady (open or closed) and
  exactly one is closed; otherwise it stays still and ``interlock`` is raised.
* the sleeve stops at its end stops; the catheter moves with the sleeve while the moving gripper
  is closed.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from catheter_driver.core.relay import ActuatorCommand, GripperState, RelayConfig, SleeveFeedback


@dataclass
class _Gripper:
    close_time: float
    open_time: float
    state: GripperState = GripperState.OPEN
    remaining: float = 0.0

    def command(self, close: bool) -> None:
        if close and self.state in (GripperState.OPEN, GripperState.OPENING):
            self.state, self.remaining = GripperState.CLOSING, self.close_time
        elif not close and self.state in (GripperState.CLOSED, GripperState.CLOSING):
            self.state, self.remaining = GripperState.OPENING, self.open_time

    def advance(self, dt: float) -> None:
        if self.state in (GripperState.CLOSING, GripperState.OPENING):
            self.remaining -= dt
            if self.remaining <= 0.0:
                self.remaining = 0.0
                self.state = (GripperState.CLOSED if self.state == GripperState.CLOSING
                              else GripperState.OPEN)


class SleeveMechanism:
    """The simulated sleeve, grippers and catheter.

    Attributes:
        catheter_position: true catheter insertion, m.
        catheter_velocity: true catheter velocity over the last step, m/s.
        min_held: smallest number of closed grippers at any instant of the last step.
        interlock: True if the last step's sleeve command was refused by the interlock.
        stalled: fault injection; the sleeve does not move while True.
    """

    def __init__(self, config: RelayConfig, *, motor_speed_limit: float = 0.05,
                 sleeve_position: float | None = None, catheter_position: float = 0.0) -> None:
        """Create the mechanism homed: sleeve at ``stroke_min``, fixed gripper holding.

        Args:
            config: geometry and gripper timings.
            motor_speed_limit: the sleeve motor's own speed limit, m/s.
            sleeve_position: initial sleeve position (default ``stroke_min``), m.
            catheter_position: initial catheter insertion, m.
        """
        if not (math.isfinite(motor_speed_limit) and motor_speed_limit > 0.0):
            raise ValueError(
                f'motor_speed_limit must be a finite number > 0, found {motor_speed_limit!r}')
        self.config = config
        self.motor_speed_limit = motor_speed_limit
        self.sleeve_position = config.stroke_min if sleeve_position is None else sleeve_position
        self.sleeve_velocity = 0.0
        self.catheter_position = catheter_position
        self.catheter_velocity = 0.0
        self.moving = _Gripper(config.gripper_close_time, config.gripper_open_time)
        self.fixed = _Gripper(config.gripper_close_time, config.gripper_open_time,
                              GripperState.CLOSED)
        self.min_held = 1
        self.interlock = False
        self.stalled = False

    def feedback(self) -> SleeveFeedback:
        """The state a real device would report."""
        return SleeveFeedback(self.sleeve_position, self.moving.state, self.fixed.state)

    def held(self) -> int:
        """Number of grippers closed on the catheter now."""
        return ((self.moving.state == GripperState.CLOSED)
                + (self.fixed.state == GripperState.CLOSED))

    def step(self, command: ActuatorCommand, dt: float) -> None:
        """Apply ``command`` for ``dt`` seconds."""
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f'dt must be a finite number > 0, found {dt!r}')
        if not math.isfinite(command.sleeve_velocity):
            raise ValueError(
                f'expected a finite sleeve velocity, found {command.sleeve_velocity!r}')
        # Valves switch at the start of the interval; an opening gripper stops holding at once,
        # a closing one only holds once its transition completes, so the minimum number of
        # holding grippers over the interval is the count right after the switch.
        self.moving.command(command.moving_close)
        self.fixed.command(command.fixed_close)
        self.min_held = self.held()
        steady = {GripperState.OPEN, GripperState.CLOSED}
        may_move = (self.moving.state in steady and self.fixed.state in steady
                    and self.held() == 1)
        velocity = max(-self.motor_speed_limit,
                       min(self.motor_speed_limit, command.sleeve_velocity))
        self.interlock = velocity != 0.0 and not may_move
        if not may_move or self.stalled:
            velocity = 0.0
        start = self.sleeve_position
        target = start + velocity * dt
        target = max(self.config.stroke_min, min(self.config.stroke_max, target))
        self.sleeve_position = target
        self.sleeve_velocity = (target - start) / dt
        if self.moving.state == GripperState.CLOSED:
            self.catheter_position += target - start
            self.catheter_velocity = (target - start) / dt
        else:
            self.catheter_velocity = 0.0
        self.moving.advance(dt)
        self.fixed.advance(dt)

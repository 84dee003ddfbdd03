"""Command supervision for the PAM bank: validation, caps, rate limit, watchdog, e-stop, backoff.

Pure logic with an explicit clock (``now`` in seconds, any monotonic origin) so every rule is
unit tested without ROS or CAN. The node feeds it commands and ticks; whatever it returns is
within ``[min_pressure_pa, max_pressure_pa]`` whatever came in.

Behaviour:

- a command is rejected (``CommandRejectedError``, nothing changes) when it is NaN/inf, over the
  bend cap, or while the e-stop is engaged;
- on each tick the sent setpoints move towards the target by at most
  ``max_pressure_rate_pa_s * dt`` per chamber (slew limit);
- no command for ``command_timeout_s`` (or none yet): the watchdog vents, i.e. every chamber goes
  to ``vent_pressure_pa`` at once (venting is the safe direction, so it is not slew limited),
  and stays there until a fresh command arrives;
- e-stop engaged: vent at once, mode ``VENT`` (the regulators open their exhaust), commands
  refused; released: still vented until a fresh command (never jumps back to the old target).
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pam_controller.core.bending_model import BendingModel
from pam_controller.errors import CommandRejectedError

FloatArray = NDArray[np.float64]


class BankMode(enum.IntEnum):
    """Mode the host requests from the regulator bank (CAN ``PAM_HOST_HEARTBEAT.MODE``)."""

    IDLE = 0
    """Regulators vented, setpoints ignored."""
    RUN = 1
    """Regulators track the setpoints."""
    VENT = 2
    """Emergency vent: exhaust open, setpoints ignored (e-stop)."""
    CLEAR_FAULTS = 3
    """Clear latched faults, then behave as IDLE."""


class Phase(enum.Enum):
    """Why the supervisor sends what it sends."""

    WAITING = 'waiting'
    """No command received yet: vented."""
    ACTIVE = 'active'
    """Tracking the last command."""
    STALE = 'stale'
    """Watchdog expired: vented."""
    ESTOP = 'estop'
    """E-stop engaged: vented, commands refused."""


@dataclass(frozen=True)
class SupervisorConfig:
    """Watchdog, rate limit and vent settings."""

    command_timeout_s: float = 0.5
    """A command older than this vents the chambers (watchdog), s. In (0, 60]."""

    max_pressure_rate_pa_s: float = 600e3
    """Slew limit of each chamber's setpoint, Pa/s (0 -> 300 kPa in 0.5 s; estimate of what
    the PAMs tolerate). In (0, 1e7]."""

    vent_pressure_pa: float = 0.0
    """Safe pressure every chamber goes to on watchdog or e-stop, Pa gauge. Must lie within
    the model's pressure limits."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.command_timeout_s) and 0.0 < self.command_timeout_s <= 60.0):
            raise ValueError(
                f'command_timeout_s must be in (0, 60], found {self.command_timeout_s}')
        if not (math.isfinite(self.max_pressure_rate_pa_s)
                and 0.0 < self.max_pressure_rate_pa_s <= 1e7):
            raise ValueError(
                f'max_pressure_rate_pa_s must be in (0, 1e7], found {self.max_pressure_rate_pa_s}')
        if not math.isfinite(self.vent_pressure_pa) or self.vent_pressure_pa < 0.0:
            raise ValueError(
                f'vent_pressure_pa must be a finite number >= 0, found {self.vent_pressure_pa}')


@dataclass(frozen=True)
class TickOutput:
    """What to send to the bank this tick."""

    setpoints_pa: FloatArray
    """Four chamber setpoints, Pa, within the pressure limits."""
    mode: BankMode
    """Mode for the host heartbeat."""
    phase: Phase
    """Supervisor phase (for diagnostics)."""


class PamSupervisor:
    """Turns bend commands into safe, rate-limited pressure setpoints.

    Args:
        model: the bending model (its config carries the pressure and bend caps).
        config: watchdog / rate / vent settings.
        now: clock value at construction, s.

    Raises:
        ValueError: ``vent_pressure_pa`` outside the model's pressure limits.
    """

    def __init__(self, model: BendingModel, config: SupervisorConfig, now: float) -> None:
        mc = model.config
        if not (mc.min_pressure_pa <= config.vent_pressure_pa <= mc.max_pressure_pa):
            raise ValueError(
                f'vent_pressure_pa must be in [min_pressure_pa={mc.min_pressure_pa}, '
                f'max_pressure_pa={mc.max_pressure_pa}], found {config.vent_pressure_pa}')
        self.model = model
        self.config = config
        self._vent = np.full(4, config.vent_pressure_pa)
        self._setpoints = self._vent.copy()
        self._target = self._vent.copy()
        self._last_command: float | None = None
        self._last_tick = now
        self._phase = Phase.WAITING
        self.rejected_count = 0
        self.last_rejection = ''
        self.model.note_sent_pressures(self._vent)

    @property
    def phase(self) -> Phase:
        """Current phase."""
        return self._phase

    @property
    def estop_engaged(self) -> bool:
        """True while the e-stop holds."""
        return self._phase is Phase.ESTOP

    @property
    def target_pa(self) -> FloatArray:
        """Pressures the last accepted command asked for (or the vent pressures)."""
        return self._target.copy()

    @property
    def setpoints_pa(self) -> FloatArray:
        """Setpoints sent on the last tick."""
        return self._setpoints.copy()

    def command(self, bend: ArrayLike, now: float) -> FloatArray:
        """Accept a bend command ``[alpha, gamma]`` (rad) at time ``now``.

        Returns:
            The target pressures (Pa, 4) the setpoints now ramp to.

        Raises:
            CommandRejectedError: e-stop engaged, NaN/inf, or over the bend cap; nothing changes.
        """
        try:
            if self._phase is Phase.ESTOP:
                raise CommandRejectedError('expected no command while the e-stop is engaged, '
                                      'found one (release pam_controller/estop first)')
            target = self.model.pressures_for_bend(bend)
        except CommandRejectedError as err:
            self.note_rejection(err)
            raise
        self._target = target
        self._last_command = now
        self._phase = Phase.ACTIVE
        return target.copy()

    def note_rejection(self, err: Exception) -> None:
        """Count a command refused before it reached :meth:`command` (e.g. a bad message)."""
        self.rejected_count += 1
        self.last_rejection = str(err)

    def engage_estop(self) -> None:
        """Vent now and refuse commands until :meth:`release_estop`."""
        self._enter_vent(Phase.ESTOP)

    def release_estop(self) -> None:
        """Allow commands again; the chambers stay vented until a fresh command."""
        if self._phase is Phase.ESTOP:
            self._phase = Phase.WAITING
            self._last_command = None

    def _enter_vent(self, phase: Phase) -> None:
        self._phase = phase
        self._target = self._vent.copy()
        self._setpoints = self._vent.copy()
        self.model.note_sent_pressures(self._vent)

    def tick(self, now: float) -> TickOutput:
        """Advance to ``now``: watchdog, slew limit; returns what to send."""
        dt = max(0.0, now - self._last_tick)
        self._last_tick = now
        if (self._phase is Phase.ACTIVE and self._last_command is not None
                and now - self._last_command > self.config.command_timeout_s):
            self._enter_vent(Phase.STALE)
        if self._phase is Phase.ACTIVE:
            step = self.config.max_pressure_rate_pa_s * dt
            delta = (self._target - self._setpoints).clip(-step, step)
            self._setpoints = self.model.clip_pressures(self._setpoints + delta)
            mode = BankMode.RUN
        elif self._phase is Phase.ESTOP:
            mode = BankMode.VENT
        else:
            mode = BankMode.RUN if self.config.vent_pressure_pa > 0.0 else BankMode.IDLE
        return TickOutput(self._setpoints.copy(), mode, self._phase)


class Backoff:
    """Exponential retry schedule: ``initial_s, 2*initial_s, ... <= max_s``; reset on success.

    Args:
        initial_s: first delay, s (> 0).
        max_s: largest delay, s (>= initial_s).
    """

    def __init__(self, initial_s: float, max_s: float) -> None:
        if not (math.isfinite(initial_s) and initial_s > 0.0):
            raise ValueError(f'initial_s must be a finite number > 0, found {initial_s}')
        if not (math.isfinite(max_s) and max_s >= initial_s):
            raise ValueError(f'max_s must be >= initial_s={initial_s}, found {max_s}')
        self.initial_s = initial_s
        self.max_s = max_s
        self.attempts = 0
        self._next: float | None = None

    def due(self, now: float) -> bool:
        """True when a retry should be made now (the first failure retries at once)."""
        return self._next is None or now >= self._next

    def failed(self, now: float) -> float:
        """Record a failed attempt at ``now``; returns the delay until the next one."""
        delay = min(self.max_s, self.initial_s * 2.0 ** self.attempts)
        self.attempts += 1
        self._next = now + delay
        return delay

    def succeeded(self) -> None:
        """Back to the initial delay."""
        self.attempts = 0
        self._next = None

    def seconds_to_next(self, now: float) -> float:
        """Time until the next retry (0 when due)."""
        return 0.0 if self._next is None else max(0.0, self._next - now)

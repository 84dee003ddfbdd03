"""Joystick teleoperation: Joy axes/buttons -> insertion velocity and bend commands.

Deadman convention of ``teleop_twist_joy``: commands are produced only while the enable button
is held; on release (or when Joy messages stop for ``joy_timeout`` s, or a malformed Joy arrives
while enabled) exactly one stop (insertion velocity 0) is produced, then nothing until the
button is held again.

Bend modes:

* ``rate`` (default): the bend axes command the bend *rate*, ``scale_bend`` rad/s at full
  deflection; the setpoint is integrated between Joy messages (step capped at ``max_dt``) and
  kept while the deadman is released, so the catheter holds its bend. It starts at 0.
* ``position``: the bend axes command the bend angle directly, ``scale_bend`` rad at full
  deflection (the stick springs back, so releasing the stick straightens the catheter).

The total bend ``hypot(alpha, gamma)`` is capped to ``max_bend`` (pi/2) by scaling both angles
(the bend direction is kept), which is the cap the PAM controller enforces, and the insertion
speed to ``max_insertion_speed`` (5 mm/s), whatever the axes and scales.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math

from catheter_driver.exceptions import CommandError

MAX_INSERTION_SPEED = 0.005
MAX_BEND = math.pi / 2


@dataclass(frozen=True)
class TeleopConfig:
    """Mapping from the gamepad to the catheter (defaults suit an Xbox-style pad in SDL)."""

    enable_button: int = 4
    """Deadman button index (held = enabled); 4 = left shoulder on most pads."""
    axis_insertion: int = 1
    """Axis index for insertion (left stick vertical; up = +1 = insert)."""
    scale_insertion: float = 0.005
    """Insertion velocity at full deflection, m/s (|scale| <= 0.005; negative inverts)."""
    axis_bend_alpha: int = 4
    """Axis index for the bend about the tip x axis (right stick vertical)."""
    axis_bend_gamma: int = 3
    """Axis index for the bend about the tip z axis (right stick horizontal)."""
    scale_bend: float = 0.5
    """Rate mode: rad/s at full deflection; position mode: rad at full deflection."""
    bend_mode: str = 'rate'
    """'rate' or 'position' (see the module docstring)."""
    max_insertion_speed: float = MAX_INSERTION_SPEED
    """Cap on |insertion velocity|, m/s (<= 0.005)."""
    max_bend: float = MAX_BEND
    """Cap on |bend angle|, rad (<= pi/2)."""
    max_dt: float = 0.1
    """Largest integration step in rate mode, s."""
    joy_timeout: float = 0.5
    """Enabled and no Joy for this long: send one stop and go quiet, s."""

    def __post_init__(self) -> None:
        for name in ('enable_button', 'axis_insertion', 'axis_bend_alpha', 'axis_bend_gamma'):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 0):
                raise ValueError(f'{name} must be an index >= 0, found {value!r}')
        if len({self.axis_insertion, self.axis_bend_alpha, self.axis_bend_gamma}) != 3:
            raise ValueError(
                f'axis_insertion, axis_bend_alpha and axis_bend_gamma must differ, found '
                f'{self.axis_insertion}, {self.axis_bend_alpha}, {self.axis_bend_gamma}')
        if not (math.isfinite(self.max_insertion_speed)
                and 0.0 < self.max_insertion_speed <= MAX_INSERTION_SPEED):
            raise ValueError(f'max_insertion_speed must be in (0, {MAX_INSERTION_SPEED}] m/s, '
                             f'found {self.max_insertion_speed!r}')
        if not (math.isfinite(self.max_bend) and 0.0 < self.max_bend <= MAX_BEND):
            raise ValueError(f'max_bend must be in (0, pi/2] rad, found {self.max_bend!r}')
        if not (math.isfinite(self.scale_insertion)
                and 0.0 < abs(self.scale_insertion) <= self.max_insertion_speed):
            raise ValueError(f'scale_insertion must satisfy 0 < |scale_insertion| <= '
                             f'{self.max_insertion_speed} m/s, found {self.scale_insertion!r}')
        if self.bend_mode not in ('rate', 'position'):
            raise ValueError(f"bend_mode must be 'rate' or 'position', found {self.bend_mode!r}")
        limit = self.max_bend if self.bend_mode == 'position' else 10.0
        if not (math.isfinite(self.scale_bend) and 0.0 < abs(self.scale_bend) <= limit):
            raise ValueError(f'scale_bend must satisfy 0 < |scale_bend| <= {limit:.4g} in '
                             f'{self.bend_mode} mode, found {self.scale_bend!r}')
        for name in ('max_dt', 'joy_timeout'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'{name} must be a finite number > 0 s, found {value!r}')


@dataclass(frozen=True)
class TeleopOutput:
    """What to publish after one input; None fields mean "publish nothing"."""

    insertion_velocity: float | None = None
    """Insertion velocity command, m/s."""
    bend: tuple[float, float] | None = None
    """(bend_alpha, bend_gamma) setpoint, rad."""


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


class Teleop:
    """The deadman state machine."""

    def __init__(self, config: TeleopConfig) -> None:
        """Start disabled with a straight bend setpoint."""
        self.config = config
        self._enabled = False
        self._bend = (0.0, 0.0)
        self._last_joy: float | None = None

    @property
    def enabled(self) -> bool:
        """True while the deadman is held (and Joy is fresh)."""
        return self._enabled

    @property
    def bend(self) -> tuple[float, float]:
        """The current bend setpoint, rad."""
        return self._bend

    def validate(self, axes: Sequence[float], buttons: Sequence[int]) -> None:
        """Check a Joy message has the configured indices and finite axes in [-1, 1].

        Raises:
            CommandError: naming what is wrong.
        """
        cfg = self.config
        need_axes = max(cfg.axis_insertion, cfg.axis_bend_alpha, cfg.axis_bend_gamma) + 1
        if len(axes) < need_axes:
            raise CommandError(f'expected at least {need_axes} Joy axes, found {len(axes)}')
        if len(buttons) <= cfg.enable_button:
            raise CommandError(
                f'expected at least {cfg.enable_button + 1} Joy buttons, found {len(buttons)}')
        for i in (cfg.axis_insertion, cfg.axis_bend_alpha, cfg.axis_bend_gamma):
            if not (math.isfinite(axes[i]) and -1.0 <= axes[i] <= 1.0):
                raise CommandError(f'expected Joy axis {i} finite in [-1, 1], found {axes[i]!r}')

    def on_joy(self, axes: Sequence[float], buttons: Sequence[int], now: float) -> TeleopOutput:
        """Process one Joy message received at ``now`` (s, monotonic).

        Raises:
            CommandError: for a malformed message; the caller should then publish
                :meth:`on_invalid`'s output.
        """
        self.validate(axes, buttons)
        cfg = self.config
        previous = self._last_joy
        self._last_joy = now
        if not buttons[cfg.enable_button]:
            return self._release()
        # No integration on the message that enables: the time since the last Joy says
        # nothing about how long the stick was held.
        dt = 0.0 if previous is None or not self._enabled else min(
            max(now - previous, 0.0), cfg.max_dt)
        self._enabled = True
        velocity = _clamp(axes[cfg.axis_insertion] * cfg.scale_insertion,
                          cfg.max_insertion_speed)
        a, g = axes[cfg.axis_bend_alpha], axes[cfg.axis_bend_gamma]
        if cfg.bend_mode == 'position':
            bend = (a * cfg.scale_bend, g * cfg.scale_bend)
        else:
            step = cfg.scale_bend * dt
            bend = (self._bend[0] + a * step, self._bend[1] + g * step)
        self._bend = _cap_total_bend(bend, cfg.max_bend)
        return TeleopOutput(velocity, self._bend)

    def on_invalid(self) -> TeleopOutput:
        """A malformed Joy arrived: fail safe like a release."""
        return self._release()

    def on_tick(self, now: float) -> TeleopOutput:
        """Call periodically: enabled but Joy stale for ``joy_timeout`` -> one stop."""
        if (self._enabled and self._last_joy is not None
                and now - self._last_joy > self.config.joy_timeout):
            return self._release()
        return TeleopOutput()

    def _release(self) -> TeleopOutput:
        if not self._enabled:
            return TeleopOutput()
        self._enabled = False
        return TeleopOutput(insertion_velocity=0.0)


def _cap_total_bend(bend: tuple[float, float], max_bend: float) -> tuple[float, float]:
    """Scale ``(alpha, gamma)`` so that ``hypot(alpha, gamma) <= max_bend`` (direction kept).

    Clamping each angle alone would let the diagonal reach ``sqrt(2) * max_bend``, which the
    PAM controller rejects (it caps the total bend).
    """
    total = math.hypot(bend[0], bend[1])
    if total <= max_bend:
        return bend
    k = max_bend / total
    return (bend[0] * k, bend[1] * k)

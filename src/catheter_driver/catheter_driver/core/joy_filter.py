"""The ROS ``joy`` package's conventions, as pure logic (no SDL, no rclpy).

Follows ``joy_node`` of ros-drivers/joystick_drivers (ROS 2, SDL2 back end):

* **axes**: an SDL axis (int16, -32768..32767) maps to [-1, 1]. -32768 counts as -32767; values
  within ``deadzone * 32767`` of centre read 0, the rest is shifted by the deadzone and rescaled
  so that full deflection still reads +-1 ("smooth" deadzone); the sign is inverted, because SDL
  reports forward/left as negative and ROS wants them positive.
* **hats** are appended after the axes, two per hat: left/right (left = +1), up/down (up = +1).
* **buttons** are 0/1; with ``sticky_buttons`` each press toggles the reported value.
* **publishing**: a button change publishes at once; an axis change publishes at most
  ``coalesce_interval`` later (changes in between are merged); with ``autorepeat_rate`` > 0 the
  last state is republished when nothing was published for ``1 / autorepeat_rate`` s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math

AXIS_MAX = 32767.0
TIME_EPS = 1e-9
"""Slack on timing comparisons, s (polling times are floats)."""


@dataclass(frozen=True)
class JoyConfig:
    """Parameters of the joy conventions (names as in ROS ``joy_node``)."""

    deadzone: float = 0.05
    """Fraction of the axis range around centre that reads 0, in [0, 1)."""
    autorepeat_rate: float = 20.0
    """Republish rate of an unchanged state, Hz, in [0, 1000]; 0 disables."""
    coalesce_interval: float = 0.001
    """Axis changes within this time are merged into one message, s (>= 0)."""
    sticky_buttons: bool = False
    """Each press toggles the reported button value."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.deadzone) and 0.0 <= self.deadzone < 1.0):
            raise ValueError(f'deadzone must be in [0.0, 1.0), found {self.deadzone!r}')
        if not (math.isfinite(self.autorepeat_rate) and 0.0 <= self.autorepeat_rate <= 1000.0):
            raise ValueError(
                f'autorepeat_rate must be in [0.0, 1000.0] Hz, found {self.autorepeat_rate!r}')
        if not (math.isfinite(self.coalesce_interval) and self.coalesce_interval >= 0.0):
            raise ValueError(
                f'coalesce_interval must be >= 0 s, found {self.coalesce_interval!r}')


def axis_to_ros(raw: int, deadzone: float) -> float:
    """Convert an SDL axis value to the ROS joy convention (see the module docstring)."""
    value = max(-AXIS_MAX, min(AXIS_MAX, float(raw)))
    unscaled_deadzone = AXIS_MAX * deadzone
    if value > unscaled_deadzone:
        value -= unscaled_deadzone
    elif value < -unscaled_deadzone:
        value += unscaled_deadzone
    else:
        return 0.0
    return -value / (AXIS_MAX - unscaled_deadzone)


def hat_to_ros(x: int, y: int) -> tuple[float, float]:
    """Convert a hat (SDL/pygame: x = +1 right, y = +1 up) to the joy axis pair
    (left/right with left = +1, up/down with up = +1)."""
    return float(-x), float(y)


@dataclass(frozen=True)
class JoySample:
    """One reading of a gamepad in device units."""

    axes: tuple[int, ...]
    """Raw SDL axis values, -32768..32767."""
    buttons: tuple[bool, ...]
    """Pressed state of each button."""
    hats: tuple[tuple[int, int], ...] = ()
    """(x, y) of each hat, each -1, 0 or 1 (x = +1 right, y = +1 up)."""


@dataclass(frozen=True)
class JoyOutput:
    """The content of one sensor_msgs/Joy message."""

    axes: tuple[float, ...]
    buttons: tuple[int, ...]


class JoyFilter:
    """Decides, poll by poll, what to publish. Feed every reading to :meth:`update`."""

    def __init__(self, config: JoyConfig) -> None:
        """Create the filter; it has no device until the first :meth:`update`."""
        self.config = config
        self._axes: tuple[float, ...] | None = None
        self._pressed: tuple[bool, ...] = ()
        self._buttons: tuple[int, ...] = ()
        self._pending_since: float | None = None
        self._last_publish = -math.inf

    def reset(self) -> None:
        """Forget the device (call when it is unplugged or replaced)."""
        self._axes = None
        self._pressed = ()
        self._buttons = ()
        self._pending_since = None

    def update(self, sample: JoySample, now: float) -> JoyOutput | None:
        """Take a reading at time ``now`` (s, monotonic) and return a message to publish, or
        None."""
        cfg = self.config
        axes = tuple(axis_to_ros(a, cfg.deadzone) for a in sample.axes)
        axes += tuple(v for x, y in sample.hats for v in hat_to_ros(x, y))
        first = self._axes is None or len(axes) != len(self._axes) or (
            len(sample.buttons) != len(self._pressed))
        buttons = self._next_buttons(sample.buttons, first)
        publish = first or buttons != self._buttons
        if not first and axes != self._axes and self._pending_since is None:
            self._pending_since = now
        self._axes, self._buttons = axes, buttons
        self._pressed = tuple(bool(b) for b in sample.buttons)
        if (self._pending_since is not None
                and now - self._pending_since >= cfg.coalesce_interval - TIME_EPS):
            publish = True
        if (cfg.autorepeat_rate > 0.0
                and now - self._last_publish >= 1.0 / cfg.autorepeat_rate - TIME_EPS):
            publish = True
        if not publish:
            return None
        self._pending_since = None
        self._last_publish = now
        return JoyOutput(axes, buttons)

    def _next_buttons(self, pressed: Sequence[bool], first: bool) -> tuple[int, ...]:
        if not self.config.sticky_buttons:
            return tuple(int(bool(b)) for b in pressed)
        if first:
            return tuple(0 for _ in pressed)
        return tuple(
            (1 - held) if (now and not before) else held
            for held, now, before in zip(self._buttons, pressed, self._pressed, strict=True))

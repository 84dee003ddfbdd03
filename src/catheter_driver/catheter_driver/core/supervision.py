"""Command watchdog and reconnect backoff shared by the driver node (pure logic)."""

from __future__ import annotations

from dataclasses import dataclass
import math


@dataclass(frozen=True)
class SupervisionConfig:
    """Rates and time limits of the driver node."""

    control_rate_hz: float = 50.0
    """Rate of the relay control loop and of ``catheter/insertion_state``, Hz."""
    command_timeout: float = 0.2
    """The insertion velocity falls to 0 when no valid command came for this long, s."""
    status_timeout: float = 0.25
    """The device counts as disconnected when no status came for this long, s."""
    backoff_initial: float = 0.5
    """First delay before reopening a lost link, s."""
    backoff_max: float = 8.0
    """Largest delay between reopen attempts (the delay doubles up to this), s."""
    diagnostics_period: float = 0.5
    """Period of ``/diagnostics``, s."""

    def __post_init__(self) -> None:
        for name in ('control_rate_hz', 'command_timeout', 'status_timeout', 'backoff_initial',
                     'backoff_max', 'diagnostics_period'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'{name} must be a finite number > 0, found {value!r}')
        if self.control_rate_hz > 1000.0:
            raise ValueError(
                f'control_rate_hz must be <= 1000 Hz, found {self.control_rate_hz!r}')
        if self.command_timeout < 2.0 / self.control_rate_hz:
            raise ValueError(
                f'command_timeout must be >= two control periods '
                f'({2.0 / self.control_rate_hz:.4g} s), found {self.command_timeout!r}')
        if self.backoff_max < self.backoff_initial:
            raise ValueError(f'backoff_max must be >= backoff_initial ({self.backoff_initial}),'
                             f' found {self.backoff_max!r}')


class Backoff:
    """Exponential backoff: ``initial``, ``2 * initial``, ... capped at ``maximum``."""

    def __init__(self, initial: float, maximum: float) -> None:
        """Create a reset backoff."""
        self.initial = initial
        self.maximum = maximum
        self.attempts = 0

    def next_delay(self) -> float:
        """Delay before the next attempt; each call doubles the following one."""
        delay = min(self.maximum, self.initial * 2.0 ** self.attempts)
        self.attempts += 1
        return delay

    def reset(self) -> None:
        """Back to ``initial`` (after a success)."""
        self.attempts = 0


class Watchdog:
    """True while fed within ``timeout`` s."""

    def __init__(self, timeout: float) -> None:
        """Create a starved watchdog."""
        self.timeout = timeout
        self._last: float | None = None

    def feed(self, now: float) -> None:
        """Record a valid input at ``now``."""
        self._last = now

    def starve(self) -> None:
        """Forget the last input (the watchdog reads stale until fed again)."""
        self._last = None

    def fresh(self, now: float) -> bool:
        """True if fed within the timeout."""
        return self._last is not None and now - self._last <= self.timeout

    def age(self, now: float) -> float:
        """Seconds since the last feed (inf if never fed)."""
        return math.inf if self._last is None else now - self._last

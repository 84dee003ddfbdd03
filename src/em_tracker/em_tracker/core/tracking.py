"""Tracker bookkeeping: frame accounting, port status decoding, diagnostics state.

Pure logic (no rclpy): the node feeds it device readings and asks it for the diagnostic level
and key/values to publish.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import enum

# Port status bits of the Combined API (same values as em_tracker.hw.combined_api).
PORT_OCCUPIED = 0x0001
PORT_INITIALIZED = 0x0010
PORT_ENABLED = 0x0020
PORT_OUT_OF_VOLUME = 0x0040
PORT_PARTIALLY_IN_VOLUME = 0x0080
PORT_BROKEN_COIL = 0x0100


class Level(enum.IntEnum):
    """Diagnostic levels (same numbers as ``diagnostic_msgs/DiagnosticStatus``)."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


class LinkState(enum.Enum):
    """State of the link to the Measurement System."""

    CONNECTING = 'connecting'
    TRACKING = 'tracking'
    DISCONNECTED = 'disconnected'
    STOPPED = 'stopped'


@dataclass(frozen=True)
class PortFlags:
    """Decoded port status word."""

    occupied: bool
    initialized: bool
    enabled: bool
    out_of_volume: bool
    partially_out_of_volume: bool
    broken_coil: bool

    @classmethod
    def decode(cls, status: int) -> PortFlags:
        """Decode a 32-bit port status word."""
        return cls(
            occupied=bool(status & PORT_OCCUPIED),
            initialized=bool(status & PORT_INITIALIZED),
            enabled=bool(status & PORT_ENABLED),
            out_of_volume=bool(status & PORT_OUT_OF_VOLUME),
            partially_out_of_volume=bool(status & PORT_PARTIALLY_IN_VOLUME),
            broken_coil=bool(status & PORT_BROKEN_COIL),
        )

    def problems(self) -> list[str]:
        """Human-readable list of what is wrong with the port (empty if nothing)."""
        out = []
        if not self.occupied:
            out.append('port unoccupied')
        if self.broken_coil:
            out.append('sensor coil broken')
        if self.out_of_volume:
            out.append('out of volume')
        if self.partially_out_of_volume:
            out.append('partially out of volume')
        if self.occupied and not self.enabled:
            out.append('port not enabled')
        return out


class FrameCounter:
    """Counts new, repeated and dropped device frames from the 32-bit frame numbers."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.received = 0
        self.dropped = 0
        self.repeated = 0

    def reset(self) -> None:
        """Forget the last frame number (after a reconnect the device restarts counting)."""
        self.last = None

    def update(self, frame_number: int) -> bool:
        """Account for one reply; return True if it carries a new frame.

        A frame number equal to the last one is a repeat (host polled faster than the device
        produced frames); a jump of ``n > 1`` counts ``n - 1`` dropped frames; a backwards
        jump (device restarted counting) is accepted as new without counting drops.
        """
        frame_number &= 0xFFFFFFFF
        if self.last is not None:
            delta = (frame_number - self.last) & 0xFFFFFFFF
            if delta == 0:
                self.repeated += 1
                return False
            if delta < 0x80000000:
                self.dropped += delta - 1
        self.last = frame_number
        self.received += 1
        return True


@dataclass
class TrackerHealth:
    """What the diagnostics report; updated by the node's reader thread.

    Attributes:
        link: link state.
        last_error: last error message (empty if none).
        port_status: last port status word of the tracked handle.
        tool_visible: last reading had a valid transform.
        rejected: readings rejected by validation (NaN, implausible values).
        bad_replies: replies that failed (bad CRC, ERRORxx, garbage) or were stale (the last
            frame number again, 1.5 frame periods after it first came).
        reconnects: number of reconnection attempts.
        published: poses published.
        last_frame_time: monotonic time of the last new frame, s (None before the first).
        rms_error_mm: last RMS error, mm.
        system_status: last system status word.
    """

    link: LinkState = LinkState.CONNECTING
    last_error: str = ''
    port_status: int = 0
    tool_visible: bool = False
    rejected: int = 0
    bad_replies: int = 0
    reconnects: int = 0
    published: int = 0
    last_frame_time: float | None = None
    rms_error_mm: float = float('nan')
    system_status: int = 0
    frames: FrameCounter = field(default_factory=FrameCounter)

    def level(self, now: float, stale_after_s: float) -> tuple[Level, str]:
        """Diagnostic level and one-line message at time ``now``."""
        if self.link is LinkState.STOPPED:
            return Level.STALE, 'tracker stopped'
        if self.link is not LinkState.TRACKING:
            detail = f': {self.last_error}' if self.last_error else ''
            return Level.ERROR, f'{self.link.value}{detail}'
        if self.last_frame_time is None or now - self.last_frame_time > stale_after_s:
            return Level.STALE, f'no new frame for more than {stale_after_s} s'
        flags = PortFlags.decode(self.port_status)
        if flags.broken_coil:
            return Level.ERROR, 'sensor coil broken'
        problems = flags.problems()
        if not self.tool_visible:
            return Level.WARN, 'tool MISSING' + (f' ({", ".join(problems)})' if problems else '')
        if problems:
            return Level.WARN, ', '.join(problems)
        return Level.OK, 'tracking'

    def values(self) -> dict[str, str]:
        """Key/values of the diagnostic status."""
        return {
            'link': self.link.value,
            'frames_received': str(self.frames.received),
            'frames_dropped': str(self.frames.dropped),
            'frames_repeated': str(self.frames.repeated),
            'last_frame_number': '' if self.frames.last is None else str(self.frames.last),
            'poses_published': str(self.published),
            'readings_rejected': str(self.rejected),
            'bad_replies': str(self.bad_replies),
            'reconnects': str(self.reconnects),
            'port_status': f'0x{self.port_status:08X}',
            'system_status': f'0x{self.system_status:04X}',
            'tool_visible': str(self.tool_visible).lower(),
            'rms_error_mm': f'{self.rms_error_mm:.4f}',
            'last_error': self.last_error,
        }

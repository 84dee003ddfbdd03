"""Configuration of the Aurora tracker node (one frozen dataclass, validated on creation)."""

from __future__ import annotations

from dataclasses import dataclass, field
import math

from em_tracker.core.pose import Registration

SUPPORTED_BAUDS = (9600, 19200, 38400, 57600, 115200, 230400)


@dataclass(frozen=True)
class TrackerConfig:
    """Parameters of ``aurora_node`` (defaults equal ``config/aurora.yaml``)."""

    port: str = '/dev/ttyUSB0'
    """Serial device of the Aurora System Control Unit (or a simulated Aurora's pty/symlink)."""
    baud: int = 115200
    """Baud rate set with ``COMM`` after ``INIT`` (9600 keeps the power-on rate)."""
    tool_handle: int = 0
    """Port handle published as the tip (1..255); 0 takes the first enabled handle."""
    priority: str = 'D'
    """Tracking priority passed to ``PENA``: D dynamic, S static, B button box."""
    srom_files: tuple[str, ...] = ()
    """``'hh:/path/tool.rom'`` entries: SROM images written with PVWR before ``PINIT``."""
    use_bx: bool = False
    """Poll with binary ``BX:0001`` instead of text ``TX:0001``."""
    rate_hz: float = 40.0
    """Device frame rate the poller follows, Hz (the Aurora produces 40 Hz)."""
    registration: Registration = field(default_factory=Registration.identity)
    """``aurora -> phantom`` rigid transform (``T_phantom_aurora``)."""
    tool_transform: Registration = field(default_factory=Registration.identity)
    """``sensor -> tip`` rigid transform (``T_sensor_tip``, from ``pivot_calibrate``): the
    published pose is the tip's, ``T_phantom_aurora @ T_aurora_sensor @ T_sensor_tip``; tip
    frame origin at the tip, +y along the shaft towards the tip. Identity: the sensor's pose."""
    frame_id: str = 'phantom'
    """frame_id of the published poses."""
    tracker_frame_id: str = 'aurora'
    """The field generator's frame: parent of ``frame_id`` on ``/tf_static`` (the inverse of
    the registration)."""
    tip_frame_id: str = 'catheter_tip'
    """The tip frame: child of ``frame_id`` on ``/tf``, one transform per published pose."""
    publish_tf: bool = True
    """Publish ``tracker_frame_id -> frame_id`` on ``/tf_static`` and ``frame_id ->
    tip_frame_id`` on ``/tf``."""
    max_abs_position_m: float = 1.0
    """Readings with a coordinate beyond this distance from the field generator are rejected."""
    reply_timeout_s: float = 7.0
    """Longest wait for one reply before the link is declared lost, s (ndicapi waits 5 s)."""
    max_consecutive_errors: int = 5
    """Bad replies in a row (CRC, ERRORxx, garbage) before reconnecting."""
    reconnect_initial_s: float = 0.5
    """First reconnection delay, s (doubles at each failure)."""
    reconnect_max_s: float = 8.0
    """Upper bound of the reconnection delay, s."""
    stale_after_s: float = 0.5
    """Diagnostics go STALE when no new frame arrived for this long, s."""
    diagnostics_period_s: float = 1.0
    """Period of /diagnostics, s."""
    isolate_device: bool = True
    """Run ndicapi in a child process so a crash inside the C library cannot kill the node."""
    poll_mode: str = 'thread'
    """``'thread'``: a reader thread polls on the steady clock (a real rig). ``'clock'``: a
    timer of the node's clock polls synchronously at ``rate_hz`` (the lockstep simulated rig,
    where the node clock is simulated time; a slow reply then stalls the executor)."""
    link: str = 'serial'
    """``'serial'``: ndicapi on ``port`` (a rig, or a simulated Aurora's pty). ``'in_process'``:
    the simulated Aurora of this process that serves ``port`` answers each command frame in
    the caller's thread, no pty, ndicapi or serving thread (the lockstep simulated session:
    :class:`~em_tracker.hw.aurora.InProcessAurora`); TX polling only."""

    def __post_init__(self) -> None:
        if not self.port:
            raise ValueError(f'port must be a non-empty device path, found {self.port!r}')
        if self.baud not in SUPPORTED_BAUDS:
            raise ValueError(f'baud must be one of {SUPPORTED_BAUDS}, found {self.baud!r}')
        if not 0 <= self.tool_handle <= 255:
            raise ValueError(f'tool_handle must be in 0..255, found {self.tool_handle!r}')
        if self.priority not in ('D', 'S', 'B'):
            raise ValueError(f"priority must be 'D', 'S' or 'B', found {self.priority!r}")
        if self.poll_mode not in ('thread', 'clock'):
            raise ValueError(f"poll_mode must be 'thread' or 'clock', found {self.poll_mode!r}")
        if self.link not in ('serial', 'in_process'):
            raise ValueError(f"link must be 'serial' or 'in_process', found {self.link!r}")
        if self.link == 'in_process' and self.use_bx:
            raise ValueError('link in_process polls with TX: use_bx must be false, found true')
        for entry in self.srom_files:
            handle, _, path = entry.partition(':')
            if len(handle) != 2 or not path or not all(c in '0123456789abcdefABCDEF'
                                                       for c in handle):
                raise ValueError("srom_files entries must read 'hh:/path/tool.rom', "
                                 f'found {entry!r}')
        for name, low, high in (('rate_hz', 1.0, 1000.0), ('max_abs_position_m', 0.01, 10.0),
                                ('reply_timeout_s', 0.1, 60.0),
                                ('reconnect_initial_s', 0.01, 60.0),
                                ('reconnect_max_s', 0.01, 600.0),
                                ('stale_after_s', 0.01, 60.0),
                                ('diagnostics_period_s', 0.05, 60.0)):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and low <= value <= high):
                raise ValueError(f'{name} must be in [{low}, {high}], found {value!r}')
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError(f'reconnect_max_s must be >= reconnect_initial_s '
                             f'({self.reconnect_initial_s}), found {self.reconnect_max_s!r}')
        if not 1 <= self.max_consecutive_errors <= 1000:
            raise ValueError(f'max_consecutive_errors must be in [1, 1000], found '
                             f'{self.max_consecutive_errors!r}')
        frames = (self.tracker_frame_id, self.frame_id, self.tip_frame_id)
        if not all(frames) or len(set(frames)) != 3:
            raise ValueError(f'tracker_frame_id, frame_id and tip_frame_id must be non-empty and '
                             f'distinct, found {list(frames)!r}')

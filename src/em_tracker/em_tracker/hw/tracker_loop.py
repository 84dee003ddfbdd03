"""The tracker's link: connect, poll at the device frame rate, reconnect with backoff.

No rclpy here: the node gives a device (:class:`~em_tracker.hw.aurora.AuroraDevice`), a
:class:`~em_tracker.core.config.TrackerConfig` and a callback that receives each validated
:class:`~em_tracker.core.pose.TipPose` with the time its reply was complete.

The link is one state machine, :meth:`TrackerLoop.step`, driven in one of two ways:

* **a reader thread** (:meth:`TrackerLoop.start`, a real rig): every blocking serial call
  happens on it, never on the executor; times are ``time.monotonic()``;
* **a clock** (the lockstep simulated rig, ``poll_mode: clock`` of the node): the node calls
  :meth:`TrackerLoop.step` from a timer of its own clock (simulated time) at the frame rate;
  one call polls once, synchronously, and reconnect delays are in that clock's seconds. The
  result is then a function of the simulated time only.

Polling follows the device clock: after a request that returned a new frame the next poll is
due 0.95 frame periods after that request; a repeated frame number (polled too early) is
retried 2 ms later, until :data:`STALE_AFTER_PERIODS` periods after the reply that brought
that frame (the device had it then, so the next one is due within a period). A frame number
still repeated after that is stale: the device, or ndicapi after a truncated reply whose CRC
was valid, hands back a frame it already gave. It counts as a bad reply and the next poll is
a full period later, so a stuck reply never makes the loop poll faster than ``rate_hz``.
Frame-number gaps are counted as dropped frames. ``ProtocolError`` and
``DeviceError`` replies (bad CRC, garbage, ``ERRORxx``) are counted and tolerated up to
``max_consecutive_errors`` in a row; after that, or on any disconnect/timeout, the link is
closed and re-opened after ``reconnect_initial_s``, doubling up to ``reconnect_max_s``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import math
import threading
import time

from em_tracker.core.config import TrackerConfig
from em_tracker.core.errors import DeviceError, EmTrackerError, ProtocolError
from em_tracker.core.pose import convert_sample, TipPose
from em_tracker.core.tracking import LinkState, TrackerHealth
from em_tracker.hw.aurora import AuroraDevice, ToolReading

PoseCallback = Callable[[TipPose, float], None]

EARLY_RETRY_S = 0.002
"""Wait before polling again after a repeated frame number that may just be early, s."""
STALE_AFTER_PERIODS = 1.5
"""A frame number repeated this many frame periods after the reply that first brought it is
stale (the device produces a new frame every period)."""


class TrackerLoop:
    """Owns the device link and keeps :attr:`health` up to date.

    Args:
        device: the tracker (ndicapi, child process or fake).
        config: validated node configuration.
        on_pose: called with ``(pose, time)`` for each new, valid frame (from the reader thread
            in thread mode, from :meth:`step`'s caller in clock mode).
        on_warning: called with a message when the link is lost (the node logs it throttled).
    """

    def __init__(self, device: AuroraDevice, config: TrackerConfig, on_pose: PoseCallback,
                 on_warning: Callable[[str], None] = lambda message: None) -> None:
        self.device = device
        self.config = config
        self.on_pose = on_pose
        self.on_warning = on_warning
        self.health = TrackerHealth()
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='aurora_reader', daemon=True)
        self._handle: int | None = None  # tracked handle while tracking, None while not
        self._retry_at = -math.inf
        self._last_new_at = -math.inf  # when the last new frame came (reply or clock time)
        self._delay = config.reconnect_initial_s
        self._errors = 0
        self._closed = False
        self._threaded = False

    @property
    def tracking(self) -> bool:
        """Whether the link is up and polling."""
        return self._handle is not None

    # ------------------------------------------------------------------ thread mode
    def start(self) -> None:
        """Start the reader thread (thread mode)."""
        self._threaded = True
        self._thread.start()

    def stop(self, timeout_s: float | None = None) -> None:
        """Stop: the reader thread (if started) sends TSTOP, closes the port and ends; in clock
        mode the link is closed here."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)
        elif not self._closed:
            self.close()

    def close(self) -> None:
        """Stop tracking (TSTOP), release the port and mark the link stopped; idempotent."""
        self._handle = None
        self.device.close()
        self._closed = True
        with self.lock:
            self.health.link = LinkState.STOPPED

    def _run(self) -> None:
        while not self._stop.is_set():
            due = self.step(time.monotonic())
            wait = due - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                break
        self.close()

    # ------------------------------------------------------------------ the state machine
    def step(self, now: float) -> float:
        """Advance the link once at time ``now``: connect when due, else poll one reply.

        Returns:
            When the next step is due (same clock as ``now``): the reconnect time after a
            failure, 0.95 frame periods after a request that returned a new frame, 2 ms after
            a repeated frame (polled too early), a period after a stale frame, a quarter
            period after a bad reply.
        """
        if self._closed:
            return math.inf
        if self._handle is None:
            if now < self._retry_at:
                return self._retry_at
            return self._connect(now)
        return self._poll_once(self._handle, now)

    def _connect(self, now: float) -> float:
        with self.lock:
            self.health.link = LinkState.CONNECTING
        try:
            handle = self._select_handle(self.device.connect())
        except EmTrackerError as exc:
            return self._lost(exc, now)
        with self.lock:
            self.health.link = LinkState.TRACKING
            self.health.frames.reset()
        self._handle = handle
        self._delay = self.config.reconnect_initial_s
        self._errors = 0
        return now

    def _lost(self, exc: EmTrackerError, now: float) -> float:
        """The link failed: close it and schedule a reconnect with exponential backoff."""
        delay = self._delay
        with self.lock:
            self.health.last_error = f'{type(exc).__name__}: {exc}'
        self.on_warning(f'Aurora link lost: {exc}; retrying in {delay:.2f} s')
        self._handle = None
        self.device.close()
        with self.lock:
            self.health.link = LinkState.DISCONNECTED
            self.health.reconnects += 1
        self._retry_at = now + delay
        self._delay = min(2.0 * delay, self.config.reconnect_max_s)
        return self._retry_at

    def _select_handle(self, handles: Sequence[int]) -> int:
        handle = self.config.tool_handle or (handles[0] if handles else 0)
        if handle not in handles:
            raise DeviceError(f'expected tool handle {handle:02X} among the enabled handles, '
                              f'found {[f"{h:02X}" for h in handles]}')
        return handle

    def _poll_once(self, handle: int, requested: float) -> float:
        period = 1.0 / self.config.rate_hz
        try:
            reply = self.device.read()
        except (ProtocolError, DeviceError) as exc:
            self._errors += 1
            with self.lock:
                self.health.bad_replies += 1
                self.health.last_error = f'{type(exc).__name__}: {exc}'
            if self._errors >= self.config.max_consecutive_errors:
                return self._lost(exc, requested)
            return requested + 0.25 * period
        except EmTrackerError as exc:
            return self._lost(exc, requested)
        self._errors = 0
        tool = next((t for t in reply.tools if t.handle == handle), None)
        if tool is None:
            return self._lost(DeviceError(
                f'expected handle {handle:02X} in the tracking reply, found '
                f'{[f"{t.handle:02X}" for t in reply.tools]}'), requested)
        with self.lock:
            new = self.health.frames.update(tool.frame_number)
            self.health.system_status = reply.system_status
        if not new:
            return self._repeated(tool.frame_number, requested, period)
        # Thread mode anchors on the request time, not the reply time, so that a slow reply
        # cannot make the poll phase drift past the next frame (which would drop it). The
        # reply's own time stamps the pose and starts the stale-frame count; in clock mode
        # both are the caller's ``now``.
        self._last_new_at = reply.host_time if self._threaded else requested
        self._accept(tool, self._last_new_at)
        return requested + 0.95 * period

    def _repeated(self, frame_number: int, requested: float, period: float) -> float:
        """The reply carried the last frame number again: polled a little early, or stale."""
        age = requested - self._last_new_at
        if age < STALE_AFTER_PERIODS * period:
            return requested + EARLY_RETRY_S
        with self.lock:
            self.health.bad_replies += 1
            self.health.last_error = (
                f'stale reply: expected a new frame within {STALE_AFTER_PERIODS * period:.3f} '
                f's, found frame {frame_number} again after {age:.3f} s')
        return requested + period

    def _accept(self, tool: ToolReading, host_time: float) -> None:
        with self.lock:
            self.health.port_status = tool.port_status
            self.health.tool_visible = tool.visible
            self.health.last_frame_time = host_time
            if not tool.visible:
                return
            try:
                pose = convert_sample(tool.quat_wxyz, tool.position_mm, tool.error_mm,
                                      self.config.registration,
                                      max_abs_position_m=self.config.max_abs_position_m,
                                      tool_transform=self.config.tool_transform)
            except ValueError as exc:
                self.health.rejected += 1
                self.health.tool_visible = False
                self.health.last_error = f'rejected reading: {exc}'
                return
            self.health.rms_error_mm = float(tool.error_mm)
        self.on_pose(pose, host_time)

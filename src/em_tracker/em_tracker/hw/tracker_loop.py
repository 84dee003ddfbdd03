"""The tracker's reader thread: connect, poll at the device frame rate, reconnect with backoff.

No rclpy here: the node gives a device (:class:`~em_tracker.hw.aurora.AuroraDevice`), a
:class:`~em_tracker.core.config.TrackerConfig` and a callback that receives each validated
:class:`~em_tracker.core.pose.TipPose` with the monotonic time its reply was complete. Every
blocking serial call happens on this thread, never on the executor.

Polling follows the device clock: after a request that returned a new frame the next poll is
due 0.95 frame periods after that request; a repeated frame number (polled too early) is
retried 2 ms later. Frame-number gaps are counted as dropped frames. ``ProtocolError`` and
``DeviceError`` replies (bad CRC, garbage, ``ERRORxx``) are counted and tolerated up to
``max_consecutive_errors`` in a row; after that, or on any disconnect/timeout, the link is
closed and re-opened after ``reconnect_initial_s``, doubling up to ``reconnect_max_s``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import threading
import time

from em_tracker.core.config import TrackerConfig
from em_tracker.core.errors import DeviceError, EmTrackerError, ProtocolError
from em_tracker.core.pose import convert_sample, TipPose
from em_tracker.core.tracking import LinkState, TrackerHealth
from em_tracker.hw.aurora import AuroraDevice, ToolReading

PoseCallback = Callable[[TipPose, float], None]


class TrackerLoop:
    """Owns the device on a background thread and keeps :attr:`health` up to date.

    Args:
        device: the tracker (ndicapi, child process or fake).
        config: validated node configuration.
        on_pose: called from the reader thread with ``(pose, host_time)`` for each new frame.
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

    def start(self) -> None:
        """Start the reader thread."""
        self._thread.start()

    def stop(self, timeout_s: float | None = None) -> None:
        """Ask the thread to stop (TSTOP and close happen on it) and wait for it."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)

    def _run(self) -> None:
        cfg = self.config
        delay = cfg.reconnect_initial_s
        while not self._stop.is_set():
            with self.lock:
                self.health.link = LinkState.CONNECTING
            try:
                handle = self._select_handle(self.device.connect())
                with self.lock:
                    self.health.link = LinkState.TRACKING
                    self.health.frames.reset()
                delay = cfg.reconnect_initial_s
                self._poll(handle)
            except EmTrackerError as exc:
                with self.lock:
                    self.health.last_error = f'{type(exc).__name__}: {exc}'
                self.on_warning(f'Aurora link lost: {exc}; retrying in {delay:.2f} s')
            self.device.close()
            if self._stop.is_set():
                break
            with self.lock:
                self.health.link = LinkState.DISCONNECTED
                self.health.reconnects += 1
            self._stop.wait(delay)
            delay = min(2.0 * delay, cfg.reconnect_max_s)
        with self.lock:
            self.health.link = LinkState.STOPPED

    def _select_handle(self, handles: Sequence[int]) -> int:
        handle = self.config.tool_handle or (handles[0] if handles else 0)
        if handle not in handles:
            raise DeviceError(f'expected tool handle {handle:02X} among the enabled handles, '
                              f'found {[f"{h:02X}" for h in handles]}')
        return handle

    def _poll(self, handle: int) -> None:
        cfg = self.config
        period = 1.0 / cfg.rate_hz
        errors = 0
        next_poll = time.monotonic()
        while not self._stop.is_set():
            wait = next_poll - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                return
            requested = time.monotonic()
            try:
                reply = self.device.read()
            except (ProtocolError, DeviceError) as exc:
                errors += 1
                with self.lock:
                    self.health.bad_replies += 1
                    self.health.last_error = f'{type(exc).__name__}: {exc}'
                if errors >= cfg.max_consecutive_errors:
                    raise
                next_poll = time.monotonic() + 0.25 * period
                continue
            errors = 0
            tool = next((t for t in reply.tools if t.handle == handle), None)
            if tool is None:
                raise DeviceError(f'expected handle {handle:02X} in the tracking reply, found '
                                  f'{[f"{t.handle:02X}" for t in reply.tools]}')
            with self.lock:
                new = self.health.frames.update(tool.frame_number)
                self.health.system_status = reply.system_status
            if not new:
                next_poll = time.monotonic() + 0.002
                continue
            # Anchor on the request time, not the reply time, so that a slow reply cannot make
            # the poll phase drift past the next frame (which would drop it).
            next_poll = requested + 0.95 * period
            self._accept(tool, reply.host_time)

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
                                      max_abs_position_m=self.config.max_abs_position_m)
            except ValueError as exc:
                self.health.rejected += 1
                self.health.tool_visible = False
                self.health.last_error = f'rejected reading: {exc}'
                return
            self.health.rms_error_mm = float(tool.error_mm)
        self.on_pose(pose, host_time)

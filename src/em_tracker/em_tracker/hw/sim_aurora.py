"""A simulated NDI Aurora that speaks the Combined API on a pseudo-terminal.

The simulated device owns the master side of a pty (``os.openpty``); the host opens the slave
path exactly like ``/dev/ttyUSB0`` (ndicapi's ``ndiOpen`` works on it). Optionally the slave
path is published through a stable symlink, like ``/dev/serial/by-id/...`` of a USB adapter,
so that :meth:`SimAurora.reconnect` can model an unplug/replug: a new pty appears behind the
same name and the device is back in its power-on state.

Behaviour (as a real Aurora): power-on -> ``INIT:`` -> setup mode (``PHSR``, ``PVWR``,
``PINIT``, ``PENA``, ``PDIS``, ``PHF``, ``COMM``, ``VER``, ``BEEP``) -> ``TSTART:`` ->
tracking mode (``TX``, ``BX``, ``TSTOP``). Commands in the wrong mode get ``ERROR0C``, unknown
commands and frames that are not a command (no ``:`` or space after the name, e.g. a bare
``TX``) ``ERROR01``, a bad command CRC ``ERROR04``, a parameter that is not what the command
takes (``TX:ZZZZ``, ``BX:G001``) ``ERROR23`` or the command's own code. No input stops the
device: a line whose handling fails anyway is answered ``ERROR01`` and recorded in
:attr:`SimStats.handler_errors`. ``COMM`` is acknowledged with ``OKAY``
and the new baud rate is recorded but ignored, since a pty has no line speed. The device
produces frames at ``frame_rate_hz`` from ``TSTART``; ``TX``/``BX`` return the latest one,
with its frame number.

Pose source: a callable ``t -> (position_mm, quat_wxyz)`` (``t`` in seconds since
``TSTART``), e.g. a :class:`ScriptedTrajectory` or a wrapper around the simulator's tip pose:
the catheter tip's pose in the phantom frame.

Ground truth (:class:`SimGroundTruth`, hidden from the host): where the phantom sits in the
field generator's frame, how the sensor is mounted behind the tip, and the Aurora's noise. The
device reports what a real Aurora would, the *sensor's* pose in the *tracker* frame,
``T_aurora_phantom @ T_phantom_tip @ inv(T_sensor_tip)`` plus noise drawn per frame. The
default (identity placement and mounting, no noise) reports the pose source unchanged.

Faults (thread-safe setters): bad CRC on the next replies, MISSING tool, out of volume,
partially out of volume, broken coil, extra port/system status bits, ``ERRORxx`` replies to
tracking commands, garbage bytes before a reply, dropped frames, unanswered commands, and a
disconnect (the pty is closed: the host gets read/write errors).

In-process link: a started device is also found by its :attr:`~SimAurora.port` with
:func:`in_process_device`, and :meth:`SimAurora.exchange` answers one command frame in the
caller's thread, as the serving thread answers a line from the pty
(:class:`em_tracker.hw.aurora.InProcessAurora`, the lockstep simulated session).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import contextlib
from dataclasses import dataclass, field
import errno
import math
import os
import re
import select
import signal
import tempfile
import threading
import time
import tty

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from em_tracker.core.errors import ProtocolError
from em_tracker.hw import combined_api as api

_NAME_COLON = re.compile(rb'[A-Z0-9]+:')
#: The started devices of this process, by port (:func:`in_process_device`).
_IN_PROCESS: dict[str, SimAurora] = {}
_HEX_DIGITS = frozenset('0123456789ABCDEFabcdef')

PoseSource = Callable[[float], tuple[Sequence[float] | np.ndarray, Sequence[float] | np.ndarray]]
"""``t_s -> (position_mm (3,), quat_wxyz (4,))`` of the tip in the phantom frame (with the
default :class:`SimGroundTruth`: what the device reports, the field-generator frame)."""


def _placement(value: object, name: str) -> NDArray[np.float64]:
    """``value`` as a read-only rigid 4x4 transform (translation in mm).

    Raises:
        ValueError: not a finite 4x4 matrix with last row ``0 0 0 1`` and an orthonormal
            rotation block of det +1; the message names ``name``.
    """
    m = np.array(value, dtype=float)
    ok = m.shape == (4, 4) and bool(np.all(np.isfinite(m)))
    if ok:
        rot = m[:3, :3]
        ok = (np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9)
              and np.allclose(rot @ rot.T, np.eye(3), atol=1e-6)
              and float(np.linalg.det(rot)) > 0.0)
    if not ok:
        raise ValueError(f'{name} must be a rigid 4x4 transform (orthonormal rotation, det +1, '
                         f'last row 0 0 0 1), found {value!r}')
    m.setflags(write=False)
    return m


def pose_matrix(position_mm: Sequence[float] | np.ndarray,
                quat_wxyz: Sequence[float] | np.ndarray) -> NDArray[np.float64]:
    """The 4x4 transform (translation in mm) of a pose in NDI order."""
    w, x, y, z = (float(v) for v in quat_wxyz)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    out[:3, 3] = np.asarray(position_mm, dtype=float)
    return out


@dataclass(frozen=True, eq=False)  # (no field-wise ==: the fields are arrays)
class SimGroundTruth:
    """The simulated rig's ground truth, hidden from the host (what calibration recovers).

    Transforms are 4x4 with the translation in mm (device units, as everything in ``hw``);
    ``T_a_b`` maps frame-b points into frame a, as in :mod:`em_tracker.core.pose`.
    """

    phantom_in_tracker: np.ndarray = field(default_factory=lambda: np.eye(4))
    """``T_aurora_phantom``: the phantom's placement in the field generator's frame. The
    ``registration`` that ``register_phantom`` should find is its inverse (in metres)."""
    tip_in_sensor: np.ndarray = field(default_factory=lambda: np.eye(4))
    """``T_sensor_tip``: the sensor's mounting; its translation is the tip offset in the sensor
    frame. The ``tool_transform`` that ``pivot_calibrate`` should find (up to the roll about
    the shaft, which a pivot does not observe)."""
    position_noise_mm: float = 0.0
    """3-D RMS of the position noise of each frame, mm; [0, 10] (Aurora 6DOF: 0.48,
    :data:`em_tracker.core.registration.AURORA_POSITION_RMS_M`). Isotropic Gaussian, per-axis
    sigma ``rms / sqrt(3)`` (the model of ``cgail_planner``'s ``TrackingNoise``)."""
    orientation_noise_deg: float = 0.0
    """RMS rotation angle of the orientation noise of each frame, deg; [0, 10] (Aurora 6DOF:
    0.30). A rotation vector with per-axis sigma ``rms / sqrt(3)``, in the tracker frame."""
    seed: int = 0
    """Seed of the noise: frame ``k`` after the ``n``-th ``TSTART`` draws from ``(seed, n,
    k)``, so a reading depends on neither how often nor when the host polls."""

    def __post_init__(self) -> None:
        object.__setattr__(self, 'phantom_in_tracker',
                           _placement(self.phantom_in_tracker, 'phantom_in_tracker'))
        object.__setattr__(self, 'tip_in_sensor', _placement(self.tip_in_sensor,
                                                             'tip_in_sensor'))
        for name in ('position_noise_mm', 'orientation_noise_deg'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and 0.0 <= value <= 10.0):
                raise ValueError(f'{name} must be in [0, 10], found {value!r}')
        if not (isinstance(self.seed, int) and self.seed >= 0):
            raise ValueError(f'seed must be a non-negative integer, found {self.seed!r}')
        # (asked at every frame; the fields are frozen)
        object.__setattr__(self, '_passthrough', (
            self.position_noise_mm == 0.0 and self.orientation_noise_deg == 0.0
            and bool(np.array_equal(self.phantom_in_tracker, np.eye(4)))
            and bool(np.array_equal(self.tip_in_sensor, np.eye(4)))))

    @property
    def passthrough(self) -> bool:
        """Identity placement and mounting and no noise: readings are the pose source's."""
        return bool(self.__dict__['_passthrough'])

    def registration_m(self) -> NDArray[np.float64]:
        """The true ``T_phantom_aurora`` in metres (the ``registration`` parameter's form)."""
        out = np.linalg.inv(self.phantom_in_tracker)
        out[:3, 3] *= 1e-3
        return out

    def tool_transform_m(self) -> NDArray[np.float64]:
        """The true ``T_sensor_tip`` in metres (the ``tool_transform`` parameter's form)."""
        out = np.array(self.tip_in_sensor)
        out[:3, 3] *= 1e-3
        return out

    def reading(self, tip_position_mm: Sequence[float] | np.ndarray,
                tip_quat_wxyz: Sequence[float] | np.ndarray,
                rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
        """What the Aurora reports for a tip pose in the phantom frame: the sensor's pose in
        the tracker frame, ``(position_mm, quat_wxyz)`` with ``q0 >= 0``, plus noise drawn from
        ``rng`` (none if ``rng`` is None)."""
        sensor = (self.phantom_in_tracker @ pose_matrix(tip_position_mm, tip_quat_wxyz)
                  @ np.linalg.inv(self.tip_in_sensor))
        rot, pos = sensor[:3, :3], sensor[:3, 3]
        if rng is not None:
            pos = pos + rng.normal(0.0, self.position_noise_mm / math.sqrt(3.0), 3)
            tilt = rng.normal(0.0, math.radians(self.orientation_noise_deg) / math.sqrt(3.0), 3)
            rot = Rotation.from_rotvec(tilt).as_matrix() @ rot
        x, y, z, w = Rotation.from_matrix(rot).as_quat(canonical=True)
        return pos, np.array([w, x, y, z])


class ScriptedTrajectory:
    """Piecewise-linear trajectory through timed waypoints (slerp for the rotation).

    Args:
        times_s: strictly increasing waypoint times, s (first one is usually 0).
        positions_mm: (N, 3) positions, mm.
        quats_wxyz: (N, 4) unit quaternions in NDI order; identity if omitted.
        loop: wrap time around after the last waypoint instead of holding it.
    """

    def __init__(self, times_s: Sequence[float], positions_mm: Sequence[Sequence[float]],
                 quats_wxyz: Sequence[Sequence[float]] | None = None, *, loop: bool = False):
        self.times = np.asarray(times_s, dtype=float)
        self.positions = np.asarray(positions_mm, dtype=float)
        if self.times.ndim != 1 or self.times.size < 1:
            raise ValueError(f'times_s must be a non-empty 1-D sequence, found {times_s!r}')
        if np.any(np.diff(self.times) <= 0):
            raise ValueError(f'times_s must be strictly increasing, found {times_s!r}')
        if self.positions.shape != (self.times.size, 3):
            raise ValueError(f'positions_mm must have shape ({self.times.size}, 3), '
                             f'found {self.positions.shape}')
        if quats_wxyz is None:
            self.quats = np.tile([1.0, 0.0, 0.0, 0.0], (self.times.size, 1))
        else:
            self.quats = np.asarray(quats_wxyz, dtype=float)
            if self.quats.shape != (self.times.size, 4):
                raise ValueError(f'quats_wxyz must have shape ({self.times.size}, 4), '
                                 f'found {self.quats.shape}')
            self.quats = self.quats / np.linalg.norm(self.quats, axis=1, keepdims=True)
        self.loop = loop

    def __call__(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(position_mm, quat_wxyz)`` at time ``t_s``."""
        t0, t1 = float(self.times[0]), float(self.times[-1])
        if self.loop and t1 > t0:
            t_s = t0 + (t_s - t0) % (t1 - t0)
        t_s = min(max(t_s, t0), t1)
        i = int(np.searchsorted(self.times, t_s, side='right')) - 1
        i = min(max(i, 0), self.times.size - 1)
        if i == self.times.size - 1:
            return self.positions[i].copy(), self.quats[i].copy()
        a = (t_s - self.times[i]) / (self.times[i + 1] - self.times[i])
        pos = (1.0 - a) * self.positions[i] + a * self.positions[i + 1]
        q0, q1 = self.quats[i], self.quats[i + 1]
        dot = float(np.dot(q0, q1))
        if dot < 0.0:
            q1, dot = -q1, -dot
        if dot > 0.9995:
            quat = (1.0 - a) * q0 + a * q1
        else:
            theta = math.acos(dot)
            quat = (math.sin((1 - a) * theta) * q0 + math.sin(a * theta) * q1) / math.sin(theta)
        return pos, quat / np.linalg.norm(quat)


def circle_trajectory(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Default pose source: a 20 mm circle 200 mm in front of the field generator, 0.2 Hz."""
    w = 2.0 * math.pi * 0.2
    pos = np.array([20.0 * math.cos(w * t_s), 20.0 * math.sin(w * t_s), -200.0])
    half = 0.5 * w * t_s
    return pos, np.array([math.cos(half), 0.0, 0.0, math.sin(half)])


@dataclass
class Faults:
    """The faults currently injected (mutate through :class:`SimAurora` setters).

    Attributes:
        bad_crc: number of next replies whose CRC is corrupted.
        garbage: number of next replies preceded by garbage bytes.
        garbage_bytes: the bytes sent as garbage.
        no_reply: number of next commands left unanswered (host times out).
        missing: tool reported MISSING (sensor not seen).
        out_of_volume: tool outside the measurement volume (MISSING + bit 6).
        partially_out: tool partially out of volume (transform + bit 7).
        broken_coil: sensor coil broken (MISSING + bit 8).
        extra_port_status: bits OR-ed into every port status word.
        system_status: system status word of tracking replies.
        tracking_error: when set, TX/BX are answered ``ERRORxx`` with this code.
        drop_frames: frame numbers skipped once at the next frame (frames lost by the device).
    """

    bad_crc: int = 0
    garbage: int = 0
    garbage_bytes: bytes = b'\x15#@!~zq'
    no_reply: int = 0
    missing: bool = False
    out_of_volume: bool = False
    partially_out: bool = False
    broken_coil: bool = False
    extra_port_status: int = 0
    system_status: int = 0
    tracking_error: int | None = None
    drop_frames: int = 0


@dataclass
class _Port:
    handle: int
    occupied: bool = True
    initialized: bool = False
    enabled: bool = False
    priority: str = ''
    srom: bytearray = field(default_factory=lambda: bytearray(1024))


@dataclass
class SimStats:
    """Counters of what the simulated device saw (for tests and the benchmark).

    ``commands`` keeps the raw command frames received (the oldest are dropped past 10000).
    ``handler_errors`` records the exceptions raised while handling a line (the line was
    answered ``ERROR01``; the first 100 are kept): empty unless the simulator has a bug.
    """

    commands: list[str] = field(default_factory=list)
    bad_command_crc: int = 0
    handler_errors: list[str] = field(default_factory=list)
    baud: int = 9600
    frames_served: int = 0


class SimAurora:
    """Simulated Aurora on a pty; start with :meth:`start`, stop with :meth:`close`.

    Args:
        pose_source: ``t_s -> (position_mm, quat_wxyz)`` of the tip in the phantom frame;
            :func:`circle_trajectory` if None.
        tool_handles: port handles with a sensor plugged in.
        frame_rate_hz: device frame rate (the Aurora runs at 40 Hz).
        error_mm: RMS error reported with each valid transform, mm.
        link_path: if set, a symlink to the current pty slave (stable across reconnects).
        first_frame: frame number of the first frame after TSTART.
        clock: monotonic clock, s (injectable for tests).
        truth: the hidden placement, mounting and noise (default: none of them, the pose
            source is reported as it is).
    """

    def __init__(self, pose_source: PoseSource | None = None, *,
                 tool_handles: Sequence[int] = (0x0A,), frame_rate_hz: float = 40.0,
                 error_mm: float = 0.25, link_path: str | None = None, first_frame: int = 1,
                 clock: Callable[[], float] = time.monotonic,
                 truth: SimGroundTruth | None = None) -> None:
        if not frame_rate_hz > 0:
            raise ValueError(f'frame_rate_hz must be > 0, found {frame_rate_hz!r}')
        if not tool_handles or any(not 0 < h <= 0xFF for h in tool_handles):
            raise ValueError(f'tool_handles must be handles in 0x01..0xFF, '
                             f'found {tool_handles!r}')
        self.pose_source: PoseSource = pose_source or circle_trajectory
        self.truth = truth or SimGroundTruth()
        self._tstarts = 0  # TSTART count: a key of the noise draws
        self.tool_handles = tuple(tool_handles)
        self.frame_rate_hz = float(frame_rate_hz)
        self.error_mm = float(error_mm)
        self.link_path = link_path
        self.first_frame = int(first_frame)
        self.clock = clock
        self.faults = Faults()
        self.stats = SimStats()
        self.frame_times: dict[int, float] = {}
        self._lock = threading.RLock()
        self._master = -1
        self._slave = -1
        self._generation = 0  # pty (re)opened or closed: a select's readiness is stale
        self._slave_name = ''
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        self._power_on()

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> str:
        """The path the host opens: the symlink if any, else the pty slave."""
        return self.link_path or self._slave_name

    @property
    def slave_name(self) -> str:
        """The current pty slave device, e.g. ``/dev/pts/7``."""
        return self._slave_name

    def start(self) -> SimAurora:
        """Create the pty and start serving commands in a background thread."""
        self._open_pty()
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name='sim_aurora', daemon=True)
        self._thread.start()
        _IN_PROCESS[self.port] = self
        return self

    def close(self) -> None:
        """Stop serving and close the pty (and remove the symlink)."""
        if _IN_PROCESS.get(self.port) is self:
            del _IN_PROCESS[self.port]
        self._stop.set()
        os.write(self._wake_w, b'x')
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_fds()
        if self.link_path and os.path.islink(self.link_path):
            os.unlink(self.link_path)
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def __enter__(self) -> SimAurora:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def disconnect(self) -> None:
        """Fault: the device vanishes (cable pulled). The host sees I/O errors."""
        with self._lock:
            self._close_fds()

    def reconnect(self) -> None:
        """Bring the device back (new pty behind the same symlink), in power-on state."""
        with self._lock:
            self._close_fds()
            self._power_on()
            self._open_pty()
        os.write(self._wake_w, b'x')

    @property
    def tracking_start_time(self) -> float:
        """Clock time of the last ``TSTART`` (frame ``k`` exists from this + k / rate)."""
        return self._t_start

    @property
    def connected(self) -> bool:
        """True while the pty is open."""
        return self._master >= 0

    # ------------------------------------------------------------------ faults
    def inject(self, **changes: object) -> None:
        """Set fault fields atomically, e.g. ``inject(missing=True)`` or ``inject(bad_crc=2)``.

        Raises:
            ValueError: unknown fault name.
        """
        with self._lock:
            for name, value in changes.items():
                if not hasattr(self.faults, name):
                    raise ValueError(f'unknown fault {name!r}; expected one of '
                                     f'{sorted(vars(self.faults))}')
                setattr(self.faults, name, value)

    def clear_faults(self) -> None:
        """Remove every injected fault."""
        with self._lock:
            self.faults = Faults()

    # ------------------------------------------------------------------ internals
    def _power_on(self) -> None:
        self.initialized = False
        self.tracking = False
        self.ports = {h: _Port(h) for h in self.tool_handles}
        self.stats.baud = 9600
        self._t_start = 0.0
        self._frame_offset = 0
        self._last_frame_index = -1

    def _open_pty(self) -> None:
        self._generation += 1
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo / CR translation before the host configures the port
        self._master, self._slave = master, slave
        self._slave_name = os.ttyname(slave)
        if self.link_path:
            tmp = self.link_path + '.tmp'
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self._slave_name, tmp)
            os.replace(tmp, self.link_path)

    def _close_fds(self) -> None:
        self._generation += 1
        for name in ('_master', '_slave'):
            fd = getattr(self, name)
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
                setattr(self, name, -1)

    def _serve(self) -> None:
        buffer = b''
        while not self._stop.is_set():
            # (the pty it selected on, or a readiness seen on a closed one could send the read
            # to a new pty's fd of the same number, blocking with the lock held)
            generation = self._generation
            fds = [self._wake_r] + ([self._master] if self._master >= 0 else [])
            try:
                ready, _, _ = select.select(fds, [], [], 0.5)
            except (OSError, ValueError):
                time.sleep(0.01)
                continue
            if self._wake_r in ready:
                os.read(self._wake_r, 64)
                buffer = b''
                continue
            with self._lock:
                master = self._master
                if master < 0 or master not in ready or self._generation != generation:
                    continue
                try:
                    chunk = os.read(master, 4096)
                except OSError:
                    continue
                buffer += chunk
                while b'\r' in buffer:
                    line, buffer = buffer.split(b'\r', 1)
                    reply = self._handle_safely(line)
                    if reply is not None and self._master >= 0:
                        with contextlib.suppress(OSError):
                            os.write(self._master, reply)

    def exchange(self, frame: bytes) -> bytes | None:
        """Answer one command frame (up to its CR) in the caller's thread, as the serving
        thread answers a line read from the pty: the reply, or None for no reply.

        Raises:
            OSError: the device is disconnected (the pty is closed).
        """
        with self._lock:
            if self._master < 0:
                raise OSError(errno.EIO, 'the simulated Aurora is disconnected')
            return self._handle_safely(frame.rstrip(b'\r'))

    def _handle_safely(self, line: bytes) -> bytes | None:
        """:meth:`_handle`, answering ``ERROR01`` if it raises: the serving thread must never
        die, or the device would go deaf for good. Anything may raise here (a pose source is
        arbitrary code), hence the broad catch; what it caught is kept for tests."""
        try:
            return self._handle(line)
        except Exception as exc:  # deliberately broad, see the docstring
            if len(self.stats.handler_errors) < 100:
                self.stats.handler_errors.append(f'{line!r}: {type(exc).__name__}: {exc}')
            return api.encode_error(api.ERR_INVALID_COMMAND)

    def _handle(self, line: bytes) -> bytes | None:
        line = line.lstrip(b'\n\x00')
        if not line:
            return None
        self.stats.commands.append(line.decode('ascii', 'replace'))
        if len(self.stats.commands) > 10000:  # keep memory bounded on long runs
            del self.stats.commands[:5000]
        if self.faults.no_reply > 0:
            self.faults.no_reply -= 1
            return None
        try:
            cmd = api.decode_command(line)
        except ProtocolError:
            if _NAME_COLON.match(line):  # a command with a CRC, and the CRC is wrong
                self.stats.bad_command_crc += 1
                reply = api.encode_error(api.ERR_BAD_COMMAND_CRC)
            else:
                reply = api.encode_error(api.ERR_INVALID_COMMAND)
            return self._decorate(reply)
        return self._decorate(self._dispatch(cmd))

    def _decorate(self, reply: bytes) -> bytes:
        """Apply the bad-CRC and garbage faults to an encoded reply."""
        if self.faults.bad_crc > 0:
            self.faults.bad_crc -= 1
            if reply.startswith(api.BX_START):
                reply = reply[:-2] + bytes([reply[-2] ^ 0xFF, reply[-1]])
            else:
                crc = reply[-5:-1]
                flipped = b'%04X' % (int(crc, 16) ^ 0x5A5A)
                reply = reply[:-5] + flipped + api.CR
        if self.faults.garbage > 0:
            self.faults.garbage -= 1
            reply = self.faults.garbage_bytes + reply
        return reply

    def _ok(self) -> bytes:
        return api.encode_text_reply('OKAY')

    def _dispatch(self, cmd: api.Command) -> bytes:
        handler = getattr(self, '_cmd_' + cmd.name.lower(), None)
        if handler is None:
            return api.encode_error(api.ERR_INVALID_COMMAND)
        if not self.initialized and cmd.name not in ('INIT', 'COMM', 'VER', 'BEEP', 'RESET'):
            return api.encode_error(api.ERR_NOT_INITIALIZED)
        return handler(cmd.params)

    def _port(self, text: str) -> _Port | bytes:
        handle = _hex(text[:2], 2)
        port = None if handle is None else self.ports.get(handle)
        if port is None:
            return api.encode_error(api.ERR_INVALID_PORT_HANDLE)
        return port

    def _cmd_init(self, params: str) -> bytes:
        self.initialized = True
        self.tracking = False
        return self._ok()

    def _cmd_reset(self, params: str) -> bytes:
        self._power_on()
        return api.encode_text_reply('RESET')

    def _cmd_beep(self, params: str) -> bytes:
        return api.encode_text_reply('1')

    def _cmd_ver(self, params: str) -> bytes:
        return api.encode_text_reply(
            'Aurora Simulated Control Unit\nem_tracker.hw.sim_aurora\n'
            'Combined Firmware Revision: 008\n')

    def _cmd_comm(self, params: str) -> bytes:
        if len(params) != 5 or params[0] not in api.COMM_BAUD or \
                any(c not in '012' for c in params[1:]):
            return api.encode_error(api.ERR_BAD_COMM_PARAMS)
        # Acknowledged at the old rate, then the device switches; a pty has no line speed.
        self.stats.baud = api.COMM_BAUD[params[0]]
        return self._ok()

    def _cmd_phsr(self, params: str) -> bytes:
        option = params or '00'
        if option not in ('00', '01', '02', '03', '04'):
            return api.encode_error(api.ERR_PARAMETER_RANGE)
        selected: list[tuple[int, int]] = []
        for port in self.ports.values():
            status = (0x001 if port.occupied else 0) | (0x010 if port.initialized else 0) | (
                0x020 if port.enabled else 0)
            if option == '00' or (option == '02' and port.occupied and not port.initialized) \
                    or (option == '03' and port.initialized and not port.enabled) \
                    or (option == '04' and port.enabled):
                selected.append((port.handle, status))
        return api.encode_text_reply(api.encode_phsr_body(selected))

    def _cmd_pinit(self, params: str) -> bytes:
        if self.tracking:
            return api.encode_error(api.ERR_INVALID_MODE)
        port = self._port(params)
        if isinstance(port, bytes):
            return port
        if not port.occupied:
            return api.encode_error(api.ERR_NO_TOOL)
        port.initialized = True
        return self._ok()

    def _cmd_pena(self, params: str) -> bytes:
        if self.tracking:
            return api.encode_error(api.ERR_INVALID_MODE)
        port = self._port(params)
        if isinstance(port, bytes):
            return port
        if len(params) != 3 or params[2] not in 'SDB':
            return api.encode_error(api.ERR_INVALID_PRIORITY)
        if not port.initialized:
            return api.encode_error(api.ERR_PORT_NOT_INITIALIZED)
        port.enabled, port.priority = True, params[2]
        return self._ok()

    def _cmd_pdis(self, params: str) -> bytes:
        if self.tracking:
            return api.encode_error(api.ERR_INVALID_MODE)
        port = self._port(params)
        if isinstance(port, bytes):
            return port
        port.enabled = False
        return self._ok()

    def _cmd_pvwr(self, params: str) -> bytes:
        """``PVWR:hhAAAA<128 hex>``: write 64 bytes of a tool definition (SROM image)."""
        if self.tracking:
            return api.encode_error(api.ERR_INVALID_MODE)
        port = self._port(params)
        if isinstance(port, bytes):
            return port
        address = _hex(params[2:6], 4)
        if address is None or len(params) != 6 + 128 or _hex(params[6:], 128) is None \
                or address % 64 or address + 64 > len(port.srom):
            return api.encode_error(api.ERR_PARAMETER_RANGE)
        port.srom[address:address + 64] = bytes.fromhex(params[6:])
        return self._ok()

    def _cmd_phf(self, params: str) -> bytes:
        if self.tracking:
            return api.encode_error(api.ERR_INVALID_MODE)
        port = self._port(params)
        if isinstance(port, bytes):
            return port
        port.initialized = port.enabled = False
        return self._ok()

    def _cmd_tstart(self, params: str) -> bytes:
        if self.tracking:
            return api.encode_error(api.ERR_INVALID_MODE)
        self.tracking = True
        self._t_start = self.clock()
        self._tstarts += 1
        self._last_frame_index = -1
        return self._ok()

    def _cmd_tstop(self, params: str) -> bytes:
        if not self.tracking:
            return api.encode_error(api.ERR_INVALID_MODE)
        self.tracking = False
        return self._ok()

    def _cmd_tx(self, params: str) -> bytes:
        return self._tracking_reply(params, binary=False)

    def _cmd_bx(self, params: str) -> bytes:
        return self._tracking_reply(params, binary=True)

    def _tracking_reply(self, params: str, *, binary: bool) -> bytes:
        if not self.tracking:
            return api.encode_error(api.ERR_INVALID_MODE)
        if self.faults.tracking_error is not None:
            return api.encode_error(self.faults.tracking_error)
        # The reply option is 4 hex digits (none: transforms); anything else is out of range.
        option = _hex(params, 4) if params else api.REPLY_TRANSFORMS
        if option is None or not option & api.REPLY_TRANSFORMS:
            return api.encode_error(api.ERR_PARAMETER_RANGE)
        frames = self._current_frames()
        self.stats.frames_served += 1
        if binary:
            return api.encode_bx_reply(frames, self.faults.system_status)
        return api.encode_tx_reply(frames, self.faults.system_status)

    def _current_frames(self) -> list[api.ToolFrame]:
        elapsed = self.clock() - self._t_start
        # (+1e-6 frame, 25 ns at 40 Hz: a host clock stepped in whole frame periods, as the
        # lockstep rig's, must not see a frame boundary move by float round-off)
        index = max(0, math.floor(elapsed * self.frame_rate_hz + 1e-6))
        if index != self._last_frame_index:
            if self.faults.drop_frames > 0:
                self._frame_offset += self.faults.drop_frames
                self.faults.drop_frames = 0
            self._last_frame_index = index
        t_frame = index / self.frame_rate_hz
        frame_number = (self.first_frame + index + self._frame_offset) & 0xFFFFFFFF
        self.frame_times.setdefault(frame_number, self._t_start + t_frame)
        if len(self.frame_times) > 4096:
            for key in sorted(self.frame_times)[:2048]:
                del self.frame_times[key]
        pos, quat = self.pose_source(t_frame)
        truth = self.truth
        if not truth.passthrough:
            noisy = truth.position_noise_mm > 0.0 or truth.orientation_noise_deg > 0.0
            rng = np.random.default_rng((truth.seed, self._tstarts, index)) if noisy else None
            pos, quat = truth.reading(pos, quat, rng)
        faults = self.faults
        out = []
        for port in self.ports.values():
            status = (api.PORT_OCCUPIED if port.occupied else 0) | (
                api.PORT_INITIALIZED if port.initialized else 0) | (
                api.PORT_ENABLED if port.enabled else 0) | faults.extra_port_status
            if not port.enabled:
                out.append(api.ToolFrame(port.handle, api.ToolState.DISABLED,
                                         port_status=status, frame_number=frame_number))
                continue
            state = api.ToolState.VALID
            if faults.out_of_volume:
                status |= api.PORT_OUT_OF_VOLUME
                state = api.ToolState.MISSING
            if faults.broken_coil:
                status |= api.PORT_BROKEN_COIL
                state = api.ToolState.MISSING
            if faults.missing:
                state = api.ToolState.MISSING
            if faults.partially_out:
                status |= api.PORT_PARTIALLY_IN_VOLUME
            out.append(api.ToolFrame(
                port.handle, state,
                quat_wxyz=tuple(float(q) for q in quat),  # type: ignore[arg-type]
                position_mm=tuple(float(p) for p in pos),  # type: ignore[arg-type]
                error_mm=self.error_mm, port_status=status, frame_number=frame_number))
        return out


def in_process_device(port: str) -> SimAurora | None:
    """The started :class:`SimAurora` of this process whose :attr:`~SimAurora.port` is
    ``port``, or None."""
    return _IN_PROCESS.get(port)


def _hex(text: str, digits: int) -> int | None:
    """``text`` as exactly ``digits`` hex digits, or None (``int(text, 16)`` alone would also
    take a sign, spaces, underscores or a ``0x`` prefix)."""
    if len(text) != digits or not all(c in _HEX_DIGITS for c in text):
        return None
    return int(text, 16)


def main(args: Sequence[str] | None = None) -> None:
    """Start a simulated Aurora and print the serial port path to open."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--link', default=os.path.join(tempfile.gettempdir(), 'sim_aurora'),
                        help='stable symlink to the pty slave (default: %(default)s)')
    parser.add_argument('--rate', type=float, default=40.0, help='frame rate, Hz')
    parser.add_argument('--handles', default='0A',
                        help='comma-separated hex port handles with a sensor (default 0A)')
    ns = parser.parse_args(args)
    handles = [int(h, 16) for h in ns.handles.split(',') if h]
    sim = SimAurora(tool_handles=handles, frame_rate_hz=ns.rate, link_path=ns.link).start()
    print(f'simulated Aurora on {sim.slave_name} (link {sim.port}); Ctrl-C to stop',
          flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()


if __name__ == '__main__':
    main()

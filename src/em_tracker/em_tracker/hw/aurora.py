"""Host side of the NDI Aurora link, through ndicapi (``ndicapy``).

ndicapi does the port handling, command framing, CRCs and reply parsing; this module only
sequences the start-up and turns its results into :class:`TrackingReply` records (device
units, as read) or exceptions of :mod:`em_tracker.core.errors`.

Start-up (:meth:`NdiAurora.connect`): ``ndiOpen`` -> ``INIT:`` -> ``COMM:`` baud change ->
optional SROM images (``PVWR``) -> ``PHSR:02`` / ``PINIT:hh`` for every handle that needs
initialising -> ``PHSR:03`` / ``PENA:hh<priority>`` for every handle that needs enabling ->
``TSTART:``. Polling: ``TX:0001`` (or ``BX:0001``). Shutdown: ``TSTOP:``.

:class:`InProcessAurora` runs the same sequence against a simulated Aurora of this process
(:class:`~em_tracker.hw.sim_aurora.SimAurora`), which answers each command frame in the
caller's thread: no pty, no ndicapi, no serving thread. Its TX parsing gives ndicapi's values
to the bit (the same scaling products); the lockstep simulated session takes it, since a
serial exchange there is a thread switch and a pty round trip per frame, and the pty path is
what a rig runs and what the package's tests drive.

Known ndicapi hazard, and why :class:`IsolatedAurora` exists: when a reply fails (bad CRC,
timeout) *and* its bytes are not valid UTF-8 (line noise), ``ndicapy.ndiCommand`` dereferences a
NULL object and the process dies with SIGSEGV (observed with ndicapi 3.7.6). The node therefore
runs ndicapi in a child process by default; a crash there is reported as a disconnect and the
link is re-established with backoff.
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass, field
import json
import os
import select
import subprocess
import sys
import time
from typing import Any, Protocol

from em_tracker.core.errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceTimeout,
    EmTrackerError,
    ProtocolError,
)
from em_tracker.hw import combined_api as api

# ndicapi error codes (host-side, see ndicapi.h).
NDI_BAD_CRC = 0x100
NDI_OPEN_ERROR = 0x101
NDI_BAD_COMM = 0x102
NDI_TIMEOUT = 0x103
NDI_WRITE_ERROR = 0x104
NDI_READ_ERROR = 0x105
EOF_WITHIN_S = 1.0
"""A "timeout" reported sooner than this is an end-of-file on the line (ndicapi waits 5 s)."""

_BAUD_DIGIT = {9600: '0', 14400: '1', 19200: '2', 38400: '3', 57600: '4', 115200: '5',
               921600: '6', 1228739: '7', 230400: 'A'}


@dataclass(frozen=True)
class AuroraSettings:
    """What the host needs to bring an Aurora to tracking.

    Attributes:
        port: serial device path.
        baud: rate requested with COMM after INIT.
        priority: PENA tracking priority letter (D, S or B).
        use_bx: poll with BX (binary) instead of TX (text).
        srom_files: ``(handle, path)`` SROM images to write before PINIT.
    """

    port: str
    baud: int = 115200
    priority: str = 'D'
    use_bx: bool = False
    srom_files: tuple[tuple[int, str], ...] = ()

    def __post_init__(self) -> None:
        if self.baud not in _BAUD_DIGIT:
            raise ValueError(f'baud must be one of {sorted(_BAUD_DIGIT)}, found {self.baud!r}')
        if self.priority not in ('D', 'S', 'B'):
            raise ValueError(f"priority must be 'D', 'S' or 'B', found {self.priority!r}")


@dataclass(frozen=True)
class ToolReading:
    """One handle of a tracking reply, device units.

    Attributes:
        handle: port handle.
        visible: a transform was reported (False for MISSING/DISABLED).
        quat_wxyz: NDI quaternion (q0, qx, qy, qz); zeros when not visible.
        position_mm: position in the field-generator frame, mm; zeros when not visible.
        error_mm: RMS error, mm.
        port_status: 32-bit port status.
        frame_number: device frame number.
    """

    handle: int
    visible: bool
    quat_wxyz: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    error_mm: float = 0.0
    port_status: int = 0
    frame_number: int = 0


@dataclass(frozen=True)
class TrackingReply:
    """One TX/BX reply.

    Attributes:
        tools: readings of the enabled handles.
        system_status: 16-bit system status.
        host_time: monotonic time at which the reply was complete, s.
    """

    tools: tuple[ToolReading, ...]
    system_status: int
    host_time: float = field(default_factory=time.monotonic)


class AuroraDevice(Protocol):
    """What the node needs from a tracker (ndicapi, a child process, or a test fake)."""

    def connect(self) -> list[int]:
        """Open, initialise, enable tools and start tracking; return the enabled handles."""
        ...

    def read(self) -> TrackingReply:
        """Poll one tracking reply (blocks up to the device timeout)."""
        ...

    def close(self) -> None:
        """Stop tracking if possible and release the port; never raises."""
        ...


def _ndicapy() -> Any:
    try:
        import ndicapy
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DeviceError('ndicapy is missing: pip install ndicapi==3.7.6') from exc
    return ndicapy


class NdiAurora:
    """An Aurora driven in-process through ndicapi.

    Args:
        settings: port, baud, priority, TX/BX, SROM images.
    """

    def __init__(self, settings: AuroraSettings) -> None:
        self.settings = settings
        self._ndi = _ndicapy()
        self._dev: Any = None
        self.handles: list[int] = []

    def _error(self, command: str, exc: BaseException, elapsed_s: float) -> EmTrackerError:
        code = int(self._ndi.ndiGetError(self._dev)) if self._dev is not None else -1
        text = f'{command}: {exc}'
        if code in (NDI_READ_ERROR, NDI_WRITE_ERROR, NDI_OPEN_ERROR):
            return DeviceDisconnected(text)
        if code == NDI_TIMEOUT and elapsed_s < EOF_WITHIN_S:
            # ndicapi reports a 0-byte read as a timeout; one that comes back long before its
            # 5 s wait is an end-of-file: the line hung up (pty closed, USB adapter unplugged).
            return DeviceDisconnected(f'{text} after {elapsed_s * 1e3:.0f} ms: the line hung up')
        if code == NDI_TIMEOUT:
            return DeviceTimeout(text)
        if code == NDI_BAD_CRC:
            return ProtocolError(text)
        if isinstance(exc, UnicodeDecodeError):
            return ProtocolError(f'{command}: undecodable reply ({exc})')
        return DeviceError(text, code)

    def command(self, text: str) -> str:
        """Send one command through ``ndiCommand``; return the reply without CRC.

        Raises:
            DeviceDisconnected, DeviceTimeout, ProtocolError, DeviceError: as ndicapi reports.
        """
        if self._dev is None:
            raise DeviceDisconnected(f'{text}: port {self.settings.port} is not open')
        start = time.monotonic()
        try:
            reply = self._ndi.ndiCommand(self._dev, text)
        except (OSError, UnicodeDecodeError) as exc:
            raise self._error(text, exc, time.monotonic() - start) from exc
        return '' if reply is None else str(reply)

    def _phsr(self, option: str) -> list[int]:
        self.command(f'PHSR:{option}')
        count = int(self._ndi.ndiGetPHSRNumberOfHandles(self._dev))
        return [int(self._ndi.ndiGetPHSRHandle(self._dev, i)) for i in range(count)]

    def write_srom(self, handle: int, path: str) -> None:
        """Write a tool definition (SROM image, up to 1 kB) to ``handle`` with PVWR.

        Same commands as ndicapi's ``ndiPVWRFromFile`` (16 x 64 bytes, zero padded), sent
        through ``ndiCommand``: ``ndiPVWRFromFile`` keeps the GIL while it waits for each
        reply, which would starve a simulated device running in this interpreter.

        Raises:
            DeviceError: the file cannot be read or is larger than 1024 bytes, or PVWR fails.
        """
        try:
            with open(path, 'rb') as stream:
                image = stream.read(1025)
        except OSError as exc:
            raise DeviceError(f'PVWR of {path} on handle {handle:02X}: cannot read the SROM '
                              f'image ({exc})') from exc
        if len(image) > 1024:
            raise DeviceError(f'PVWR of {path}: expected an SROM image of at most 1024 bytes, '
                              f'found a larger file')
        image = image.ljust(1024, b'\0')
        for address in range(0, 1024, 64):
            self.command(f'PVWR:{handle:02X}{address:04X}'
                         f'{image[address:address + 64].hex().upper()}')

    def _open(self) -> None:
        if not os.path.exists(self.settings.port):
            raise DeviceDisconnected(f'serial port {self.settings.port} does not exist')
        dev = self._ndi.ndiOpen(self.settings.port)
        if dev is None:
            raise DeviceDisconnected(f'ndiOpen could not open {self.settings.port}')
        self._dev = dev

    def connect(self) -> list[int]:
        """Run the start-up sequence and return the enabled handles."""
        self.close()
        self._open()
        self.command('INIT:')
        if self.settings.baud != 9600:
            self.command(f'COMM:{_BAUD_DIGIT[self.settings.baud]}0000')
        for handle, path in self.settings.srom_files:
            self.write_srom(handle, path)
        for _ in range(4):  # splitters can reveal more handles once initialised
            pending = self._phsr('02')
            if not pending:
                break
            for handle in pending:
                self.command(f'PINIT:{handle:02X}')
        for handle in self._phsr('03'):
            self.command(f'PENA:{handle:02X}{self.settings.priority}')
        self.handles = self._phsr('04')
        self.command('TSTART:')
        return list(self.handles)

    def read(self) -> TrackingReply:
        """Poll ``TX:0001`` or ``BX:0001`` and read every enabled handle through ndicapi."""
        ndi = self._ndi
        binary = self.settings.use_bx
        self.command('BX:0001' if binary else 'TX:0001')
        now = time.monotonic()
        get_transform = ndi.ndiGetBXTransform if binary else ndi.ndiGetTXTransform
        get_status = ndi.ndiGetBXPortStatus if binary else ndi.ndiGetTXPortStatus
        get_frame = ndi.ndiGetBXFrame if binary else ndi.ndiGetTXFrame
        get_system = ndi.ndiGetBXSystemStatus if binary else ndi.ndiGetTXSystemStatus
        tools = []
        for handle in self.handles:
            key = bytes([handle])
            transform = get_transform(self._dev, key)
            status = int(get_status(self._dev, key)) & 0xFFFFFFFF
            if binary and status >> 7 == 0x1FFFFFF:
                # ndicapi sign-extends a BX status byte >= 0x80 over the upper bytes; only
                # the low byte (occupied..partially-out bits) is trustworthy then.
                status &= 0xFF
            frame = int(get_frame(self._dev, key)) & 0xFFFFFFFF
            if isinstance(transform, str):  # 'MISSING' or 'DISABLED'
                tools.append(ToolReading(handle, False, port_status=status, frame_number=frame))
                continue
            values = tuple(float(v) for v in transform)
            tools.append(ToolReading(handle, True, values[0:4], values[4:7],  # type: ignore
                                     values[7], status, frame))
        return TrackingReply(tuple(tools), int(get_system(self._dev)) & 0xFFFF, now)

    def close(self) -> None:
        """Send TSTOP if possible and close the port."""
        if self._dev is None:
            return
        with contextlib.suppress(OSError, UnicodeDecodeError):
            self._ndi.ndiCommand(self._dev, 'TSTOP:')
        with contextlib.suppress(OSError):
            self._ndi.ndiClose(self._dev)
        self._dev = None


class InProcessAurora(NdiAurora):
    """:class:`NdiAurora`'s sequence with a simulated Aurora of this process answering each
    command frame in the caller's thread (module docstring); TX polling only.

    Args:
        settings: as for :class:`NdiAurora` (``port``: the simulated Aurora's ``port``).

    Raises:
        ValueError: ``use_bx`` set.
    """

    def __init__(self, settings: AuroraSettings) -> None:  # (no ndicapy)
        if settings.use_bx:
            raise ValueError('InProcessAurora polls with TX: use_bx must be false, found true')
        self.settings = settings
        self._dev: Any = None  # the SimAurora while open
        self.handles: list[int] = []

    def _open(self) -> None:
        from em_tracker.hw.sim_aurora import in_process_device

        device = in_process_device(self.settings.port)
        if device is None:
            raise DeviceDisconnected(f'no simulated Aurora of this process serves '
                                     f'{self.settings.port}')
        self._dev = device

    def command(self, text: str) -> str:
        """Send one command frame (with its CRC) and return the reply's body.

        Raises:
            DeviceDisconnected: not open, or the device's line is down.
            DeviceTimeout: the device left the command unanswered.
            ProtocolError: a reply that is not a text reply with a good CRC.
            DeviceError: an ``ERRORxx`` reply (``code`` xx).
        """
        if self._dev is None:
            raise DeviceDisconnected(f'{text}: port {self.settings.port} is not open')
        try:
            reply = self._dev.exchange(api.encode_command(text))
        except OSError as exc:
            raise DeviceDisconnected(f'{text}: {exc}') from exc
        if reply is None:
            raise DeviceTimeout(f'{text}: no reply')
        body = api.decode_text_reply(reply)  # (ProtocolError: bad CRC, garbage)
        if body.startswith('ERROR') and len(body) == 7:
            raise DeviceError(f'{text}: the device answered {body}', int(body[5:], 16))
        return body

    def _phsr(self, option: str) -> list[int]:
        body = self.command(f'PHSR:{option}')
        return [int(body[2 + 5 * i:4 + 5 * i], 16) for i in range(int(body[:2], 16))]

    def read(self) -> TrackingReply:
        """Poll ``TX:0001``; the readings of the enabled handles, parsed as ndicapi parses
        them (quaternion and error ``* 0.0001``, position ``* 0.01`` mm).

        Raises:
            ProtocolError: a reply that does not parse as a TX reply.
        """
        body = self.command('TX:0001')
        now = time.monotonic()
        records: dict[int, ToolReading] = {}
        try:
            pos = 2
            for _ in range(int(body[:2], 16)):
                handle = int(body[pos:pos + 2], 16)
                pos += 2
                values: tuple[float, ...] | None = None
                if body.startswith('MISSING', pos):
                    pos += 7
                elif body.startswith('DISABLED', pos):
                    pos += 8
                else:
                    f = body[pos:pos + 51]
                    values = (*(int(f[k:k + 6]) * 0.0001 for k in range(0, 24, 6)),
                              *(int(f[k:k + 7]) * 0.01 for k in range(24, 45, 7)),
                              int(f[45:51]) * 0.0001)
                    pos += 51
                status, frame = int(body[pos:pos + 8], 16), int(body[pos + 8:pos + 16], 16)
                pos += 16 + (body[pos + 16:pos + 17] == '\n')
                records[handle] = ToolReading(handle, False, port_status=status,
                                              frame_number=frame) if values is None else \
                    ToolReading(handle, True, values[0:4], values[4:7],  # type: ignore[arg-type]
                                values[7], status, frame)
            system = int(body[pos:pos + 4], 16)
        except ValueError as exc:
            raise ProtocolError(f'TX:0001: expected a TX reply, found {body!r}') from exc
        tools = tuple(records[h] if h in records else ToolReading(h, False)
                      for h in self.handles)
        return TrackingReply(tools, system, now)

    def close(self) -> None:
        """Send TSTOP if possible and let go of the device."""
        if self._dev is None:
            return
        with contextlib.suppress(EmTrackerError):
            self.command('TSTOP:')
        self._dev = None


# ---------------------------------------------------------------------- child-process wrapper
_ERRORS: dict[str, type[EmTrackerError]] = {
    'DeviceDisconnected': DeviceDisconnected, 'DeviceTimeout': DeviceTimeout,
    'ProtocolError': ProtocolError, 'DeviceError': DeviceError,
}


class IsolatedAurora:
    """:class:`NdiAurora` running in a child process (``python -m em_tracker.hw.aurora``).

    Requests and replies are JSON lines on the child's stdin/stdout. If the child dies (e.g.
    SIGSEGV inside ndicapi) or does not answer within ``reply_timeout_s``, it is killed and the
    call raises :class:`DeviceDisconnected` / :class:`DeviceTimeout`.

    Args:
        settings: as for :class:`NdiAurora`.
        reply_timeout_s: longest wait for one answer, s.
    """

    def __init__(self, settings: AuroraSettings, reply_timeout_s: float = 7.0) -> None:
        self.settings = settings
        self.reply_timeout_s = reply_timeout_s
        self._proc: subprocess.Popen[bytes] | None = None
        self._buffer = b''

    def _spawn(self) -> subprocess.Popen[bytes]:
        self._kill()
        self._buffer = b''
        self._proc = subprocess.Popen(
            [sys.executable, '-m', 'em_tracker.hw.aurora'], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, bufsize=0,
            # Own session: a Ctrl-C on the terminal must not kill the child before the parent
            # has sent TSTOP; the child ends when its stdin closes.
            start_new_session=True)
        return self._proc

    def _kill(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=5)
        for stream in (proc.stdin, proc.stdout):
            if stream is not None:
                stream.close()

    def _call(self, request: dict[str, Any], timeout_s: float) -> dict[str, Any]:
        proc = self._proc
        if proc is None or proc.poll() is not None or proc.stdin is None or proc.stdout is None:
            raise DeviceDisconnected('tracker process is not running')
        try:
            proc.stdin.write(json.dumps(request).encode() + b'\n')
        except (BrokenPipeError, OSError) as exc:
            self._kill()
            raise DeviceDisconnected(f'tracker process gone: {exc}') from exc
        deadline = time.monotonic() + timeout_s
        fd = proc.stdout.fileno()
        while b'\n' not in self._buffer:
            left = deadline - time.monotonic()
            ready = select.select([fd], [], [], max(left, 0.0))[0] if left > 0 else []
            if not ready:
                self._kill()
                raise DeviceTimeout(f'no answer from the tracker within {timeout_s} s')
            chunk = os.read(fd, 65536)
            if not chunk:
                code = proc.wait(timeout=5)
                self._kill()
                raise DeviceDisconnected(f'tracker process exited with code {code}')
            self._buffer += chunk
        line, self._buffer = self._buffer.split(b'\n', 1)
        answer: dict[str, Any] = json.loads(line)
        if not answer.get('ok'):
            cls = _ERRORS.get(answer.get('error', ''), DeviceError)
            if cls is DeviceError:
                raise DeviceError(answer.get('message', ''), int(answer.get('code', -1)))
            raise cls(answer.get('message', ''))
        return answer

    def connect(self) -> list[int]:
        """Start a fresh child and run the start-up sequence in it."""
        if not os.path.exists(self.settings.port):
            self._kill()
            raise DeviceDisconnected(f'serial port {self.settings.port} does not exist')
        self._spawn()
        settings = asdict(self.settings)
        answer = self._call({'op': 'connect', 'settings': settings},
                            self.reply_timeout_s * 4)
        return [int(h) for h in answer['handles']]

    def read(self) -> TrackingReply:
        """Poll one reply through the child."""
        answer = self._call({'op': 'read'}, self.reply_timeout_s)
        tools = tuple(ToolReading(t['handle'], t['visible'], tuple(t['quat_wxyz']),
                                  tuple(t['position_mm']), t['error_mm'], t['port_status'],
                                  t['frame_number']) for t in answer['tools'])
        # The child's clock is the same CLOCK_MONOTONIC as ours.
        return TrackingReply(tools, int(answer['system_status']), float(answer['host_time']))

    def close(self) -> None:
        """Ask the child to stop tracking, then end it."""
        if self._proc is not None and self._proc.poll() is None:
            with contextlib.suppress(EmTrackerError):
                self._call({'op': 'close'}, 2.0)
        self._kill()


def _serve_child() -> None:
    """Child side of :class:`IsolatedAurora`: JSON requests on stdin, answers on stdout."""
    out = sys.stdout.buffer
    device: NdiAurora | None = None
    for raw in sys.stdin.buffer:
        request = json.loads(raw)
        answer: dict[str, Any] = {'ok': True}
        try:
            if request['op'] == 'connect':
                s = dict(request['settings'])
                s['srom_files'] = tuple((int(h), str(p)) for h, p in s['srom_files'])
                device = NdiAurora(AuroraSettings(**s))
                answer['handles'] = device.connect()
            elif request['op'] == 'read':
                if device is None:
                    raise DeviceDisconnected('read before connect')
                reply = device.read()
                answer.update(tools=[asdict(t) for t in reply.tools],
                              system_status=reply.system_status, host_time=reply.host_time)
            elif request['op'] == 'close':
                if device is not None:
                    device.close()
                answer['closed'] = True
        except EmTrackerError as exc:
            answer = {'ok': False, 'error': type(exc).__name__, 'message': str(exc),
                      'code': getattr(exc, 'code', -1)}
        out.write(json.dumps(answer).encode() + b'\n')
        out.flush()
        if request['op'] == 'close':
            return
    if device is not None:  # parent went away without 'close': still stop tracking
        device.close()


if __name__ == '__main__':
    _serve_child()

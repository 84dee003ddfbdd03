"""NDI Combined API framing: CRC-16, commands, and the device-side reply encoders.

This module is the *device side* of the protocol (what an NDI Aurora puts on the wire). The
host side deliberately does not use it: the host talks through ndicapi (``ndicapy``), an
independent implementation, so tests that run ndicapi against :mod:`em_tracker.hw.sim_aurora`
check these encoders against the library real Aurora users rely on.

Wire format (NDI Aurora / Polaris "Combined API"):

* Command: ``NAME:params`` + 4 upper-case hex digits of CRC-16 over ``NAME:params`` + ``CR``.
  A command sent with a space instead of the colon carries no CRC (``NAME params CR``).
* Text reply: ``body`` + 4 upper-case hex CRC over ``body`` + ``CR``; errors are
  ``ERRORxx`` (two hex digits), e.g. ``ERROR01`` for an invalid command.
* CRC-16/ARC: polynomial 0x8005 (reflected 0xA001), initial value 0, no final XOR.
  ``INIT:`` -> ``E3A5`` and ``OKAY`` -> ``A896``.
* TX (text tracking) reply, option 0x0001, per port handle:
  ``hh`` + (``MISSING`` | ``DISABLED`` | ``Q0 Qx Qy Qz`` as sign + 5 digits x 1e-4,
  ``Tx Ty Tz`` as sign + 6 digits x 0.01 mm, error as sign + 5 digits x 1e-4 mm)
  + 8 hex port status + 8 hex frame number + ``LF``; the reply starts with the 2 hex digit
  handle count and ends with the 4 hex digit system status.
* BX (binary tracking) reply: ``C4 A5`` start sequence (0xA5C4 little endian), 2 byte body
  length, 2 byte header CRC (over the first 4 bytes), body, 2 byte body CRC, all little endian.
  Body, option 0x0001: handle count (1 byte) and per handle: handle (1 byte), handle status
  (1 byte: 0x01 valid, 0x02 missing, 0x04 disabled), 8 float32 (q0 qx qy qz tx ty tz error;
  omitted when missing or disabled), port status (uint32), frame number (uint32); then the
  system status (uint16).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import enum
from functools import lru_cache
import math
import re
import struct

from em_tracker.core.errors import ProtocolError

CR = b'\r'
_NAME = re.compile(r'[A-Z0-9]+')
LF = b'\n'
BX_START = b'\xc4\xa5'

# Port status bits (TX: 8 hex digits, BX: uint32).
PORT_OCCUPIED = 0x0001
PORT_SWITCH_1 = 0x0002
PORT_SWITCH_2 = 0x0004
PORT_SWITCH_3 = 0x0008
PORT_INITIALIZED = 0x0010
PORT_ENABLED = 0x0020
PORT_OUT_OF_VOLUME = 0x0040
PORT_PARTIALLY_IN_VOLUME = 0x0080
PORT_BROKEN_COIL = 0x0100
PORT_PROCESSING_EXCEPTION = 0x0800

# System status bits (TX: 4 hex digits, BX: uint16).
SYSTEM_COMM_SYNC_ERROR = 0x0001
SYSTEM_CRC_ERROR = 0x0004
SYSTEM_RECOVERABLE_EXCEPTION = 0x0008
SYSTEM_HARDWARE_FAILURE = 0x0010
SYSTEM_HARDWARE_CHANGE = 0x0020
SYSTEM_PORT_OCCUPIED = 0x0040
SYSTEM_PORT_UNOCCUPIED = 0x0080

# BX handle status byte.
BX_HANDLE_VALID = 0x01
BX_HANDLE_MISSING = 0x02
BX_HANDLE_DISABLED = 0x04

# Reply options of TX/BX.
REPLY_TRANSFORMS = 0x0001

# Error codes the simulated device uses (Combined API numbering).
ERR_INVALID_COMMAND = 0x01
ERR_TOO_LONG = 0x02
ERR_TOO_SHORT = 0x03
ERR_BAD_COMMAND_CRC = 0x04
ERR_COMMAND_TIMEOUT = 0x05
ERR_BAD_COMM_PARAMS = 0x06
ERR_BAD_PARAM_COUNT = 0x07
ERR_INVALID_PORT_HANDLE = 0x08
ERR_INVALID_PRIORITY = 0x09
ERR_INVALID_MODE = 0x0C
ERR_NO_TOOL = 0x0D
ERR_PORT_NOT_INITIALIZED = 0x0E
ERR_PORT_NOT_ENABLED = 0x0F
ERR_NOT_INITIALIZED = 0x10
ERR_TSTOP_FAIL = 0x11
ERR_TSTART_FAIL = 0x12
ERR_PINIT_FAIL = 0x13
ERR_PARAMETER_RANGE = 0x23

# COMM baud digit -> baud rate (digit 'A' is 230400).
COMM_BAUD = {
    '0': 9600, '1': 14400, '2': 19200, '3': 38400, '4': 57600, '5': 115200,
    '6': 921600, '7': 1228739, 'A': 230400,
}
BAUD_TO_COMM_DIGIT = {baud: digit for digit, baud in COMM_BAUD.items()}

# Fixed-point scales of the TX text reply.
TX_QUAT_SCALE = 1e-4
TX_POS_SCALE_MM = 0.01
TX_ERROR_SCALE_MM = 1e-4


def _crc16_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC16_TABLE = _crc16_table()


def crc16(data: bytes, crc: int = 0) -> int:
    """CRC-16/ARC (poly 0x8005 reflected as 0xA001, init 0) as the Combined API uses it.

    Table-driven, a byte per step (the simulated Aurora checksums every reply it sends: the
    bit-by-bit loop cost ~40 us per reply).

    Args:
        data: the bytes to checksum.
        crc: running value to continue from (0 to start).

    Returns:
        The 16-bit CRC.
    """
    table = _CRC16_TABLE
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def crc_hex(data: bytes) -> bytes:
    """Return the CRC of ``data`` as the 4 upper-case hex digits sent on the wire."""
    return b'%04X' % crc16(data)


@lru_cache(maxsize=256)
def encode_command(text: str) -> bytes:
    """Frame a host command: ``NAME:params`` + CRC + CR (no CRC when there is no colon).
    (Cached: a host polls with the same few commands.)

    Args:
        text: the command without CRC or CR, e.g. ``'TX:0001'``.

    Returns:
        The bytes a host sends.
    """
    raw = text.encode('ascii')
    head = raw.split(b':', 1)[0]
    if b':' in raw and head.isalnum():
        return raw + crc_hex(raw) + CR
    return raw + CR


@dataclass(frozen=True)
class Command:
    """A command as the device parsed it.

    Attributes:
        name: the command name, e.g. ``'TX'``.
        params: the parameter characters after the separator, CRC removed.
    """

    name: str
    params: str


def decode_command(frame: bytes) -> Command:
    """Parse one host command frame (with or without its trailing CR). (Cached: a host polls
    with the same few frames; a frame that raises is not cached.)

    Args:
        frame: bytes up to the CR, e.g. ``b'PENA:0AD8C3B'``.

    Returns:
        The parsed command.

    Raises:
        ProtocolError: the frame is not ASCII, has no name, has no ``:`` or space after the
            name (a bare ``TX``), or its CRC does not match (the message names the expected
            and found CRC).
    """
    return _decode_command(bytes(frame))


@lru_cache(maxsize=256)
def _decode_command(frame: bytes) -> Command:
    frame = frame.rstrip(CR)
    try:
        text = frame.decode('ascii')
    except UnicodeDecodeError as exc:
        raise ProtocolError(f'expected an ASCII command, found {frame!r}') from exc
    sep = min((i for i in (text.find(':'), text.find(' ')) if i >= 0), default=len(text))
    name = text[:sep]
    if not _NAME.fullmatch(name):
        raise ProtocolError(f'expected an upper-case command name, found {name!r}')
    if sep == len(text):
        raise ProtocolError(f"expected ':' or ' ' after the command name, found {text!r}")
    if text[sep] == ':':
        rest = text[sep + 1:]
        if len(rest) < 4:
            raise ProtocolError(f'expected 4 CRC digits after {name}:, found {rest!r}')
        params, crc_text = rest[:-4], rest[-4:]
        expected = f'{crc16((name + ":" + params).encode("ascii")):04X}'
        if crc_text.upper() != expected:
            raise ProtocolError(f'expected command CRC {expected}, found {crc_text!r}')
    else:
        params = text[sep + 1:]
    return Command(name=name, params=params)


def encode_text_reply(body: str | bytes) -> bytes:
    """Frame a text reply: ``body`` + 4 hex CRC + CR."""
    raw = body.encode('ascii') if isinstance(body, str) else body
    return raw + crc_hex(raw) + CR


def encode_error(code: int) -> bytes:
    """Frame an ``ERRORxx`` reply for the given error code (0x01..0xFF)."""
    if not 0 < code <= 0xFF:
        raise ValueError(f'code must be in 0x01..0xFF, found {code!r}')
    return encode_text_reply(f'ERROR{code:02X}')


def decode_text_reply(frame: bytes) -> str:
    """Check the CRC of a text reply and return its body (used by the device-side tests).

    Raises:
        ProtocolError: missing CR, too short, or CRC mismatch.
    """
    if not frame.endswith(CR):
        raise ProtocolError(f'expected a reply ending in CR, found {frame[-8:]!r}')
    if len(frame) < 5:
        raise ProtocolError(f'expected at least 4 CRC digits and CR, found {frame!r}')
    body, crc_text = frame[:-5], frame[-5:-1]
    expected = crc_hex(body)
    if crc_text.upper() != expected:
        raise ProtocolError(f'expected reply CRC {expected!r}, found {crc_text!r}')
    return body.decode('ascii')


class ToolState(enum.Enum):
    """What the device reports for one port handle in a tracking reply."""

    VALID = 'valid'
    MISSING = 'missing'
    DISABLED = 'disabled'


@dataclass(frozen=True)
class ToolFrame:
    """One port handle's record in a TX/BX reply, in device units.

    Attributes:
        handle: port handle, 0x01..0xFF.
        state: valid transform, MISSING or DISABLED.
        quat_wxyz: rotation quaternion in NDI order (q0, qx, qy, qz).
        position_mm: translation (x, y, z) in mm, field-generator frame.
        error_mm: RMS fit error of the sensor in mm.
        port_status: 32-bit port status word (``PORT_*`` bits).
        frame_number: 32-bit frame counter of the device.
    """

    handle: int
    state: ToolState
    quat_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    error_mm: float = 0.0
    port_status: int = PORT_OCCUPIED | PORT_INITIALIZED | PORT_ENABLED
    frame_number: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.handle <= 0xFF:
            raise ValueError(f'handle must be in 0x01..0xFF, found {self.handle!r}')
        if not 0 <= self.port_status <= 0xFFFFFFFF:
            raise ValueError(f'port_status must fit 32 bits, found {self.port_status!r}')
        if not 0 <= self.frame_number <= 0xFFFFFFFF:
            raise ValueError(f'frame_number must fit 32 bits, found {self.frame_number!r}')


def _signed_field(value: float, digits: int) -> str:
    """Format ``round(value)`` as sign + ``digits`` zero-padded digits, saturating."""
    if not math.isfinite(value):
        raise ValueError(f'expected a finite value to encode, found {value!r}')
    limit = 10**digits - 1
    ivalue = max(-limit, min(limit, round(value)))
    return ('+' if ivalue >= 0 else '-') + str(abs(ivalue)).zfill(digits)


def encode_tx_transform(frame: ToolFrame) -> str:
    """The 51 characters of one TX transform (q, t, error), without handle or status."""
    quat = ''.join(_signed_field(q / TX_QUAT_SCALE, 5) for q in frame.quat_wxyz)
    pos = ''.join(_signed_field(p / TX_POS_SCALE_MM, 6) for p in frame.position_mm)
    return quat + pos + _signed_field(frame.error_mm / TX_ERROR_SCALE_MM, 5)


def encode_tx_body(frames: Sequence[ToolFrame], system_status: int = 0) -> str:
    """The body of a TX:0001 reply (without CRC and CR)."""
    parts = [f'{len(frames):02X}']
    for frame in frames:
        if frame.state is ToolState.VALID:
            record = encode_tx_transform(frame)
        elif frame.state is ToolState.MISSING:
            record = 'MISSING'
        else:
            record = 'DISABLED'
        parts.append(f'{frame.handle:02X}{record}{frame.port_status:08X}{frame.frame_number:08X}\n')
    parts.append('%04X' % (system_status & 0xFFFF))
    return ''.join(parts)


def encode_tx_reply(frames: Sequence[ToolFrame], system_status: int = 0) -> bytes:
    """A complete TX:0001 reply: body + CRC + CR."""
    return encode_text_reply(encode_tx_body(frames, system_status))


def encode_bx_body(frames: Sequence[ToolFrame], system_status: int = 0) -> bytes:
    """The body of a BX:0001 reply (between header and body CRC)."""
    out = bytearray(struct.pack('<B', len(frames)))
    for frame in frames:
        if frame.state is ToolState.DISABLED:
            out += struct.pack('<BB', frame.handle, BX_HANDLE_DISABLED)
            continue
        if frame.state is ToolState.MISSING:
            out += struct.pack('<BB', frame.handle, BX_HANDLE_MISSING)
        else:
            out += struct.pack('<BB', frame.handle, BX_HANDLE_VALID)
            out += struct.pack('<8f', *frame.quat_wxyz, *frame.position_mm, frame.error_mm)
        out += struct.pack('<II', frame.port_status, frame.frame_number)
    out += struct.pack('<H', system_status & 0xFFFF)
    return bytes(out)


def encode_bx_reply(frames: Sequence[ToolFrame], system_status: int = 0) -> bytes:
    """A complete BX:0001 reply: header (start, length, header CRC) + body + body CRC."""
    body = encode_bx_body(frames, system_status)
    header = BX_START + struct.pack('<H', len(body))
    return header + struct.pack('<H', crc16(header)) + body + struct.pack('<H', crc16(body))


def encode_phsr_body(handles: Sequence[tuple[int, int]]) -> str:
    """The body of a PHSR reply: count, then per handle 2 hex handle + 3 hex status."""
    return f'{len(handles):02X}' + ''.join(f'{h:02X}{s & 0xFFF:03X}' for h, s in handles)

"""The PAM regulator bank's CAN message set (``config/pam.dbc``), encoded/decoded by cantools.

Message set (full description: ``docs/can_pam.md``; little-endian signals, 11-bit ids):

=====  ======================  =========  ====  ==============================================
id     name                    sender     DLC   content
=====  ======================  =========  ====  ==============================================
0x200  ``PAM_SETPOINTS``       host       8     4 x 12-bit setpoint (0.1 kPa), counter, CRC
0x201  ``PAM_MEASURED``        bank       8     4 x 12-bit pressure (0.1 kPa, -10 kPa offset),
                                                counter, CRC
0x202  ``PAM_STATUS``          bank       8     state, fault flags, channel fault mask, supply
                                                pressure, counter, CRC
0x700  ``PAM_HOST_HEARTBEAT``  host       3     counter, requested mode, CRC
=====  ======================  =========  ====  ==============================================

The CRC byte (last byte) is CRC-8/SAE-J1850 over the arbitration id (2 bytes, big-endian) and
the payload bytes before it, so a frame of random bytes on a known id is rejected with
probability 255/256, and the counter exposes lost frames. Device units (kPa) stay in this
module; everything in and out of it is in Pa.
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
import functools
from pathlib import Path

import can
import cantools
from cantools.database.can import Database
import numpy as np
from numpy.typing import ArrayLike, NDArray

from cgail_node_utils.can_codec import FastCodec
from pam_controller.core.supervisor import BankMode
from pam_controller.errors import ProtocolError

FloatArray = NDArray[np.float64]

SETPOINTS_ID = 0x200
MEASURED_ID = 0x201
STATUS_ID = 0x202
HOST_HEARTBEAT_ID = 0x700
KNOWN_IDS = frozenset({SETPOINTS_ID, MEASURED_ID, STATUS_ID, HOST_HEARTBEAT_ID})

SETPOINT_MAX_KPA = 409.5
"""Largest encodable setpoint (12 bits x 0.1 kPa)."""
MEASURED_MIN_KPA = -10.0
"""Smallest encodable measured pressure."""
MEASURED_MAX_KPA = 399.5
"""Largest encodable measured pressure."""


class BankState(enum.IntEnum):
    """``PAM_STATUS.STATE``."""

    INIT = 0
    READY = 1
    ACTIVE = 2
    VENTING = 3
    FAULT = 4


FAULT_NAMES: tuple[str, ...] = (
    'FAULT_OVERPRESSURE', 'FAULT_STUCK', 'FAULT_HOST_TIMEOUT', 'FAULT_SUPPLY_LOW',
    'FAULT_BAD_FRAME')
"""The fault flag signals of ``PAM_STATUS``."""


def _crc8_step(crc: int) -> int:
    """Eight shifts of the CRC-8/SAE-J1850 register (poly 0x1D), MSB first."""
    for _ in range(8):
        crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


#: ``_crc8_step`` of every register value: the CRC one byte at a time (every frame of the
#: control loops goes through it).
_CRC8_TABLE = bytes(_crc8_step(value) for value in range(256))


def crc8_sae_j1850(data: bytes) -> int:
    """CRC-8/SAE-J1850: poly 0x1D, init 0xFF, no reflection, xorout 0xFF (check 0x4B)."""
    crc = 0xFF
    for byte in data:
        crc = _CRC8_TABLE[crc ^ byte]
    return crc ^ 0xFF


def frame_crc(arbitration_id: int, payload_without_crc: bytes) -> int:
    """The CRC byte of a frame: CRC-8/SAE-J1850 over ``id (2 bytes BE) + payload[:-1]``."""
    return crc8_sae_j1850(arbitration_id.to_bytes(2, 'big') + payload_without_crc)


def dbc_path() -> Path:
    """Path of ``pam.dbc``: the source tree's ``config/`` or the installed share directory."""
    here = Path(__file__).resolve().parents[2] / 'config' / 'pam.dbc'
    if here.is_file():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory('pam_controller')) / 'config' / 'pam.dbc'
    except (ImportError, LookupError) as err:
        raise FileNotFoundError(
            f'expected pam.dbc at {here} or in the pam_controller share directory') from err


@functools.cache
def load_database() -> Database:
    """The parsed DBC (cached)."""
    db = cantools.database.load_file(str(dbc_path()))
    assert isinstance(db, Database)
    return db


@dataclass(frozen=True)
class Setpoints:
    """Decoded ``PAM_SETPOINTS``."""

    pressures_pa: FloatArray
    counter: int


@dataclass(frozen=True)
class Measured:
    """Decoded ``PAM_MEASURED``."""

    pressures_pa: FloatArray
    counter: int


@dataclass(frozen=True)
class Status:
    """Decoded ``PAM_STATUS``."""

    state: BankState
    faults: frozenset[str]
    channel_fault_mask: int
    supply_pressure_pa: float
    counter: int


@dataclass(frozen=True)
class HostHeartbeat:
    """Decoded ``PAM_HOST_HEARTBEAT``."""

    mode: BankMode
    counter: int


Decoded = Setpoints | Measured | Status | HostHeartbeat


def _four(values: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if arr.shape != (4,) or not np.isfinite(arr).all():
        raise ProtocolError(f'expected 4 finite {name}, found {np.asarray(values).tolist()}')
    return arr


@functools.cache
def _codecs() -> dict[str, FastCodec]:
    """The fast codec of every message of ``pam.dbc`` (:mod:`cgail_node_utils.can_codec`:
    cantools' bytes and values by shifts; the control loop sends several frames per tick)."""
    return {m.name: FastCodec(m) for m in load_database().messages}


def _encode(name: str, signals: dict[str, float | int]) -> can.Message:
    codec = _codecs()[name]
    frame_id = codec.frame_id
    payload = codec.pack({**signals, 'CRC': 0})
    if payload is None:  # cantools decides (and raises)
        try:
            payload = load_database().encode_message(name, {**signals, 'CRC': 0})
        except cantools.database.EncodeError as err:
            raise ProtocolError(f'cannot encode {name}: {err}') from err
    data = bytearray(payload)
    data[-1] = frame_crc(frame_id, bytes(data[:-1]))
    return can.Message(arbitration_id=frame_id, data=bytes(data), is_extended_id=False)


def encode_setpoints(pressures_pa: ArrayLike, counter: int) -> can.Message:
    """``PAM_SETPOINTS`` frame for four setpoints (Pa, each within 0..409.5 kPa)."""
    kpa = _four(pressures_pa, 'setpoints (Pa)') / 1e3
    sig: dict[str, float | int] = {f'SETPOINT_{i}': float(kpa[i]) for i in range(4)}
    return _encode('PAM_SETPOINTS', {**sig, 'COUNTER': counter % 16})


def encode_measured(pressures_pa: ArrayLike, counter: int) -> can.Message:
    """``PAM_MEASURED`` frame; pressures are clipped to the encodable -10..399.5 kPa (sensor
    saturation)."""
    kpa = (_four(pressures_pa, 'pressures (Pa)') / 1e3).clip(MEASURED_MIN_KPA, MEASURED_MAX_KPA)
    sig: dict[str, float | int] = {f'PRESSURE_{i}': float(kpa[i]) for i in range(4)}
    return _encode('PAM_MEASURED', {**sig, 'COUNTER': counter % 16})


def encode_status(state: BankState, faults: frozenset[str] | set[str], channel_fault_mask: int,
                  supply_pressure_pa: float, counter: int) -> can.Message:
    """``PAM_STATUS`` frame."""
    unknown = set(faults) - set(FAULT_NAMES)
    if unknown:
        raise ProtocolError(f'expected faults among {FAULT_NAMES}, found {sorted(unknown)}')
    sig: dict[str, float | int] = {name: int(name in faults) for name in FAULT_NAMES}
    supply_kpa = min(max(supply_pressure_pa / 1e3, 0.0), SETPOINT_MAX_KPA)
    return _encode('PAM_STATUS', {**sig, 'STATE': int(state),
                                  'CHANNEL_FAULT_MASK': channel_fault_mask & 0xF,
                                  'SUPPLY_PRESSURE': supply_kpa, 'COUNTER': counter % 16})


def encode_host_heartbeat(mode: BankMode, counter: int) -> can.Message:
    """``PAM_HOST_HEARTBEAT`` frame."""
    return _encode('PAM_HOST_HEARTBEAT', {'MODE': int(mode), 'COUNTER': counter % 16})


def decode(msg: can.Message) -> Decoded | None:
    """Decode one frame of the message set.

    Returns:
        The decoded message, or ``None`` for a frame that is not ours (other id, extended id).

    Raises:
        ProtocolError: a frame on one of our ids that is an error/remote frame, has the wrong
            length, a bad CRC, or an out-of-range enum value.
    """
    if msg.is_extended_id or msg.arbitration_id not in KNOWN_IDS:
        return None
    aid = msg.arbitration_id
    if msg.is_error_frame or msg.is_remote_frame:
        raise ProtocolError(
            f'expected a data frame on id 0x{aid:03X}, found an error/remote frame')
    db = load_database()
    msg_def = db.get_message_by_frame_id(aid)
    data = bytes(msg.data)
    if len(data) != msg_def.length:
        raise ProtocolError(
            f'expected {msg_def.length} data bytes for {msg_def.name} (0x{aid:03X}), '
            f'found {len(data)}')
    crc = frame_crc(aid, data[:-1])
    if data[-1] != crc:
        raise ProtocolError(
            f'expected CRC 0x{crc:02X} for {msg_def.name}, found 0x{data[-1]:02X}')
    codec = _codecs()[msg_def.name]
    if codec.supported:
        sig = codec.unpack(data)
    else:
        try:
            raw = db.decode_message(aid, data, decode_choices=False)
        except cantools.database.DecodeError as err:
            raise ProtocolError(f'cannot decode {msg_def.name}: {err}') from err
        if not isinstance(raw, dict):
            raise ProtocolError(f'expected a signal dict for {msg_def.name}, found {type(raw)}')
        sig = {k: float(v) for k, v in raw.items() if isinstance(v, int | float)}
    counter = int(sig['COUNTER'])
    if aid == SETPOINTS_ID:
        return Setpoints(np.array([float(sig[f'SETPOINT_{i}']) for i in range(4)]) * 1e3, counter)
    if aid == MEASURED_ID:
        return Measured(np.array([float(sig[f'PRESSURE_{i}']) for i in range(4)]) * 1e3, counter)
    if aid == STATUS_ID:
        state = int(sig['STATE'])
        if state not in BankState._value2member_map_:
            raise ProtocolError(f'expected PAM_STATUS.STATE in 0..4, found {state}')
        return Status(BankState(state), frozenset(n for n in FAULT_NAMES if int(sig[n])),
                      int(sig['CHANNEL_FAULT_MASK']), float(sig['SUPPLY_PRESSURE']) * 1e3,
                      counter)
    mode = int(sig['MODE'])
    if mode not in BankMode._value2member_map_:
        raise ProtocolError(f'expected PAM_HOST_HEARTBEAT.MODE in 0..3, found {mode}')
    return HostHeartbeat(BankMode(mode), counter)

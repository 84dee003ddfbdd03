"""The sleeve driver's CAN message set, encoded and decoded with cantools from ``driver.dbc``.

Classic CAN, 11-bit ids, little-endian (Intel) signals. Device units (mm, mm/s) exist only in
this module; the dataclasses below carry SI units.

========= ============ ===== ======================================================= ========
id        name         bytes signals (bit start|length, scale, unit)                 sender
========= ============ ===== ======================================================= ========
0x080     DRV_ESTOP    1     Stop 0|1                                                host
0x200     DRV_COMMAND  4     SleeveVelocity 0|16 signed 0.001 mm/s;                  host
                             MovingGripperClose 16|1; FixedGripperClose 17|1;
                             Counter 24|8 (rolling)
0x210     DRV_STATUS   8     SleevePosition 0|32 signed 0.001 mm;                    driver
                             SleeveVelocity 32|16 signed 0.001 mm/s;
                             MovingGripperState 48|2, FixedGripperState 50|2
                             (0 OPEN, 1 CLOSING, 2 CLOSED, 3 OPENING);
                             Stopped 52|1, Stall 53|1, Interlock 54|1,
                             CommandTimeout 55|1; Counter 56|8 (rolling)
========= ============ ===== ======================================================= ========
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import os
from pathlib import Path

import can
import cantools
from cantools.database.can import Database

from catheter_driver.core.relay import GripperState
from catheter_driver.exceptions import ProtocolError
from cgail_node_utils.can_codec import FastCodec

ESTOP_ID = 0x080
COMMAND_ID = 0x200
STATUS_ID = 0x210
MM_PER_M = 1000.0


def default_dbc_path() -> Path:
    """Locate ``driver.dbc``: next to the sources (develop/symlink installs), else the package
    share directory of an installed workspace.

    Raises:
        FileNotFoundError: if neither location holds the file.
    """
    here = Path(os.path.realpath(__file__)).parents[2] / 'config' / 'driver.dbc'
    if here.is_file():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory

        shared = Path(get_package_share_directory('catheter_driver')) / 'config' / 'driver.dbc'
    except (ImportError, LookupError, ValueError) as exc:
        raise FileNotFoundError(f'expected driver.dbc at {here}, found nothing ({exc})') from exc
    if not shared.is_file():
        raise FileNotFoundError(f'expected driver.dbc at {here} or {shared}, found neither')
    return shared


@dataclass(frozen=True)
class DriverCommand:
    """DRV_COMMAND in SI units."""

    sleeve_velocity: float
    """Sleeve velocity setpoint, m/s."""
    moving_close: bool
    """Close the gripper on the sleeve."""
    fixed_close: bool
    """Close the gripper on the frame."""
    counter: int = 0
    """Rolling alive counter, 0..255."""


@dataclass(frozen=True)
class DriverStatus:
    """DRV_STATUS in SI units."""

    sleeve_position: float
    """Sleeve position along its stroke, m."""
    sleeve_velocity: float
    """Measured sleeve velocity, m/s."""
    moving: GripperState
    """Gripper on the sleeve."""
    fixed: GripperState
    """Gripper on the frame."""
    stopped: bool = False
    """E-stop latch engaged in the driver."""
    stall: bool = False
    """Sleeve commanded to move but not moving."""
    interlock: bool = False
    """Sleeve command refused by the gripper interlock."""
    command_timeout: bool = False
    """No command within the driver's watchdog time; sleeve stopped."""
    counter: int = 0
    """Rolling alive counter, 0..255."""


class DriverCodec:
    """Encodes and decodes the driver's frames.

    Args:
        dbc_path: the DBC file (default :func:`default_dbc_path`).
        position_range: plausible sleeve positions (m); a status outside is a ProtocolError.

    Raises:
        ProtocolError: the DBC file is missing, unreadable or not a CAN database.
    """

    def __init__(self, dbc_path: Path | str | None = None, *,
                 position_range: tuple[float, float] = (-0.01, 0.2)) -> None:
        path = Path(dbc_path) if dbc_path else default_dbc_path()
        try:
            db = cantools.database.load_file(str(path))
        except (OSError, cantools.database.UnsupportedDatabaseFormatError) as exc:
            raise ProtocolError(f'expected a readable CAN database (DBC) at {path}, found '
                                f'{type(exc).__name__}: {exc}') from exc
        if not isinstance(db, Database):
            raise ProtocolError(f'expected a CAN database in {path}, found {type(db).__name__}')
        self._estop = db.get_message_by_frame_id(ESTOP_ID)
        self._command = db.get_message_by_frame_id(COMMAND_ID)
        self._status = db.get_message_by_frame_id(STATUS_ID)
        # cantools' bytes and values by shifts (cgail_node_utils.can_codec): a frame or two per
        # control tick each way; cantools still decides (and raises) where the values do not fit
        self._codecs = {m.frame_id: FastCodec(m) for m in (self._estop, self._command,
                                                            self._status)}
        self.position_range = position_range

    # -- host -> driver ----------------------------------------------------------------------

    def encode_command(self, command: DriverCommand) -> can.Message:
        """DRV_COMMAND frame for ``command``.

        Raises:
            ProtocolError: if the velocity is not finite or does not fit the signal.
        """
        if not math.isfinite(command.sleeve_velocity):
            raise ProtocolError(
                f'expected a finite sleeve velocity, found {command.sleeve_velocity!r}')
        try:
            data = self._encode(self._command, {
                'SleeveVelocity': round(command.sleeve_velocity * MM_PER_M, 3),
                'MovingGripperClose': int(command.moving_close),
                'FixedGripperClose': int(command.fixed_close),
                'Counter': command.counter & 0xFF,
            })
        except cantools.database.EncodeError as exc:
            raise ProtocolError(f'cannot encode {command}: {exc}') from exc
        return can.Message(arbitration_id=COMMAND_ID, data=data, is_extended_id=False)

    def encode_stop(self, engaged: bool) -> can.Message:
        """DRV_ESTOP frame."""
        data = self._estop.encode({'Stop': int(engaged)})
        return can.Message(arbitration_id=ESTOP_ID, data=data, is_extended_id=False)

    def decode_command(self, msg: can.Message) -> DriverCommand:
        """Decode a DRV_COMMAND frame (driver side)."""
        sig = self._decode(self._command, msg)
        return DriverCommand(sig['SleeveVelocity'] / MM_PER_M, bool(sig['MovingGripperClose']),
                             bool(sig['FixedGripperClose']), int(sig['Counter']))

    def decode_stop(self, msg: can.Message) -> bool:
        """Decode a DRV_ESTOP frame (driver side): True = engaged."""
        return bool(self._decode(self._estop, msg)['Stop'])

    # -- driver -> host ----------------------------------------------------------------------

    def encode_status(self, status: DriverStatus) -> can.Message:
        """DRV_STATUS frame (driver side)."""
        try:
            data = self._encode(self._status, {
                'SleevePosition': round(status.sleeve_position * MM_PER_M, 3),
                'SleeveVelocity': round(status.sleeve_velocity * MM_PER_M, 3),
                'MovingGripperState': int(status.moving),
                'FixedGripperState': int(status.fixed),
                'Stopped': int(status.stopped),
                'Stall': int(status.stall),
                'Interlock': int(status.interlock),
                'CommandTimeout': int(status.command_timeout),
                'Counter': status.counter & 0xFF,
            })
        except cantools.database.EncodeError as exc:
            raise ProtocolError(f'cannot encode {status}: {exc}') from exc
        return can.Message(arbitration_id=STATUS_ID, data=data, is_extended_id=False)

    def decode_status(self, msg: can.Message) -> DriverStatus:
        """Decode a DRV_STATUS frame.

        Raises:
            ProtocolError: wrong id, length or an implausible sleeve position.
        """
        sig = self._decode(self._status, msg)
        position = sig['SleevePosition'] / MM_PER_M
        lo, hi = self.position_range
        if not lo <= position <= hi:
            raise ProtocolError(
                f'expected a sleeve position in [{lo}, {hi}] m, found {position!r} m')
        return DriverStatus(
            sleeve_position=position,
            sleeve_velocity=sig['SleeveVelocity'] / MM_PER_M,
            moving=GripperState(int(sig['MovingGripperState'])),
            fixed=GripperState(int(sig['FixedGripperState'])),
            stopped=bool(sig['Stopped']), stall=bool(sig['Stall']),
            interlock=bool(sig['Interlock']), command_timeout=bool(sig['CommandTimeout']),
            counter=int(sig['Counter']))

    def _decode(self, message: cantools.database.Message, msg: can.Message) -> dict[str, float]:
        if msg.arbitration_id != message.frame_id or msg.is_extended_id:
            raise ProtocolError(
                f'expected frame id {message.frame_id:#05x} ({message.name}), found '
                f'{msg.arbitration_id:#x}')
        if len(msg.data) != message.length:
            raise ProtocolError(
                f'expected {message.length} data bytes in {message.name}, found {len(msg.data)}')
        codec = self._codecs.get(message.frame_id)
        if codec is not None and codec.supported:
            return codec.unpack(bytes(msg.data))
        try:
            decoded = message.decode(bytes(msg.data), decode_choices=False, scaling=True)
        except cantools.database.DecodeError as exc:
            raise ProtocolError(f'cannot decode {message.name}: {exc}') from exc
        return {k: float(v) for k, v in decoded.items()}  # type: ignore[arg-type,union-attr]

    def _encode(self, message: cantools.database.Message, values: dict[str, float | int]
                ) -> bytes:
        """``message.encode(values)``: packed by its fast codec where the values fit."""
        codec = self._codecs.get(message.frame_id)
        data = codec.pack(values) if codec is not None else None
        return data if data is not None else message.encode(values)

"""Host side of the sleeve driver link: a small Protocol and its python-can implementation.

The simulated twin of the device is :class:`catheter_driver.hw.sim_driver.SimulatedDriver`,
which sits on the same python-can bus (``interface='virtual'`` in tests and simulation).
"""

from __future__ import annotations

from typing import Protocol

import can

from catheter_driver.exceptions import DeviceDisconnectedError, ProtocolError
from catheter_driver.hw.can_protocol import (
    COMMAND_ID,
    DriverCodec,
    DriverCommand,
    DriverStatus,
    ESTOP_ID,
    STATUS_ID,
)
from cgail_node_utils.virtual_can import open_bus

MAX_FRAMES_PER_POLL = 256


class DriverLink(Protocol):
    """What the driver node needs from the device."""

    def send_command(self, command: DriverCommand) -> None:
        """Send a velocity/valve command (non-blocking)."""

    def send_stop(self, engaged: bool) -> None:
        """Engage or release the driver's e-stop latch."""

    def poll(self) -> DriverStatus | None:
        """Return the newest valid status received since the last poll, or None."""

    def close(self) -> None:
        """Release the bus."""


class CanDriverLink:
    """:class:`DriverLink` over python-can.

    Malformed frames never raise out of :meth:`poll`; they are counted in
    :attr:`protocol_errors` and the last reason is kept in :attr:`last_error`.
    Bus failures raise :class:`~catheter_driver.exceptions.DeviceDisconnectedError`.
    """

    def __init__(self, bus: can.BusABC, codec: DriverCodec) -> None:
        """Wrap an open bus."""
        self._bus = bus
        self._codec = codec
        self._counter = 0
        self._last_counter: int | None = None
        self.protocol_errors = 0
        self.dropped_frames = 0
        self.last_error = ''

    @classmethod
    def open(cls, interface: str, channel: str, codec: DriverCodec,
             bitrate: int = 500000) -> CanDriverLink:
        """Open a python-can bus.

        Raises:
            DeviceDisconnectedError: if the bus cannot be opened.
        """
        try:
            if interface == 'virtual':
                bus = open_bus(interface, channel)
            else:
                bus = open_bus(interface, channel, bitrate=bitrate)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise DeviceDisconnectedError(
                f'expected to open CAN {interface}:{channel}, found error: {exc}') from exc
        return cls(bus, codec)

    def send_command(self, command: DriverCommand) -> None:
        """Encode and send DRV_COMMAND with the link's rolling counter."""
        msg = self._codec.encode_command(DriverCommand(
            command.sleeve_velocity, command.moving_close, command.fixed_close, self._counter))
        self._counter = (self._counter + 1) & 0xFF
        self._send(msg)

    def send_stop(self, engaged: bool) -> None:
        """Send DRV_ESTOP."""
        self._send(self._codec.encode_stop(engaged))

    def poll(self) -> DriverStatus | None:
        """Drain pending frames and return the newest valid DRV_STATUS, or None."""
        newest: DriverStatus | None = None
        for _ in range(MAX_FRAMES_PER_POLL):
            try:
                msg = self._bus.recv(timeout=0.0)
            except can.CanError as exc:
                raise DeviceDisconnectedError(f'CAN receive failed: {exc}') from exc
            if msg is None:
                break
            if msg.arbitration_id in (COMMAND_ID, ESTOP_ID) and not msg.is_extended_id:
                continue  # another host's traffic (or our own echo)
            if msg.arbitration_id != STATUS_ID or msg.is_extended_id or msg.is_error_frame:
                self._reject(f'expected frame id {STATUS_ID:#05x}, found '
                             f'{msg.arbitration_id:#x}')
                continue
            try:
                status = self._codec.decode_status(msg)
            except ProtocolError as exc:
                self._reject(str(exc))
                continue
            if self._last_counter is not None:
                self.dropped_frames += (status.counter - self._last_counter - 1) & 0xFF
            self._last_counter = status.counter
            newest = status
        return newest

    def close(self) -> None:
        """Shut the bus down (idempotent)."""
        self._bus.shutdown()

    def _reject(self, reason: str) -> None:
        self.protocol_errors += 1
        self.last_error = reason

    def _send(self, msg: can.Message) -> None:
        try:
            self._bus.send(msg, timeout=0.01)
        except can.CanError as exc:
            raise DeviceDisconnectedError(f'CAN send failed: {exc}') from exc

"""Host side of the regulator bank: the ``RegulatorBank`` protocol and its python-can adapter.

``CanRegulatorBank`` talks the message set of :mod:`pam_controller.hw.can_protocol` over any
python-can bus (``socketcan`` on the rig, ``virtual`` in tests and the simulated rig, where
:mod:`pam_controller.hw.sim_regulators` is the device on the same channel). It never blocks:
:meth:`CanRegulatorBank.poll` drains what is queued with ``recv(timeout=0)``. Malformed frames
are counted and remembered, never raised, so a noisy bus cannot crash the caller.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
import math
from typing import Protocol

import can
import numpy as np
from numpy.typing import ArrayLike, NDArray

from cgail_node_utils.virtual_can import open_bus
from pam_controller.core.supervisor import BankMode
from pam_controller.errors import DeviceUnavailableError, ProtocolError
from pam_controller.hw import can_protocol as proto

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LinkConfig:
    """How the host reaches the bank and decides it is gone."""

    interface: str = 'virtual'
    """python-can interface (``virtual`` for the simulated rig and tests, ``socketcan`` on
    the rig)."""
    channel: str = 'pam0'
    """python-can channel (``can0`` on the rig)."""
    bitrate: int = 1_000_000
    """Bit rate, bit/s (ignored by ``virtual``). In [10000, 1000000]."""
    heartbeat_period_s: float = 0.1
    """Period of ``PAM_HOST_HEARTBEAT``, s; must stay below the bank's 0.5 s host timeout.
    In [0.01, 0.4]."""
    device_timeout_s: float = 0.3
    """No ``PAM_MEASURED`` for this long: the bank counts as disconnected, s. In [0.02, 10]."""
    reconnect_initial_s: float = 0.2
    """First reconnect delay, s; doubles per failed attempt. In (0, 60]."""
    reconnect_max_s: float = 5.0
    """Largest reconnect delay, s. In [reconnect_initial_s, 600]."""

    def __post_init__(self) -> None:
        if not self.interface:
            raise ValueError('interface must be a non-empty python-can interface name, found ""')
        if not self.channel:
            raise ValueError('channel must be a non-empty channel name, found ""')
        if not 10_000 <= self.bitrate <= 1_000_000:
            raise ValueError(f'bitrate must be in [10000, 1000000], found {self.bitrate}')
        ranges = {'heartbeat_period_s': (0.01, 0.4), 'device_timeout_s': (0.02, 10.0),
                  'reconnect_initial_s': (1e-6, 60.0),
                  'reconnect_max_s': (self.reconnect_initial_s, 600.0)}
        for name, (lo, hi) in ranges.items():
            value = getattr(self, name)
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f'{name} must be in [{lo}, {hi}], found {value}')


@dataclass
class BankFeedback:
    """What the host knows about the bank after a poll."""

    measured: list[FloatArray] = field(default_factory=list)
    """Measured pressure vectors (Pa, 4) received in this poll, oldest first."""
    status: proto.Status | None = None
    """Latest status received in this poll (None if none)."""
    bad_frames: int = 0
    """Malformed frames on our ids in this poll."""
    last_error: str = ''
    """Reason of the last malformed frame in this poll."""


class RegulatorBank(Protocol):
    """What the node needs from a regulator bank."""

    def open(self) -> None:
        """Open (or re-open) the connection; raises ``DeviceUnavailableError``."""

    def close(self) -> None:
        """Release the connection (idempotent)."""

    @property
    def is_open(self) -> bool:
        """True when the connection is open."""

    def send_setpoints(self, pressures_pa: ArrayLike) -> None:
        """Send four setpoints (Pa); raises ``DeviceUnavailableError``."""

    def send_heartbeat(self, mode: BankMode) -> None:
        """Send the host heartbeat with the requested mode; raises ``DeviceUnavailableError``."""

    def poll(self) -> BankFeedback:
        """Drain received frames without blocking."""


class CanRegulatorBank:
    """``RegulatorBank`` over a python-can bus.

    Args:
        interface: python-can interface name (``virtual``, ``socketcan``, ...).
        channel: channel name (``pam0`` on the virtual bus, ``can0`` on the rig).
        bitrate: bit rate for interfaces that take one (ignored by ``virtual``).
        max_frames_per_poll: cap on frames drained per poll, so a flooded bus cannot starve
            the executor.
    """

    def __init__(self, interface: str, channel: str, bitrate: int = 1_000_000,
                 max_frames_per_poll: int = 1000) -> None:
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.max_frames_per_poll = max_frames_per_poll
        self._bus: can.BusABC | None = None
        self._setpoint_counter = 0
        self._heartbeat_counter = 0
        self._last_measured_counter: int | None = None
        self.lost_frames = 0
        """Measured frames missed, from gaps in the alive counter."""
        self.bad_frames_total = 0
        """Malformed frames since construction."""

    @property
    def is_open(self) -> bool:
        """True when the bus is open."""
        return self._bus is not None

    def open(self) -> None:
        """Open the bus (closing a previous one first)."""
        self.close()
        kwargs: dict[str, object] = {}
        if self.interface != 'virtual':
            kwargs['bitrate'] = self.bitrate
        try:
            self._bus = open_bus(self.interface, self.channel, **kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as err:
            self._bus = None
            raise DeviceUnavailableError(
                f'expected to open CAN {self.interface}:{self.channel}, found error: {err}'
            ) from err
        self._last_measured_counter = None

    def close(self) -> None:
        """Shut the bus down (idempotent)."""
        if self._bus is not None:
            bus, self._bus = self._bus, None
            with contextlib.suppress(can.CanError, OSError):
                bus.shutdown()

    def _send(self, msg: can.Message) -> None:
        if self._bus is None:
            raise DeviceUnavailableError(
                f'expected an open CAN bus {self.interface}:{self.channel}, found it closed')
        try:
            self._bus.send(msg, timeout=0.0)
        except (can.CanError, OSError) as err:
            raise DeviceUnavailableError(
                f'CAN send on {self.interface}:{self.channel} failed: {err}') from err

    def send_setpoints(self, pressures_pa: ArrayLike) -> None:
        """Send ``PAM_SETPOINTS`` (Pa, 4 values)."""
        self._send(proto.encode_setpoints(pressures_pa, self._setpoint_counter))
        self._setpoint_counter = (self._setpoint_counter + 1) % 16

    def send_heartbeat(self, mode: BankMode) -> None:
        """Send ``PAM_HOST_HEARTBEAT``."""
        self._send(proto.encode_host_heartbeat(mode, self._heartbeat_counter))
        self._heartbeat_counter = (self._heartbeat_counter + 1) % 16

    def poll(self) -> BankFeedback:
        """Drain up to ``max_frames_per_poll`` frames; malformed ones are counted, not raised."""
        fb = BankFeedback()
        if self._bus is None:
            return fb
        for _ in range(self.max_frames_per_poll):
            try:
                msg = self._bus.recv(timeout=0.0)
            except (can.CanError, OSError) as err:
                raise DeviceUnavailableError(
                    f'CAN receive on {self.interface}:{self.channel} failed: {err}') from err
            if msg is None:
                break
            try:
                decoded = proto.decode(msg)
            except ProtocolError as err:
                fb.bad_frames += 1
                fb.last_error = str(err)
                continue
            if isinstance(decoded, proto.Measured):
                if self._last_measured_counter is not None:
                    self.lost_frames += (decoded.counter - self._last_measured_counter - 1) % 16
                self._last_measured_counter = decoded.counter
                fb.measured.append(decoded.pressures_pa)
            elif isinstance(decoded, proto.Status):
                fb.status = decoded
        self.bad_frames_total += fb.bad_frames
        return fb

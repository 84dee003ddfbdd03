"""python-can buses of the device nodes and their simulated twins, ``virtual`` made cheaper.

:func:`open_bus` opens ``can.Bus(interface=..., channel=..., **kwargs)``, except that the
``virtual`` interface gets a :class:`LightVirtualBus`: python-can's own ``VirtualBus`` on the
same channels (it talks to any other ``virtual`` bus of the process, as before), which copies a
sent frame for each receiver by constructing it rather than by ``copy.deepcopy`` (the same
fields, its own ``data`` bytearray: what deepcopy gives), receives into an unbounded
``queue.SimpleQueue`` (C, thread-safe; python-can's default ``rx_queue_size=0`` is unbounded
too, and peers put into it as into a ``queue.Queue``) and answers ``recv(timeout=0)`` (the
device nodes' poll) with one ``get_nowait`` when no filters are set, without ``BusABC.recv``'s
timing loop. The simulated rig sends and polls ~7 frames per 40 Hz tick in one thread; the
generic path cost ~40 us of it per tick. Any other interface (``socketcan`` on the rig) is
python-can's, untouched.
"""

from __future__ import annotations

import queue
import time
from typing import Any

import can
from can.interfaces.virtual import channels_lock, VirtualBus


class LightVirtualBus(VirtualBus):
    """``VirtualBus`` with a cheaper copy per receiver and a non-blocking zero-timeout take
    (module docstring); behaviour otherwise python-can's."""

    def __init__(self, channel: Any = None, receive_own_messages: bool = False,
                 rx_queue_size: int = 0, **kwargs: Any) -> None:
        super().__init__(channel=channel, receive_own_messages=receive_own_messages,
                         rx_queue_size=rx_queue_size, **kwargs)
        if rx_queue_size <= 0:  # unbounded: the C queue in the channel's list, in its place
            with channels_lock:
                fast: Any = queue.SimpleQueue()
                self.channel[next(i for i, q in enumerate(self.channel)
                                  if q is self.queue)] = fast
                self.queue = fast

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """As ``BusABC.recv``; a zero timeout without filters is one non-blocking take."""
        if timeout is not None and timeout <= 0.0 and not self._filters:
            self._check_if_open()
            try:
                msg: can.Message = self.queue.get_nowait()
            except queue.Empty:
                return None
            return msg
        return super().recv(timeout)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """As ``VirtualBus.send``: every other queue of the channel (and this one with
        ``receive_own_messages``) gets its own copy, stamped with the send time."""
        self._check_if_open()
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        all_sent = True
        own = self.queue
        for bus_queue in self.channel:
            if bus_queue is own and not self.receive_own_messages:
                continue
            copy = can.Message(
                timestamp=timestamp, arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame, channel=self.channel_id, dlc=msg.dlc,
                data=bytearray(msg.data), is_fd=msg.is_fd, is_rx=bus_queue is not own,
                bitrate_switch=msg.bitrate_switch,
                error_state_indicator=msg.error_state_indicator)
            try:
                bus_queue.put(copy, block=True, timeout=timeout)
            except queue.Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError('Could not send message to one or more recipients')

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if timeout is not None and timeout <= 0.0:
            self._check_if_open()
            try:
                return self.queue.get_nowait(), False
            except queue.Empty:
                return None, False
        return super()._recv_internal(timeout)


def open_bus(interface: str, channel: Any, **kwargs: Any) -> can.BusABC:
    """``can.Bus(interface=interface, channel=channel, **kwargs)``; ``virtual``: a
    :class:`LightVirtualBus` (module docstring).

    Raises:
        can.CanError, OSError, ValueError, ImportError: as ``can.Bus``.
    """
    if interface == 'virtual':
        return LightVirtualBus(channel=channel, **kwargs)
    bus: can.BusABC = can.Bus(interface=interface, channel=channel, **kwargs)
    return bus

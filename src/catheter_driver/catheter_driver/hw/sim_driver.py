"""Simulated sleeve driver on a python-can virtual bus (the device's twin).

It behaves like the driver's controller board: it receives DRV_COMMAND / DRV_ESTOP, drives a
:class:`~catheter_driver.core.mechanism.SleeveMechanism` and answers DRV_STATUS at ``rate_hz``.
Its own safety: the sleeve stops when no command arrives within ``command_timeout`` s, and the
e-stop latch holds the sleeve and freezes the valves.

Fault injection: :meth:`SimulatedDriver.disconnect` (goes silent and deaf, like a pulled cable),
:meth:`SimulatedDriver.set_stall` (the sleeve motor does not move), and
:meth:`SimulatedDriver.inject_garbage` (malformed frames on the status id and unknown ids).

python-can's ``virtual`` interface only connects buses in the same process, so the console
script ``sim_driver`` runs the simulated driver together with a host-side relay loop and prints
the state; the driver node starts one in-process with ``simulate_device:=true``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import threading
import time

import can
import numpy as np

from catheter_driver.core.mechanism import SleeveMechanism
from catheter_driver.core.relay import ActuatorCommand, RelayConfig
from catheter_driver.exceptions import ProtocolError
from catheter_driver.hw.can_protocol import (
    COMMAND_ID,
    DriverCodec,
    DriverStatus,
    ESTOP_ID,
    STATUS_ID,
)
from cgail_node_utils.virtual_can import open_bus


class SimulatedDriver:
    """The simulated driver board. Use :meth:`start`/:meth:`stop` (or ``with``) for the
    background thread, or call :meth:`step` directly for deterministic tests."""

    def __init__(self, channel: str = 'sleeve_driver', *, config: RelayConfig | None = None,
                 rate_hz: float = 100.0, command_timeout: float = 0.2,
                 codec: DriverCodec | None = None, seed: int = 0) -> None:
        """Create the driver and open its virtual bus.

        Args:
            channel: python-can virtual channel name.
            config: mechanism geometry and gripper timings.
            rate_hz: status rate (and simulation step rate), Hz.
            command_timeout: sleeve stops after this long without DRV_COMMAND, s.
            codec: frame codec (default: from ``driver.dbc``).
            seed: seed of the garbage generator.
        """
        if not rate_hz > 0.0:
            raise ValueError(f'rate_hz must be > 0, found {rate_hz!r}')
        if not command_timeout > 0.0:
            raise ValueError(f'command_timeout must be > 0, found {command_timeout!r}')
        self.config = config or RelayConfig()
        self.mechanism = SleeveMechanism(self.config)
        self.codec = codec or DriverCodec()
        self.rate_hz = rate_hz
        self.command_timeout = command_timeout
        self._bus = open_bus('virtual', channel, receive_own_messages=False)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._command = ActuatorCommand(0.0, False, True)
        self._since_command = float('inf')
        self._stopped = False
        self._connected = True
        self._counter = 0
        self.commands_received = 0
        self.bad_frames = 0
        self._thread: threading.Thread | None = None
        self._running = threading.Event()

    # -- fault injection ---------------------------------------------------------------------

    def disconnect(self) -> None:
        """Pull the cable: no status frames, incoming frames dropped. The board keeps running,
        so the sleeve stops only when its command watchdog expires."""
        with self._lock:
            self._connected = False

    def reconnect(self) -> None:
        """Undo :meth:`disconnect`."""
        with self._lock:
            self._connected = True

    def set_stall(self, stalled: bool) -> None:
        """Block the sleeve motor (it reports Stall while commanded to move)."""
        with self._lock:
            self.mechanism.stalled = stalled

    def inject_garbage(self, count: int = 10) -> None:
        """Send ``count`` malformed frames: short status frames, status frames with an
        implausible position, and random ids."""
        for i in range(count):
            kind = i % 3
            if kind == 0:
                short = self._rng.integers(0, 256, int(self._rng.integers(0, 8))).tobytes()
                msg = can.Message(arbitration_id=STATUS_ID, data=short, is_extended_id=False)
            elif kind == 1:
                wild = bytearray(self._rng.integers(0, 256, 8).tobytes())
                wild[3] = 0x7F  # SleevePosition > 2e6 mm
                msg = can.Message(arbitration_id=STATUS_ID, data=bytes(wild),
                                  is_extended_id=False)
            else:
                msg = can.Message(arbitration_id=int(self._rng.integers(0x300, 0x7FF)),
                                  data=self._rng.integers(0, 256, 8).tobytes(),
                                  is_extended_id=False)
            self._bus.send(msg)

    # -- simulation --------------------------------------------------------------------------

    def step(self, dt: float) -> DriverStatus | None:
        """Handle pending frames, advance the mechanism by ``dt`` and send a status frame.

        Returns:
            The status sent, or None while disconnected.
        """
        with self._lock:
            self._receive()
            mech = self.mechanism
            self._since_command += dt
            timed_out = self._since_command > self.command_timeout
            velocity = self._command.sleeve_velocity
            if timed_out or self._stopped:
                velocity = 0.0
            mech.step(ActuatorCommand(velocity, self._command.moving_close,
                                      self._command.fixed_close), dt)
            if not self._connected:  # cable pulled: the board runs on, the host hears nothing
                return None
            status = DriverStatus(
                sleeve_position=mech.sleeve_position, sleeve_velocity=mech.sleeve_velocity,
                moving=mech.moving.state, fixed=mech.fixed.state, stopped=self._stopped,
                stall=mech.stalled and velocity != 0.0, interlock=mech.interlock,
                command_timeout=timed_out, counter=self._counter)
            self._counter = (self._counter + 1) & 0xFF
            self._bus.send(self.codec.encode_status(status))
            return status

    def _receive(self) -> None:
        while (msg := self._bus.recv(timeout=0.0)) is not None:
            if not self._connected:
                continue
            try:
                if msg.arbitration_id == COMMAND_ID:
                    cmd = self.codec.decode_command(msg)
                    if not self._stopped:  # the e-stop latch freezes the valves too
                        self._command = ActuatorCommand(cmd.sleeve_velocity, cmd.moving_close,
                                                        cmd.fixed_close)
                    self._since_command = 0.0
                    self.commands_received += 1
                elif msg.arbitration_id == ESTOP_ID:
                    self._stopped = self.codec.decode_stop(msg)
            except ProtocolError:
                self.bad_frames += 1

    # -- thread ------------------------------------------------------------------------------

    def start(self) -> SimulatedDriver:
        """Run :meth:`step` at ``rate_hz`` in a daemon thread."""
        if self._thread is None:
            self._running.set()
            self._thread = threading.Thread(target=self._run, name='sim_driver', daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the bus (idempotent)."""
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._bus.shutdown()

    def __enter__(self) -> SimulatedDriver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_time = time.monotonic()
        while self._running.is_set():
            self.step(period)
            next_time += period
            delay = next_time - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_time = time.monotonic()


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``sim_driver``: simulated driver + host relay loop on a virtual bus."""
    from catheter_driver.core.relay import RelayController, SleeveFeedback
    from catheter_driver.hw.can_protocol import DriverCommand
    from catheter_driver.hw.driver_link import CanDriverLink

    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--channel', default='sleeve_driver_demo')
    parser.add_argument('--velocity', type=float, default=0.005,
                        help='catheter velocity command, m/s (capped at 0.005)')
    parser.add_argument('--duration', type=float, default=20.0, help='seconds to run')
    parser.add_argument('--rate', type=float, default=50.0, help='host control rate, Hz')
    parser.add_argument('--stall-at', type=float, default=None,
                        help='inject a sleeve stall at this time, s')
    parser.add_argument('--disconnect-at', type=float, default=None,
                        help='pull the (virtual) cable at this time for 1 s')
    args = parser.parse_args(argv)
    codec = DriverCodec()
    with SimulatedDriver(args.channel, codec=codec) as sim:
        link = CanDriverLink.open('virtual', args.channel, codec)
        controller: RelayController | None = None
        dt = 1.0 / args.rate
        start = time.monotonic()
        last_print = -1.0
        try:
            while (t := time.monotonic() - start) < args.duration:
                if args.stall_at is not None:
                    sim.set_stall(t >= args.stall_at)
                if args.disconnect_at is not None:
                    if args.disconnect_at <= t < args.disconnect_at + 1.0:
                        sim.disconnect()
                    else:
                        sim.reconnect()
                status = link.poll()
                if status is not None:
                    fb = SleeveFeedback(status.sleeve_position, status.moving, status.fixed)
                    if controller is None:
                        controller = RelayController(RelayConfig(), fb)
                    cmd = controller.step(args.velocity, fb, dt)
                    link.send_command(DriverCommand(cmd.sleeve_velocity, cmd.moving_close,
                                                    cmd.fixed_close))
                    if t - last_print >= 0.5:
                        last_print = t
                        print(f't={t:6.2f} s  phase={controller.phase.name:<12} '
                              f'catheter={controller.position * 1e3:7.2f} mm  '
                              f'sleeve={status.sleeve_position * 1e3:6.2f} mm  '
                              f'moving={status.moving.name:<7} fixed={status.fixed.name:<7} '
                              f'stall={int(status.stall)} timeout={int(status.command_timeout)}',
                              flush=True)
                time.sleep(dt)
        except KeyboardInterrupt:
            pass
        finally:
            link.close()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())

"""Simulated regulator bank: the device side of the PAM CAN message set.

Four pressure regulators with first-order dynamics ``tau * dp/dt = sp - p`` (exact
discretisation), outputs saturated to ``[0, supply_pressure_pa]``; it decodes
``PAM_SETPOINTS``/``PAM_HOST_HEARTBEAT`` and sends ``PAM_MEASURED`` (every 10 ms) and
``PAM_STATUS`` (every 100 ms) on the same python-can bus as the host. It vents on its own when
the host heartbeat stops (``FAULT_HOST_TIMEOUT``).

Fault injection: :meth:`SimRegulatorBank.set_stuck` (a regulator frozen at its pressure, flagged
``FAULT_STUCK`` once its setpoint has been more than ``stuck_detect_pa`` away for
``stuck_detect_s``), :meth:`SimRegulatorBank.set_silent` (bus silence /
disconnect: nothing sent, nothing read), :meth:`SimRegulatorBank.send_garbage` (random frames,
on our ids and others), :meth:`SimRegulatorBank.set_supply_pressure`.

**When a stuck regulator becomes observable.** A stuck regulator that is asked for the
pressure it holds delivers exactly that: nothing on the bus, and no sensor, tells it from a
healthy one. Nor does a short tracking error: a healthy regulator lags a ramp by
``rate * time_constant_s`` (48 kPa at ``pam_controller``'s 600 kPa/s slew limit and 80 ms),
which is why the bank flags only an error that lasts ``stuck_detect_s``. The bank records, per
stuck channel, when its tracking error first exceeded ``stuck_detect_pa``
(:meth:`SimRegulatorBank.stuck_error_at`) and when the first excursion beyond it that lasted
``stuck_detect_s`` began (:meth:`SimRegulatorBank.stuck_observable_at`: the excursion it flags
``FAULT_STUCK`` for, ``stuck_detect_s`` later): the moment a stuck chamber became observable,
from which a supervisor's detection time is measured (``cgail_rig.core.faults``). Recording
them changes nothing the bank does.

Drive it either with :meth:`step` (deterministic, explicit ``dt``; tests) or :meth:`start`
(a background thread on the wall clock; the node's ``simulate_regulators`` and ``main``).
python-can's ``virtual`` interface only connects buses of the same process: across processes
use a real or vcan ``socketcan`` channel (``--interface socketcan --channel vcan0``).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
import math
import threading
import time

import can
import numpy as np
from numpy.typing import NDArray

from cgail_node_utils.virtual_can import open_bus
from pam_controller.core.supervisor import BankMode
from pam_controller.errors import ProtocolError
from pam_controller.hw import can_protocol as proto

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SimRegulatorConfig:
    """Simulated bank settings."""

    interface: str = 'virtual'
    """python-can interface of the bus the bank sits on."""
    channel: str = 'pam0'
    """python-can channel name (must match the host's)."""
    time_constant_s: float = 0.08
    """First-order time constant of each regulator, s (estimate for a proportional valve
    filling a few cm^3 of PAM). In (0, 10]."""
    supply_pressure_pa: float = 350e3
    """Supply pressure: no chamber exceeds it, Pa. In (0, 399.5e3]."""
    max_setpoint_pa: float = 400e3
    """The bank's own setpoint limit, Pa: setpoints above are clipped and flagged
    ``FAULT_OVERPRESSURE``. In (0, 409.5e3]."""
    host_timeout_s: float = 0.5
    """No valid host heartbeat for this long: vent and flag ``FAULT_HOST_TIMEOUT``, s."""
    stuck_detect_pa: float = 20e3
    """Tracking error that counts as a stuck regulator, Pa."""
    stuck_detect_s: float = 0.5
    """How long the tracking error must last to flag ``FAULT_STUCK``, s."""
    measured_period_s: float = 0.01
    """Period of ``PAM_MEASURED``, s."""
    status_period_s: float = 0.1
    """Period of ``PAM_STATUS``, s."""
    step_period_s: float = 0.002
    """Wall-clock step of the background thread, s."""

    def __post_init__(self) -> None:
        checks = {
            'time_constant_s': (self.time_constant_s, 0.0, 10.0),
            'supply_pressure_pa': (self.supply_pressure_pa, 0.0, proto.MEASURED_MAX_KPA * 1e3),
            'max_setpoint_pa': (self.max_setpoint_pa, 0.0, proto.SETPOINT_MAX_KPA * 1e3),
            'host_timeout_s': (self.host_timeout_s, 0.0, 60.0),
            'stuck_detect_pa': (self.stuck_detect_pa, 0.0, 400e3),
            'stuck_detect_s': (self.stuck_detect_s, 0.0, 60.0),
            'measured_period_s': (self.measured_period_s, 0.0, 1.0),
            'status_period_s': (self.status_period_s, 0.0, 10.0),
            'step_period_s': (self.step_period_s, 0.0, 0.1),
        }
        for name, (value, lo, hi) in checks.items():
            if not (math.isfinite(value) and lo < value <= hi):
                raise ValueError(f'{name} must be in ({lo}, {hi}], found {value}')
        if not self.channel:
            raise ValueError('channel must be a non-empty string, found empty')


class SimRegulatorBank:
    """Simulated bank on a python-can bus (see the module docstring).

    Args:
        config: settings.
        seed: seed of the garbage-frame generator.
    """

    def __init__(self, config: SimRegulatorConfig | None = None, seed: int = 0) -> None:
        self.config = config if config is not None else SimRegulatorConfig()
        self._bus = open_bus(self.config.interface, self.config.channel,
                             receive_own_messages=False)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self.pressures_pa = np.zeros(4)
        self.setpoints_pa = np.zeros(4)
        self.mode = BankMode.IDLE
        self.supply_pressure_pa = self.config.supply_pressure_pa
        self.time_s = 0.0
        self._last_heartbeat: float | None = None
        self._stuck = np.zeros(4, dtype=bool)
        self._track_error_since = np.full(4, np.nan)
        # per channel, bank time (NaN: none) of the last set_stuck, of the stuck channel's first
        # tracking error beyond stuck_detect_pa and of the start of its first one that lasted
        # stuck_detect_s (stuck_error_at, stuck_observable_at)
        self._stuck_at = [math.nan] * 4
        self._stuck_error_at = [math.nan] * 4
        self._stuck_observable_at = [math.nan] * 4
        self._faults: set[str] = set()
        self._channel_fault_mask = 0
        self._bad_frame_seen = False
        self._silent = False
        self._next_measured = 0.0
        self._next_status = 0.0
        self._counters = {'measured': 0, 'status': 0}
        self.bad_frames_received = 0
        self.setpoint_frames_received = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ---- fault injection -------------------------------------------------------------
    def set_stuck(self, channel: int, stuck: bool = True) -> None:
        """Freeze (or free) regulator ``channel`` (0..3) at its current pressure.

        Freezing a channel that was not stuck starts its records afresh
        (:meth:`stuck_error_at`, :meth:`stuck_observable_at`); freeing it keeps them.
        """
        if not 0 <= channel < 4:
            raise ValueError(f'channel must be in 0..3, found {channel}')
        with self._lock:
            if stuck and not self._stuck[channel]:
                self._stuck_at[channel] = self.time_s
                self._stuck_error_at[channel] = math.nan
                self._stuck_observable_at[channel] = math.nan
            self._stuck[channel] = stuck

    def stuck_error_at(self, channel: int) -> float | None:
        """Bank time (:attr:`time_s`, s) of the first step at which stuck regulator ``channel``
        was more than ``stuck_detect_pa`` off its target since it was frozen (None: not yet).

        A short error is also what a healthy regulator shows on a ramp (module docstring); the
        moment the stuck channel became observable is :meth:`stuck_observable_at`.
        """
        if not 0 <= channel < 4:
            raise ValueError(f'channel must be in 0..3, found {channel}')
        with self._lock:
            t = self._stuck_error_at[channel]
        return None if math.isnan(t) else t

    def stuck_observable_at(self, channel: int) -> float | None:
        """Bank time (:attr:`time_s`, s) at which stuck regulator ``channel`` became observable:
        the start of the first tracking error beyond ``stuck_detect_pa`` that lasted
        ``stuck_detect_s`` while it was stuck, i.e. the error the bank flags ``FAULT_STUCK`` for
        (``stuck_detect_s`` after this time; an error already running at the freeze counts from
        the freeze).

        None: not observable (yet). It is known only once the error has lasted
        ``stuck_detect_s``; a stuck regulator asked only for pressures within
        ``stuck_detect_pa`` of the one it holds, or away from it only briefly, never becomes
        observable.
        """
        if not 0 <= channel < 4:
            raise ValueError(f'channel must be in 0..3, found {channel}')
        with self._lock:
            t = self._stuck_observable_at[channel]
        return None if math.isnan(t) else t

    def set_silent(self, silent: bool = True) -> None:
        """Bus silence / disconnect: while silent the bank neither reads nor sends."""
        with self._lock:
            self._silent = silent

    def set_supply_pressure(self, pressure_pa: float) -> None:
        """Change the supply pressure (e.g. to provoke ``FAULT_SUPPLY_LOW``)."""
        with self._lock:
            self.supply_pressure_pa = float(pressure_pa)

    def send_garbage(self, count: int) -> None:
        """Send ``count`` random frames: random bytes and lengths on our ids and on others."""
        ids = [*sorted(proto.KNOWN_IDS), 0x123, 0x7FF]
        for _ in range(count):
            aid = int(self._rng.choice(ids))
            dlc = int(self._rng.integers(0, 9))
            data = bytes(self._rng.integers(0, 256, dlc, dtype=np.uint8).tolist())
            self._bus.send(can.Message(arbitration_id=aid, data=data, is_extended_id=False))

    # ---- simulation --------------------------------------------------------------------
    def _handle(self, msg: can.Message) -> None:
        try:
            decoded = proto.decode(msg)
        except ProtocolError:
            self.bad_frames_received += 1
            self._bad_frame_seen = True
            return
        if isinstance(decoded, proto.HostHeartbeat):
            self._last_heartbeat = self.time_s
            self._faults.discard('FAULT_HOST_TIMEOUT')
            if decoded.mode is BankMode.CLEAR_FAULTS:
                self._faults.clear()
                self._channel_fault_mask = 0
                self._track_error_since[:] = np.nan
                self.mode = BankMode.IDLE
            else:
                self.mode = decoded.mode
        elif isinstance(decoded, proto.Setpoints):
            self.setpoint_frames_received += 1
            sp = decoded.pressures_pa
            if (sp > self.config.max_setpoint_pa).any():
                self._faults.add('FAULT_OVERPRESSURE')
            self.setpoints_pa = sp.clip(0.0, self.config.max_setpoint_pa)

    def _state(self) -> proto.BankState:
        if self._channel_fault_mask:
            return proto.BankState.FAULT
        if self._last_heartbeat is None:
            return proto.BankState.INIT
        if 'FAULT_HOST_TIMEOUT' in self._faults or self.mode is BankMode.VENT:
            return proto.BankState.VENTING
        return proto.BankState.ACTIVE if self.mode is BankMode.RUN else proto.BankState.READY

    def step(self, dt: float) -> None:
        """Advance the simulation by ``dt`` seconds: read frames, integrate, send frames."""
        with self._lock:
            self.time_s += dt
            if not self._silent:
                while (msg := self._bus.recv(timeout=0.0)) is not None:
                    self._handle(msg)
            cfg = self.config
            supply = self.supply_pressure_pa
            run = self.mode is BankMode.RUN
            if (self._last_heartbeat is None
                    or self.time_s - self._last_heartbeat > cfg.host_timeout_s):
                if self._last_heartbeat is not None:
                    self._faults.add('FAULT_HOST_TIMEOUT')
                target = [0.0] * 4
            elif run:
                target = self.setpoints_pa.tolist()
            else:
                target = [0.0] * 4
            # per channel in Python floats (four channels: numpy's per-call cost dominated);
            # the same IEEE operations in the same order as the array form
            target = [min(t, supply) for t in target]
            if run and max(self.setpoints_pa.tolist()) > supply:
                self._faults.add('FAULT_SUPPLY_LOW')
            alpha = 1.0 - math.exp(-dt / cfg.time_constant_s)
            now = self.time_s
            pressures, since = self.pressures_pa.tolist(), self._track_error_since.tolist()
            late_mask = 0
            for i, (t, p, stuck) in enumerate(zip(target, pressures, self._stuck.tolist(),
                                                  strict=True)):
                if not stuck:
                    p = min(max(p + alpha * (t - p), 0.0), supply)
                    pressures[i] = p
                if abs(t - p) > cfg.stuck_detect_pa:  # off target: since when (NaN: now)
                    if since[i] != since[i]:
                        since[i] = now
                    if now - since[i] >= cfg.stuck_detect_s:
                        late_mask |= 1 << i
                        if stuck and self._stuck_observable_at[i] != self._stuck_observable_at[i]:
                            self._stuck_observable_at[i] = max(since[i], self._stuck_at[i])
                    if stuck and self._stuck_error_at[i] != self._stuck_error_at[i]:
                        self._stuck_error_at[i] = now
                else:
                    since[i] = math.nan  # on target
            self.pressures_pa = np.array(pressures)
            self._track_error_since = np.array(since)
            if late_mask:
                self._faults.add('FAULT_STUCK')
                self._channel_fault_mask |= late_mask
            if self._silent:
                return
            if self.time_s + 1e-12 >= self._next_measured:
                self._next_measured = self.time_s + cfg.measured_period_s
                self._bus.send(proto.encode_measured(self.pressures_pa,
                                                     self._counters['measured']))
                self._counters['measured'] += 1
            if self.time_s + 1e-12 >= self._next_status:
                self._next_status = self.time_s + cfg.status_period_s
                faults = set(self._faults)
                if self._bad_frame_seen:
                    faults.add('FAULT_BAD_FRAME')
                    self._bad_frame_seen = False
                self._bus.send(proto.encode_status(
                    self._state(), faults, self._channel_fault_mask, self.supply_pressure_pa,
                    self._counters['status']))
                self._counters['status'] += 1

    @property
    def faults(self) -> frozenset[str]:
        """Latched faults (without the transient ``FAULT_BAD_FRAME``)."""
        with self._lock:
            return frozenset(self._faults)

    def start(self) -> None:
        """Run :meth:`step` on the wall clock in a daemon thread."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name='sim_regulators', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(self.config.step_period_s):
            now = time.monotonic()
            self.step(now - last)
            last = now

    def stop(self) -> None:
        """Stop the thread (if any) and shut the bus down."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=2.0)
            self._thread = None
        self._bus.shutdown()


def main(argv: list[str] | None = None) -> int:
    """Console script ``sim_regulators``: run a simulated bank until Ctrl-C or ``--duration``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--interface', default='virtual', help='python-can interface')
    parser.add_argument('--channel', default='pam0', help='python-can channel')
    parser.add_argument('--time-constant', type=float, default=0.08, help='regulator tau, s')
    parser.add_argument('--supply', type=float, default=350e3, help='supply pressure, Pa')
    parser.add_argument('--garbage-rate', type=float, default=0.0,
                        help='random frames per second to inject (fault test)')
    parser.add_argument('--duration', type=float, default=0.0, help='s; 0 = until Ctrl-C')
    args = parser.parse_args(argv)
    cfg = SimRegulatorConfig(interface=args.interface, channel=args.channel,
                             time_constant_s=args.time_constant,
                             supply_pressure_pa=args.supply)
    bank = SimRegulatorBank(cfg)
    bank.start()
    print(f'sim_regulators on {cfg.interface}:{cfg.channel} (tau {cfg.time_constant_s} s, '
          f'supply {cfg.supply_pressure_pa / 1e3:.0f} kPa)', flush=True)
    t0 = time.monotonic()
    try:
        while args.duration <= 0.0 or time.monotonic() - t0 < args.duration:
            time.sleep(1.0)
            if args.garbage_rate > 0.0:
                bank.send_garbage(int(args.garbage_rate))
            print(f'mode {bank.mode.name} pressures_kpa '
                  f'{np.round(bank.pressures_pa / 1e3, 1).tolist()} faults '
                  f'{sorted(bank.faults)}', flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        bank.stop()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())

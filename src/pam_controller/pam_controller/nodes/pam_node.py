"""pam_controller node: bend commands -> four PAM pressures over CAN, measured bend back.

Lifecycle node (``main`` configures and activates it unless ``autostart`` is false, which leaves
it unconfigured for a lifecycle manager). Topics, QoS and parameters: see
``docs/interfaces.md``; the topics are the node's own (``~/bend_command``, ``~/pressures``,
``~/bend_state``), remapped to the rig's names by its launch files. All maths and safety rules
live in ``core/`` (``BendingModel``, ``PamSupervisor``) and the CAN protocol in ``hw/``; this
file only wires them to ROS.

Parameters are validated in the constructor (bad values raise ``ValueError``) and read again at
configure: a change is accepted only while the node is unconfigured; in any other state
``set_parameters`` answers ``successful=False`` with the reason
(:mod:`cgail_node_utils.parameters`). ``autostart`` is read-only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
import math

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rclpy.service import Service
from rclpy.subscription import Subscription
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Header
from std_srvs.srv import SetBool

from cgail_node_utils.entry_point import run_node, start_lifecycle
from cgail_node_utils.parameters import AUTOSTART_DESCRIPTION, configure_time_guard, descriptor
from pam_controller.core.bending_model import (
    BendingModel,
    BendingModelConfig,
    GAIN_SCALE_RANGE,
    MAX_BEND_OFFSET_RAD,
    MAX_COUPLING,
)
from pam_controller.core.hysteresis import HysteresisConfig
from pam_controller.core.supervisor import (
    Backoff,
    BankMode,
    PamSupervisor,
    Phase,
    SupervisorConfig,
)
from pam_controller.errors import CommandRejectedError, DeviceUnavailableError
from pam_controller.hw import can_protocol as proto
from pam_controller.hw.regulator_bank import CanRegulatorBank, LinkConfig
from pam_controller.hw.sim_regulators import SimRegulatorBank, SimRegulatorConfig
from pam_controller.nodes import conversions as conv

COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
DIAGNOSTICS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
ERROR_FAULTS = frozenset({'FAULT_STUCK', 'FAULT_OVERPRESSURE'})

# name: (default, description, (low, high) or None). Defaults equal the dataclass defaults.
PARAMETERS: dict[str, tuple[object, str, tuple[float, float] | None]] = {
    'can_interface': ('virtual', 'python-can interface: virtual (simulated rig) or socketcan',
                      None),
    'can_channel': ('pam0', 'python-can channel (e.g. can0 on the rig)', None),
    'can_bitrate': (1_000_000, 'CAN bit rate, bit/s (ignored by virtual)', (10_000, 1_000_000)),
    'simulate_regulators': (True, 'run a simulated regulator bank in-process on the channel',
                            None),
    'sim_time_constant_s': (0.08, 'simulated regulator time constant, s', (0.001, 10.0)),
    'control_rate_hz': (50.0, 'control loop rate: setpoints sent, frames read, s^-1',
                        (1.0, 500.0)),
    'heartbeat_period_s': (0.1, 'host heartbeat period, s (bank vents after 0.5 s without)',
                           (0.01, 0.4)),
    'diagnostics_period_s': (0.5, 'period of /diagnostics, s', (0.05, 10.0)),
    'device_timeout_s': (0.3, 'no measured frame for this long = disconnected, s', (0.02, 10.0)),
    'reconnect_initial_s': (0.2, 'first reconnect delay (doubles), s', (0.001, 60.0)),
    'reconnect_max_s': (5.0, 'largest reconnect delay, s', (0.001, 600.0)),
    'command_timeout_s': (0.5, 'watchdog: vent when the last command is older, s', (0.01, 60.0)),
    'max_pressure_rate_pa_s': (600e3, 'setpoint slew limit per chamber, Pa/s', (1.0, 1e7)),
    'vent_pressure_pa': (0.0, 'safe pressure on watchdog / e-stop, Pa gauge', (0.0, 400e3)),
    'min_pressure_pa': (0.0, 'lowest chamber pressure ever commanded, Pa', (0.0, 400e3)),
    'max_pressure_pa': (300e3, 'pressure cap: highest chamber pressure ever commanded, Pa',
                        (1.0, 400e3)),
    'bias_pressure_pa': (150e3, 'common-mode pressure of each antagonistic pair, Pa',
                         (0.0, 400e3)),
    'max_bend_rad': (math.pi / 2, 'bend cap: largest hypot(alpha, gamma) accepted, rad',
                     (1e-3, math.pi / 2)),
    'hysteresis_gain_rad_per_pa': (2 * math.pi * 1e-6, 'bend per differential pressure, rad/Pa',
                                   (1e-9, 1e-3)),
    'hysteresis_fraction': (0.5, 'share of the gain in the play operators', (0.0, 0.95)),
    'hysteresis_play_count': (8, 'number of play operators', (1, 64)),
    'hysteresis_max_threshold_pa': (100e3, 'largest play threshold, Pa', (1.0, 400e3)),
    'hysteresis_density_decay': (1.0, 'exponential decay of play weights', (0.0, 20.0)),
    'bend_offset_alpha_rad': (0.0, 'alpha bend at zero differential pressure (unequal '
                              'muscles), rad', (-MAX_BEND_OFFSET_RAD, MAX_BEND_OFFSET_RAD)),
    'bend_offset_gamma_rad': (0.0, 'gamma bend at zero differential pressure (unequal '
                              'muscles), rad', (-MAX_BEND_OFFSET_RAD, MAX_BEND_OFFSET_RAD)),
    'gain_scale_alpha': (1.0, 'alpha axis gain, share of hysteresis_gain_rad_per_pa',
                         GAIN_SCALE_RANGE),
    'gain_scale_gamma': (1.0, 'gamma axis gain, share of hysteresis_gain_rad_per_pa',
                         GAIN_SCALE_RANGE),
    'coupling_alpha_from_gamma': (0.0, 'alpha bend per unit of the gamma operator output '
                                  '(cross-coupling); det K >= 0.5 s_alpha s_gamma',
                                  (-MAX_COUPLING, MAX_COUPLING)),
    'coupling_gamma_from_alpha': (0.0, 'gamma bend per unit of the alpha operator output '
                                  '(cross-coupling); det K >= 0.5 s_alpha s_gamma',
                                  (-MAX_COUPLING, MAX_COUPLING)),
    'autostart': (True, AUTOSTART_DESCRIPTION, None),
}
#: Parameters fixed for the node's life (the others are read at configure).
_READ_ONLY = frozenset({'autostart'})
_CONFIGURE_TIME = tuple(name for name in PARAMETERS if name not in _READ_ONLY)


class _Params:
    """The declared parameter values, read back with the type each configuration field wants
    (the declaration already enforced it; a mismatch here is a programming error)."""

    def __init__(self, values: dict[str, object]) -> None:
        self.values = values

    def _wrong(self, name: str, kind: str) -> ValueError:
        return ValueError(f'{name}: expected {kind}, found {self.values[name]!r}')

    def real(self, name: str) -> float:
        """A double parameter (an integer default is accepted)."""
        value = self.values[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self._wrong(name, 'a number')
        return float(value)

    def integer(self, name: str) -> int:
        """An integer parameter."""
        value = self.values[name]
        if isinstance(value, bool) or not isinstance(value, int):
            raise self._wrong(name, 'an integer')
        return value

    def text(self, name: str) -> str:
        """A string parameter."""
        value = self.values[name]
        if not isinstance(value, str):
            raise self._wrong(name, 'a string')
        return value

    def flag(self, name: str) -> bool:
        """A bool parameter."""
        value = self.values[name]
        if not isinstance(value, bool):
            raise self._wrong(name, 'a bool')
        return value


@dataclass(frozen=True)
class PamSettings:
    """What the node builds from its parameters (:func:`build_settings`)."""

    model: BendingModelConfig
    """Bending model and pressure / bend caps."""
    supervisor: SupervisorConfig
    """Watchdog, slew limit and vent pressure."""
    link: LinkConfig
    """CAN link to the regulator bank."""
    sim: SimRegulatorConfig | None
    """The in-process simulated bank, or None (``simulate_regulators: false``)."""
    control_period_s: float
    """Period of the control loop, s."""
    diagnostics_period_s: float
    """Period of /diagnostics, s."""


def build_settings(values: Mapping[str, object]) -> PamSettings:
    """The :class:`PamSettings` of the parameter values ``{name: value}``.

    Raises:
        ValueError: a value out of range or inconsistent.
    """
    p = _Params(dict(values))
    hyst = HysteresisConfig(
        gain=p.real('hysteresis_gain_rad_per_pa'),
        hysteresis_fraction=p.real('hysteresis_fraction'),
        play_count=p.integer('hysteresis_play_count'),
        max_threshold=p.real('hysteresis_max_threshold_pa'),
        density_decay=p.real('hysteresis_density_decay'))
    model = BendingModelConfig(
        min_pressure_pa=p.real('min_pressure_pa'), max_pressure_pa=p.real('max_pressure_pa'),
        bias_pressure_pa=p.real('bias_pressure_pa'), max_bend_rad=p.real('max_bend_rad'),
        hysteresis=hyst,
        bend_offset_rad=(p.real('bend_offset_alpha_rad'), p.real('bend_offset_gamma_rad')),
        gain_scale=(p.real('gain_scale_alpha'), p.real('gain_scale_gamma')),
        coupling=(p.real('coupling_alpha_from_gamma'), p.real('coupling_gamma_from_alpha')))
    supervisor = SupervisorConfig(
        command_timeout_s=p.real('command_timeout_s'),
        max_pressure_rate_pa_s=p.real('max_pressure_rate_pa_s'),
        vent_pressure_pa=p.real('vent_pressure_pa'))
    link = LinkConfig(
        interface=p.text('can_interface'), channel=p.text('can_channel'),
        bitrate=p.integer('can_bitrate'), heartbeat_period_s=p.real('heartbeat_period_s'),
        device_timeout_s=p.real('device_timeout_s'),
        reconnect_initial_s=p.real('reconnect_initial_s'),
        reconnect_max_s=p.real('reconnect_max_s'))
    sim = SimRegulatorConfig(interface=link.interface, channel=link.channel,
                             time_constant_s=p.real('sim_time_constant_s')) \
        if p.flag('simulate_regulators') else None
    # Checks the vent pressure against the limits now, so a bad one raises here.
    PamSupervisor(BendingModel(model), supervisor, 0.0)
    return PamSettings(model=model, supervisor=supervisor, link=link, sim=sim,
                       control_period_s=1.0 / p.real('control_rate_hz'),
                       diagnostics_period_s=p.real('diagnostics_period_s'))


class PamNode(LifecycleNode):
    """Node ``pam_controller`` (see the module docstring).

    Raises:
        ValueError: a parameter out of range or inconsistent (at construction).
    """

    def __init__(self, **kwargs: object) -> None:
        super().__init__('pam_controller', **kwargs)  # type: ignore[arg-type]
        for name, (default, description, bounds) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor(
                name, description, default=default, bounds=bounds,
                read_only=name in _READ_ONLY))
        self.autostart = bool(self.get_parameter('autostart').value)
        self.sim: SimRegulatorBank | None = None
        self._apply(build_settings(self._parameter_values()))
        self.add_on_set_parameters_callback(
            configure_time_guard(self, _CONFIGURE_TIME, build_settings))
        self._active = False
        self._timers: list = []
        self._lifecycle_pubs: list = []
        self._sub_command: Subscription | None = None
        self._srv_estop: Service | None = None
        self._reset_link_state()

    def _parameter_values(self) -> dict[str, object]:
        return {name: self.get_parameter(name).value for name in _CONFIGURE_TIME}

    def _apply(self, settings: PamSettings) -> None:
        """Take ``settings``: configurations, supervisor, (closed) bank and backoff."""
        self.model_config = settings.model
        self.supervisor_config = settings.supervisor
        self.link = settings.link
        self.sim_config = settings.sim
        self.control_period_s = settings.control_period_s
        self.diagnostics_period_s = settings.diagnostics_period_s
        self.supervisor = PamSupervisor(BendingModel(self.model_config), self.supervisor_config,
                                        conv.node_seconds(self))
        self.bank = CanRegulatorBank(self.link.interface, self.link.channel, self.link.bitrate)
        self.backoff = Backoff(self.link.reconnect_initial_s, self.link.reconnect_max_s)

    def _reset_link_state(self) -> None:
        self.last_rx: float | None = None
        self.opened_at: float | None = None
        self.link_error = 'not connected yet'
        self.measured_pa = np.full(4, np.nan)
        self.bend_estimate = np.full(2, np.nan)
        # refilled per publish (conv.bend_to_joint_state's out)
        self._pressures_msg: Float64MultiArray | None = None
        self._bend_msg: JointState | None = None
        self.bank_status: proto.Status | None = None
        self.bad_frames_recent = 0
        self._next_heartbeat = 0.0

    # ---- lifecycle -----------------------------------------------------------------------
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        # (valid: the guard refused any value build_settings rejects)
        self.bank.close()
        self._apply(build_settings(self._parameter_values()))
        self._reset_link_state()
        if self.sim_config is not None:
            self.sim = SimRegulatorBank(self.sim_config)
            self.sim.start()
        self.pub_pressures = self.create_lifecycle_publisher(
            Float64MultiArray, '~/pressures', qos_profile_sensor_data)
        self.pub_bend = self.create_lifecycle_publisher(
            JointState, '~/bend_state', qos_profile_sensor_data)
        self.pub_diag = self.create_lifecycle_publisher(
            DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS)
        self._lifecycle_pubs = [self.pub_pressures, self.pub_bend, self.pub_diag]
        self._sub_command = self.create_subscription(
            JointState, '~/bend_command', self._on_bend_command, COMMAND_QOS)
        self._srv_estop = self.create_service(SetBool, '~/estop', self._on_estop)
        self._timers = [self.create_timer(self.control_period_s, self._on_control_timer),
                        self.create_timer(self.diagnostics_period_s, self._on_diagnostics_timer)]
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        self.supervisor = PamSupervisor(BendingModel(self.model_config), self.supervisor_config,
                                        conv.node_seconds(self))
        self._reset_link_state()
        self._active = True
        sim = ' (simulated regulator bank in-process)' if self.sim is not None else ''
        self.get_logger().info(
            f'active on CAN {self.link.interface}:{self.link.channel}{sim}; pressure cap '
            f'{self.model_config.max_pressure_pa:.0f} Pa, bend cap '
            f'{self.model_config.max_bend_rad:.4f} rad')
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        self._active = False
        self._send_vent(BankMode.IDLE)
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self._active = False
        self._send_vent(BankMode.IDLE)
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        for timer in self._timers:
            self.destroy_timer(timer)
        self._timers = []
        for pub in self._lifecycle_pubs:
            self.destroy_lifecycle_publisher(pub)
        self._lifecycle_pubs = []
        if self._sub_command is not None:
            self.destroy_subscription(self._sub_command)
            self._sub_command = None
        if self._srv_estop is not None:
            self.destroy_service(self._srv_estop)
            self._srv_estop = None
        self.bank.close()
        if self.sim is not None:
            self.sim.stop()
            self.sim = None

    def destroy_node(self) -> None:
        if self._active:
            self._active = False
            self._send_vent(BankMode.IDLE)
        self._release()
        super().destroy_node()

    # ---- callbacks -----------------------------------------------------------------------
    def _on_bend_command(self, msg: JointState) -> None:
        if not self._active:
            return
        try:
            bend = conv.bend_from_joint_state(msg)
        except CommandRejectedError as err:
            self.supervisor.note_rejection(err)
            self._log_rejection(err)
            return
        try:
            self.supervisor.command(bend, conv.node_seconds(self))
        except CommandRejectedError as err:
            self._log_rejection(err)

    def _log_rejection(self, err: CommandRejectedError) -> None:
        self.get_logger().warning(f'bend command rejected, nothing sent: {err}',
                                  throttle_duration_sec=1.0)

    def _on_estop(self, request: SetBool.Request, response: SetBool.Response
                  ) -> SetBool.Response:
        if request.data:
            self.supervisor.engage_estop()
            self._send_vent(BankMode.VENT)
            response.message = 'e-stop engaged: chambers vented, commands refused'
        else:
            self.supervisor.release_estop()
            self._send_vent(BankMode.CLEAR_FAULTS)
            response.message = ('e-stop released, bank faults cleared: vented until the next '
                                'command')
        self.get_logger().warning(response.message)
        response.success = True
        return response

    def _send_vent(self, mode: BankMode) -> None:
        """Send ``mode`` and the vent pressures now (e-stop, deactivate, shutdown)."""
        try:
            if self.bank.is_open:
                self.bank.send_heartbeat(mode)
                self.bank.send_setpoints(np.full(4, self.supervisor_config.vent_pressure_pa))
        except DeviceUnavailableError as err:
            self._link_failed(str(err), conv.node_seconds(self))

    def _link_failed(self, reason: str, now: float) -> None:
        self.link_error = reason
        self.bank.close()
        delay = self.backoff.failed(now)
        self.get_logger().error(f'{reason}; retrying in {delay:.2f} s',
                                throttle_duration_sec=1.0)

    def _on_control_timer(self) -> None:
        if not self._active:
            return
        now = conv.node_seconds(self)
        if not self.bank.is_open and self.backoff.due(now):
            try:
                self.bank.open()
                self.opened_at = now
            except DeviceUnavailableError as err:
                self._link_failed(str(err), now)
        try:
            self._exchange(now)
        except DeviceUnavailableError as err:
            self._link_failed(str(err), now)
        if self.bank.is_open and self.opened_at is not None:
            since = max(self.last_rx or self.opened_at, self.opened_at)
            if now - since > self.link.device_timeout_s and self.backoff.due(now):
                self._link_failed(f'no frame from the regulator bank for {now - since:.2f} s '
                                  f'(device_timeout_s {self.link.device_timeout_s})', now)

    def _exchange(self, now: float) -> None:
        fb = self.bank.poll()
        if fb.bad_frames:
            self.bad_frames_recent += fb.bad_frames
            self.get_logger().warning(f'{fb.bad_frames} malformed CAN frame(s) ignored: '
                                      f'{fb.last_error}', throttle_duration_sec=1.0)
        if fb.status is not None:
            self.bank_status = fb.status
        for pressures in fb.measured:
            self.measured_pa = pressures
            self.bend_estimate = self.supervisor.model.bend_from_pressures(pressures)
        if fb.measured:
            self.last_rx = now
            self.link_error = ''
            self.backoff.succeeded()
            stamp = self.get_clock().now().to_msg()
            self._pressures_msg = conv.pressures_to_multiarray(self.measured_pa,
                                                               out=self._pressures_msg)
            self._bend_msg = conv.bend_to_joint_state(self.bend_estimate, stamp,
                                                      out=self._bend_msg)
            self.pub_pressures.publish(self._pressures_msg)
            self.pub_bend.publish(self._bend_msg)
        out = self.supervisor.tick(now)
        if not self.bank.is_open:
            return
        self.bank.send_setpoints(out.setpoints_pa)
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + self.link.heartbeat_period_s
            self.bank.send_heartbeat(out.mode)

    def _on_diagnostics_timer(self) -> None:
        if not self._active:
            return
        self.pub_diag.publish(DiagnosticArray(
            header=Header(stamp=self.get_clock().now().to_msg()), status=[self.diagnostics()]))

    def diagnostics(self) -> DiagnosticStatus:
        """The bank's DiagnosticStatus from the current state (level, message, values).

        Resets the count of malformed frames seen since the previous call.
        """
        sup, st = self.supervisor, self.bank_status
        faults = sorted(st.faults) if st is not None else []
        connected = self.last_rx is not None and not self.link_error
        if not connected and self.backoff.attempts == 0 and self.last_rx is None:
            level, msg = DiagnosticStatus.WARN, 'connecting to the regulator bank'
        elif not connected:
            level, msg = DiagnosticStatus.ERROR, f'regulator bank disconnected: {self.link_error}'
        elif st is not None and (st.state is proto.BankState.FAULT or ERROR_FAULTS & set(faults)):
            level, msg = DiagnosticStatus.ERROR, f'regulator bank fault: {", ".join(faults)}'
        elif sup.phase is Phase.ESTOP:
            level, msg = DiagnosticStatus.WARN, 'e-stop engaged: vented'
        elif sup.phase is Phase.STALE:
            level, msg = DiagnosticStatus.WARN, 'command watchdog expired: vented'
        elif faults or self.bad_frames_recent:
            level, msg = DiagnosticStatus.WARN, f'bank warnings: {faults}, ' \
                f'{self.bad_frames_recent} malformed frame(s)'
        else:
            level, msg = DiagnosticStatus.OK, f'{sup.phase.value}'
        values = [
            ('connected', connected), ('phase', sup.phase.value),
            ('estop', sup.estop_engaged),
            ('bank_state', st.state.name if st is not None else 'unknown'),
            ('faults', ','.join(faults)),
            ('channel_fault_mask', st.channel_fault_mask if st is not None else 0),
            ('supply_pressure_pa', st.supply_pressure_pa if st is not None else float('nan')),
            ('measured_pa', self.measured_pa), ('setpoints_pa', sup.setpoints_pa),
            ('target_pa', sup.target_pa), ('bend_estimate_rad', self.bend_estimate),
            ('rejected_commands', sup.rejected_count), ('last_rejection', sup.last_rejection),
            ('malformed_frames_total', self.bank.bad_frames_total),
            ('lost_frames_total', self.bank.lost_frames),
            ('reconnect_attempts', self.backoff.attempts),
            ('next_retry_s', self.backoff.seconds_to_next(conv.node_seconds(self))),
        ]
        self.bad_frames_recent = 0
        return conv.diagnostic_status('pam_controller: regulator bank',
                                      f'can:{self.link.interface}:{self.link.channel}',
                                      level, msg, values)


def main(args: list[str] | None = None) -> None:
    """Console script ``pam_node``: build the node, configure and activate it (unless
    ``autostart`` is false), spin."""
    run_node(PamNode, 'pam_node', args, start=start_lifecycle)


if __name__ == '__main__':
    main()

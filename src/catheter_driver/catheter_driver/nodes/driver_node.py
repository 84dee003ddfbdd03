"""Sleeve driver node (``sleeve_driver``): insertion velocity in, relay over CAN, state out.

Run: ``ros2 run catheter_driver driver_node`` (or ``scripts/ws driver_node`` in the pip-only
workspace); with the defaults it drives a simulated driver on a python-can virtual bus.
Topics are the node's own (``~/insertion_command`` in, ``~/insertion_state`` out, the e-stop
service ``~/estop``); the rig's launch files remap the topics to ``catheter/...``.

A lifecycle node (``rclpy.lifecycle.LifecycleNode``; ``main`` configures and activates it
unless ``autostart`` is false, which leaves it unconfigured for a lifecycle manager):

* constructor: parameters declared and validated (bad values raise ``ValueError`` here);
* ``on_configure``: the parameters are read again, the simulated driver (if any) starts, the
  CAN link is opened (a failure is retried with backoff by the control timer), lifecycle
  publishers, the command subscription, the e-stop service and the timers are created;
* ``on_activate``: insertion commands are accepted and relayed, state and diagnostics published;
* inactive (and ``on_deactivate``): commands are ignored, the sleeve is held still with both
  grippers closed (the catheter clamped) on every control tick; nothing is published;
* ``on_cleanup``: hold command, link closed, simulated driver stopped, entities destroyed;
* ``on_shutdown`` / ``on_error`` / ``destroy_node``: the same safe stop and release, in any state.

Parameters are read at configure: a change is accepted only while the node is unconfigured
(validated, applied by the next configure); in any other state ``set_parameters`` answers
``successful=False`` with the reason (:mod:`cgail_node_utils.parameters`). ``autostart`` is
read-only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.lifecycle import LifecycleNode, LifecyclePublisher, State, TransitionCallbackReturn
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool

from catheter_driver.core.relay import (
    catheter_velocity,
    RelayConfig,
    RelayController,
    SleeveFeedback,
)
from catheter_driver.core.supervision import Backoff, SupervisionConfig, Watchdog
from catheter_driver.exceptions import CommandError, DeviceDisconnectedError, ProtocolError
from catheter_driver.hw.can_protocol import DriverCodec, DriverCommand, DriverStatus
from catheter_driver.hw.driver_link import CanDriverLink
from catheter_driver.hw.sim_driver import SimulatedDriver
from catheter_driver.nodes import conversions as conv
from cgail_node_utils.entry_point import run_node, start_lifecycle
from cgail_node_utils.parameters import AUTOSTART_DESCRIPTION, configure_time_guard, declare

_R, _S = RelayConfig(), SupervisionConfig()
#: name: (default, description, (lo, hi) or None). Defaults equal the dataclass defaults.
PARAMETERS: dict[str, tuple[Any, str, tuple[float, float] | None]] = {
    'max_speed': (_R.max_speed, 'catheter speed cap, insertion and retraction, m/s',
                  (1e-6, 0.005)),
    'return_speed': (_R.return_speed, 'sleeve speed on the return stroke, m/s', (1e-6, 0.05)),
    'stroke_min': (_R.stroke_min, 'sleeve back end, m', None),
    'stroke_max': (_R.stroke_max, 'sleeve front end, m', None),
    'position_min': (_R.position_min, 'smallest catheter insertion, m', None),
    'position_max': (_R.position_max, 'largest catheter insertion, m', None),
    'gripper_close_time': (_R.gripper_close_time,
                           'nominal gripper closing time (simulation), s', None),
    'gripper_open_time': (_R.gripper_open_time, 'nominal gripper opening time (simulation), s',
                          None),
    'gripper_timeout': (_R.gripper_timeout, 'handover step longer than this is a fault, s',
                        None),
    'control_rate_hz': (_S.control_rate_hz, 'relay control loop and state rate, Hz',
                        (1.0, 1000.0)),
    'command_timeout_s': (_S.command_timeout, 'watchdog: stop when commands are older, s',
                          None),
    'status_timeout_s': (_S.status_timeout,
                         'device counts as disconnected after this silence, s', None),
    'reconnect_backoff_initial_s': (_S.backoff_initial, 'first reconnect delay, s', None),
    'reconnect_backoff_max_s': (_S.backoff_max, 'largest reconnect delay, s', None),
    'diagnostics_period_s': (_S.diagnostics_period, '/diagnostics period, s', None),
    'can_interface': ('virtual', "python-can interface ('virtual', 'socketcan', ...)", None),
    'can_channel': ('sleeve_driver', 'python-can channel', None),
    'can_bitrate': (500000, 'CAN bitrate, bit/s', (10000, 1000000)),
    'simulate_device': (True, 'start a simulated driver on the virtual bus in this process',
                        None),
    'dbc_path': ('', 'DBC file; empty = the bundled driver.dbc', None),
    'hardware_id': ('sleeve_driver', 'hardware_id in /diagnostics', None),
    'autostart': (True, AUTOSTART_DESCRIPTION, None),
}
#: Parameters fixed for the node's life (the others are read at configure).
_READ_ONLY = frozenset({'autostart'})
_CONFIGURE_TIME = tuple(name for name in PARAMETERS if name not in _READ_ONLY)


@dataclass(frozen=True)
class DriverSettings:
    """What the node builds from its parameters (:func:`build_settings`)."""

    relay: RelayConfig
    """Relay mechanism and caps."""
    supervision: SupervisionConfig
    """Rates, watchdog and reconnection."""
    interface: str
    """python-can interface."""
    channel: str
    """python-can channel."""
    bitrate: int
    """CAN bitrate, bit/s."""
    simulate: bool
    """Run the simulated driver in-process."""
    hardware_id: str
    """hardware_id in /diagnostics."""
    codec: DriverCodec
    """Frame codec of the DBC file."""


def build_settings(values: Mapping[str, Any]) -> DriverSettings:
    """The :class:`DriverSettings` of the parameter values ``{name: value}``.

    Raises:
        ValueError: a value out of range or inconsistent; ProtocolError (a ValueError) for a
            DBC file that cannot be read.
    """
    relay = RelayConfig(
        max_speed=values['max_speed'], return_speed=values['return_speed'],
        stroke_min=values['stroke_min'], stroke_max=values['stroke_max'],
        position_min=values['position_min'], position_max=values['position_max'],
        gripper_close_time=values['gripper_close_time'],
        gripper_open_time=values['gripper_open_time'],
        gripper_timeout=values['gripper_timeout'])
    supervision = SupervisionConfig(
        control_rate_hz=values['control_rate_hz'],
        command_timeout=values['command_timeout_s'],
        status_timeout=values['status_timeout_s'],
        backoff_initial=values['reconnect_backoff_initial_s'],
        backoff_max=values['reconnect_backoff_max_s'],
        diagnostics_period=values['diagnostics_period_s'])
    interface, simulate = str(values['can_interface']), bool(values['simulate_device'])
    if simulate and interface != 'virtual':
        raise ValueError(f"simulate_device requires can_interface 'virtual', found "
                         f'{interface!r}')
    codec = DriverCodec(values['dbc_path'] or None, position_range=(
        relay.stroke_min - 0.01, relay.stroke_max + 0.01))
    return DriverSettings(relay=relay, supervision=supervision, interface=interface,
                          channel=str(values['can_channel']), bitrate=int(values['can_bitrate']),
                          simulate=simulate, hardware_id=str(values['hardware_id']), codec=codec)


class DriverNode(LifecycleNode):
    """Thin lifecycle wrapper around :class:`RelayController` and :class:`CanDriverLink`.

    Raises:
        ValueError: a parameter out of range or inconsistent (at construction).
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('sleeve_driver', **kwargs)
        for name, (default, description, bounds) in PARAMETERS.items():
            lo, hi = bounds if bounds is not None else (None, None)
            declare(self, name, default, description, lo=lo, hi=hi,
                    read_only=name in _READ_ONLY)
        self.autostart = bool(self.get_parameter('autostart').value)
        self._apply(build_settings(self._parameter_values()))
        self.add_on_set_parameters_callback(
            configure_time_guard(self, _CONFIGURE_TIME, build_settings))
        self.sim: SimulatedDriver | None = None

        self._link: CanDriverLink | None = None
        self._controller: RelayController | None = None
        self._feedback: DriverStatus | None = None
        self._last_known: SleeveFeedback | None = None  # kept across disconnects
        self._next_attempt = 0.0
        self._last_status = 0.0
        self._link_error = 'not opened yet'
        self._position = 0.0
        self._velocity_cmd = 0.0
        self._estop = False
        self._last_stop_frame = 0.0
        self.rejected_commands = 0
        self._last_rejection = ''
        self.reconnects = 0
        self._active = False
        self._state_pub: LifecyclePublisher | None = None
        self._state_msg = JointState()  # refilled per publish (conv.insertion_state's out)
        self._diag_pub: LifecyclePublisher | None = None
        self._sub_command: Subscription | None = None
        self._srv_estop: Service | None = None
        self._timers: list[Timer] = []

    def _parameter_values(self) -> dict[str, Any]:
        return {name: self.get_parameter(name).value for name in _CONFIGURE_TIME}

    def _apply(self, settings: DriverSettings) -> None:
        """Take ``settings`` (the link is closed: constructor or unconfigured)."""
        self.relay_config = settings.relay
        self.supervision = settings.supervision
        self._interface, self._channel = settings.interface, settings.channel
        self._bitrate, self._simulate = settings.bitrate, settings.simulate
        self._hardware_id, self._codec = settings.hardware_id, settings.codec
        self._backoff = Backoff(self.supervision.backoff_initial, self.supervision.backoff_max)
        self._watchdog = Watchdog(self.supervision.command_timeout)
        self._period = 1.0 / self.supervision.control_rate_hz

    # -- lifecycle ---------------------------------------------------------------------------

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        # (valid: the guard refused any value build_settings rejects)
        self._apply(build_settings(self._parameter_values()))
        if self._simulate:
            self.sim = SimulatedDriver(self._channel, config=self.relay_config,
                                       codec=self._codec).start()
        self._backoff.reset()
        self._next_attempt = 0.0
        self._open(conv.node_seconds(self))
        self._state_pub = self.create_lifecycle_publisher(
            JointState, '~/insertion_state', conv.SENSOR_QOS)
        self._diag_pub = self.create_lifecycle_publisher(
            DiagnosticArray, '/diagnostics', conv.DIAGNOSTICS_QOS)
        self._sub_command = self.create_subscription(
            JointState, '~/insertion_command', self._on_insertion_command,
            conv.COMMAND_QOS)
        self._srv_estop = self.create_service(SetBool, '~/estop', self._on_estop)
        self._timers = [self.create_timer(self._period, self._on_control),
                        self.create_timer(self.supervision.diagnostics_period,
                                          self._on_diagnostics)]
        self.get_logger().info(
            f'sleeve driver on CAN {self._interface}:{self._channel}'
            f'{" (simulated device)" if self.sim is not None else ""}, '
            f'cap {self.relay_config.max_speed} m/s')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        self._velocity_cmd = 0.0
        self._watchdog.starve()
        self._active = True
        self.get_logger().info('active: accepting insertion commands')
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        self._safe_stop()
        self.get_logger().info('inactive: sleeve stopped, both grippers closed')
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self._safe_stop()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self._safe_stop()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self.get_logger().error(f'transition error in state {state.label}: stopping the sleeve')
        self._safe_stop()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _safe_stop(self) -> None:
        """Stop accepting commands; sleeve velocity 0 with both grippers closed; idempotent."""
        self._active = False
        self._velocity_cmd = 0.0
        self._watchdog.starve()
        # The relay restarts from fresh feedback on the next activation.
        self._controller = None
        self._last_known = None
        self._send_hold()

    def _send_hold(self) -> None:
        """Send the hold command (sleeve stopped, both grippers closed) if the link is open."""
        if self._link is None:
            return
        try:
            self._link.send_command(DriverCommand(0.0, True, True))
        except (DeviceDisconnectedError, ProtocolError) as exc:
            self._drop(conv.node_seconds(self), str(exc))

    def _release(self) -> None:
        """Destroy the configured entities, close the bus, stop the simulated device."""
        for timer in self._timers:
            self.destroy_timer(timer)
        self._timers = []
        for pub in (self._state_pub, self._diag_pub):
            if pub is not None:
                self.destroy_lifecycle_publisher(pub)
        self._state_pub = self._diag_pub = None
        if self._sub_command is not None:
            self.destroy_subscription(self._sub_command)
            self._sub_command = None
        if self._srv_estop is not None:
            self.destroy_service(self._srv_estop)
            self._srv_estop = None
        if self._link is not None:
            self._link.close()
            self._link = None
        self._feedback = None
        self._link_error = 'not opened yet'
        if self.sim is not None:
            self.sim.stop()
            self.sim = None

    # -- callbacks ---------------------------------------------------------------------------

    def _on_insertion_command(self, msg: JointState) -> None:
        if not self._active:
            self.get_logger().warning('inactive: insertion command ignored',
                                      throttle_duration_sec=2.0)
            return
        try:
            velocity = conv.insertion_velocity(msg, self.relay_config.max_speed)
        except CommandError as exc:
            self.rejected_commands += 1
            self._last_rejection = str(exc)
            self.get_logger().warning(f'insertion command rejected, nothing sent: {exc}',
                                      throttle_duration_sec=1.0)
            return
        self._velocity_cmd = velocity
        self._watchdog.feed(conv.node_seconds(self))

    def _on_estop(self, request: SetBool.Request, response: SetBool.Response):
        self._estop = bool(request.data)
        if self._controller is not None:
            self._controller.set_estop(self._estop)
        self._velocity_cmd = 0.0
        self._watchdog.starve()
        self._last_stop_frame = 0.0  # (re)send the latch frame on the next control tick
        self._send_stop()
        response.success = True
        response.message = 'e-stop engaged' if self._estop else 'e-stop released'
        self.get_logger().warning(response.message)
        return response

    def _on_control(self) -> None:
        now = conv.node_seconds(self)
        if self._link is None and not self._open(now):
            return
        assert self._link is not None
        try:
            status = self._link.poll()
        except DeviceDisconnectedError as exc:
            self._drop(now, str(exc))
            return
        if status is not None:
            self._feedback, self._last_status = status, now
            self._backoff.reset()
        if now - self._last_status > self.supervision.status_timeout:
            self._drop(now, f'expected DRV_STATUS within {self.supervision.status_timeout} s,'
                            f' found none for {now - self._last_status:.3f} s')
            return
        if self._feedback is None:
            return
        if not self._active:
            self._send_hold()
            return
        fb = SleeveFeedback(self._feedback.sleeve_position, self._feedback.moving,
                            self._feedback.fixed)
        if self._controller is None:
            # Start from the last state seen before a disconnect, so the sleeve travel made
            # while the link was down (at most until the driver's own watchdog) is tracked.
            self._controller = RelayController(self.relay_config, self._last_known or fb,
                                               self._position)
            self._controller.set_estop(self._estop)
        velocity = self._velocity_cmd if self._watchdog.fresh(now) else 0.0
        cmd = self._controller.step(velocity, fb, self._period)
        self._position = self._controller.position
        self._last_known = fb
        try:
            if self._estop and now - self._last_stop_frame >= 1.0:
                self._send_stop()
                self._last_stop_frame = now
            self._link.send_command(DriverCommand(cmd.sleeve_velocity, cmd.moving_close,
                                                  cmd.fixed_close))
        except (DeviceDisconnectedError, ProtocolError) as exc:
            self._drop(now, str(exc))
            return
        assert self._state_pub is not None
        self._state_pub.publish(conv.insertion_state(
            self.get_clock().now(), self._controller.position,
            catheter_velocity(fb, self._feedback.sleeve_velocity), out=self._state_msg))

    def _on_diagnostics(self) -> None:
        if not self._active or self._diag_pub is None:
            return  # inactive: nothing is published
        self._diag_pub.publish(self.diagnostics_message())

    # -- helpers -----------------------------------------------------------------------------

    def _open(self, now: float) -> bool:
        if now < self._next_attempt:
            return False
        try:
            self._link = CanDriverLink.open(self._interface, self._channel, self._codec,
                                            self._bitrate)
        except DeviceDisconnectedError as exc:
            delay = self._backoff.next_delay()
            self._next_attempt = now + delay
            self._link_error = f'{exc}; retrying in {delay:.2f} s'
            self.get_logger().error(self._link_error, throttle_duration_sec=5.0)
            return False
        self._last_status = now  # grace period for the first status
        self._send_stop()
        return True

    def _drop(self, now: float, reason: str) -> None:
        if self._link is not None:
            self._link.close()
        self._link, self._controller, self._feedback = None, None, None
        delay = self._backoff.next_delay()
        self._next_attempt = now + delay
        self.reconnects += 1
        self._link_error = f'{reason}; reconnecting in {delay:.2f} s'
        self.get_logger().error(f'sleeve driver disconnected: {self._link_error}',
                                throttle_duration_sec=2.0)

    def _send_stop(self) -> None:
        if self._link is None:
            return
        try:
            self._link.send_stop(self._estop)
        except DeviceDisconnectedError as exc:
            self._link_error = str(exc)

    def diagnostics_message(self) -> DiagnosticArray:
        """The current /diagnostics array (one status for the sleeve driver)."""
        now = conv.node_seconds(self)
        fb, ctrl = self._feedback, self._controller
        connected = self._link is not None and fb is not None
        fault = ctrl.fault if ctrl is not None else None
        level, message = DiagnosticStatus.OK, 'running'
        if not connected or fb is None:
            level, message = DiagnosticStatus.ERROR, f'disconnected: {self._link_error}'
        elif fault or fb.stall or fb.interlock:
            level = DiagnosticStatus.WARN
            message = fault or ('sleeve stalled' if fb.stall else 'interlock refused motion')
        elif self._estop:
            level, message = DiagnosticStatus.WARN, 'e-stop engaged'
        elif fb.stopped:
            level, message = DiagnosticStatus.WARN, 'driver reports its e-stop latch engaged'
        values = [
            ('connected', connected),
            ('phase', ctrl.phase.name if ctrl else 'none'),
            ('catheter_position_m', f'{self._position:.6f}'),
            ('sleeve_position_m', f'{fb.sleeve_position:.6f}' if fb else 'unknown'),
            ('moving_gripper', fb.moving.name if fb else 'unknown'),
            ('fixed_gripper', fb.fixed.name if fb else 'unknown'),
            ('stall', fb.stall if fb else 'unknown'),
            ('device_command_timeout', fb.command_timeout if fb else 'unknown'),
            ('estop', self._estop),
            ('command_fresh', self._watchdog.fresh(now)),
            ('rejected_commands', self.rejected_commands),
            ('last_rejection', self._last_rejection),
            ('device_stopped', fb.stopped if fb else 'unknown'),
            ('protocol_errors', self._link.protocol_errors if self._link else 0),
            ('dropped_frames', self._link.dropped_frames if self._link else 0),
            ('reconnects', self.reconnects),
        ]
        return conv.diagnostics(self.get_clock().now(), 'sleeve_driver: relay insertion',
                                self._hardware_id, level, message, values)

    def destroy_node(self) -> None:
        """Stop the sleeve (grippers closed), release the bus and the simulated device.

        Safe in every lifecycle state.
        """
        self._safe_stop()
        self._release()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Console script ``driver_node``: build the node, configure and activate it (unless
    ``autostart`` is false), spin."""
    run_node(DriverNode, 'driver_node', args, start=start_lifecycle)


if __name__ == '__main__':
    main()

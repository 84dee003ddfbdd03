"""sleeve_driver node in-process: topics, QoS, watchdog, e-stop, bad commands, disconnects.

Most tests own the simulated board (:class:`SteppedDriver`, ``simulate_device:=false``) and step
it from a timer of the test's executor at the board's 100 Hz: board time advances with the
node's callbacks, and no device thread races the test for the GIL. Commands come from a 50 Hz
timer, like the teleop node's. The lifecycle test keeps the node's own simulated board (its
thread is what configure starts and cleanup stops).
"""

import math
import time
import uuid

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
import pytest
from rcl_interfaces.srv import SetParameters
from rclpy.exceptions import InvalidParameterValueException
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool

from catheter_driver.core.relay import GripperState
from catheter_driver.hw.can_protocol import DriverCodec, DriverStatus
from catheter_driver.hw.sim_driver import SimulatedDriver
from catheter_driver.nodes import conversions as conv
from catheter_driver.nodes.driver_node import DriverNode
from cgail_node_utils.lifecycle import lifecycle_state

COMMAND_RATE_HZ = 50.0


class SteppedDriver(SimulatedDriver):
    """The simulated board without its thread: the test's executor steps it; ``time`` is the
    board's clock, s."""

    time = 0.0

    def step(self, dt: float) -> DriverStatus | None:
        self.time += dt
        return super().step(dt)


def _node(harness, **params):
    """A configured, active driver node (with its own simulated board unless told not to)."""
    params.setdefault('can_channel', f'drv_{uuid.uuid4().hex}')
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    node = harness.add(DriverNode(parameter_overrides=overrides))
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    return node


def _rig(harness, **params) -> tuple[DriverNode, SteppedDriver]:
    """A configured, active driver node and the simulated board on its bus, stepped at the
    board's rate by a timer of the harness executor."""
    channel = params.setdefault('can_channel', f'drv_{uuid.uuid4().hex}')
    overrides = [Parameter(k, value=v) for k, v in {**params, 'simulate_device': False}.items()]
    node = harness.add(DriverNode(parameter_overrides=overrides))
    sim = SteppedDriver(channel, config=node.relay_config, codec=node._codec)
    harness.closers.append(sim.stop)
    dt = 1.0 / sim.rate_hz
    harness.repeat(dt, lambda: sim.step(dt))
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    return node, sim


def _cmd(velocity, name='insertion'):
    msg = JointState()
    msg.name = [name]
    msg.velocity = [velocity]
    return msg


def _commanding(harness, pub, msg, sent_at: list[float] | None = None):
    """Publish ``msg`` at COMMAND_RATE_HZ until ``harness.stop``; each send time is appended
    to ``sent_at``."""
    def send() -> None:
        pub.publish(msg)
        if sent_at is not None:
            sent_at.append(time.monotonic())
    return harness.repeat(1.0 / COMMAND_RATE_HZ, send)


def _driving(node) -> bool:
    return node._controller is not None and node._controller.phase.name == 'DRIVE'


def _values(array):
    return {kv.key: kv.value for kv in array.status[0].values}


def test_topics_services_and_qos(harness):
    node = _node(harness)
    # the graph cache learns of the node's own endpoints asynchronously: wait for them
    assert harness.spin_until(lambda: all(node.get_publishers_info_by_topic(t) for t in (
        '/sleeve_driver/insertion_state', '/diagnostics'))
        and node.get_subscriptions_info_by_topic('/sleeve_driver/insertion_command'))
    pubs = {name: node.get_publishers_info_by_topic(name) for name in
            ('/sleeve_driver/insertion_state', '/diagnostics')}
    state_qos = pubs['/sleeve_driver/insertion_state'][0].qos_profile
    assert state_qos.reliability == ReliabilityPolicy.BEST_EFFORT
    diag_qos = pubs['/diagnostics'][0].qos_profile
    assert diag_qos.reliability == ReliabilityPolicy.RELIABLE
    assert diag_qos.durability == DurabilityPolicy.VOLATILE
    subs = node.get_subscriptions_info_by_topic('/sleeve_driver/insertion_command')
    assert subs[0].qos_profile.reliability == ReliabilityPolicy.RELIABLE
    # the graph cache learns of the node's own service asynchronously: wait for it
    def services():
        return dict(node.get_service_names_and_types_by_node('sleeve_driver', '/'))
    assert harness.spin_until(lambda: '/sleeve_driver/estop' in services())
    assert services()['/sleeve_driver/estop'] == ['std_srvs/srv/SetBool']


def test_insertion_command_moves_the_catheter_and_state_reports_it(harness):
    node, sim = _rig(harness)
    states = harness.collect(JointState, '/sleeve_driver/insertion_state', conv.SENSOR_QOS)
    pub = harness.probe.create_publisher(JointState, '/sleeve_driver/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: states and _driving(node))
    _commanding(harness, pub, _cmd(0.005))
    assert harness.spin_until(lambda: states[-1].position[0] > 0.002)
    last = states[-1]
    assert last.name == ['insertion']
    # the catheter waits (velocity 0) while the sleeve returns between relays, so look at
    # every state: it moved, and never faster than the cap
    velocities = [m.velocity[0] for m in states]
    assert 0.0 < max(velocities) <= 0.005 + 1e-9
    assert min(velocities) >= 0.0
    assert sim.mechanism.catheter_position == pytest.approx(last.position[0], abs=5e-4)


def test_watchdog_stops_on_stale_commands(harness):
    node, sim = _rig(harness, command_timeout_s=0.2)
    pub = harness.probe.create_publisher(JointState, '/sleeve_driver/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: _driving(node))
    sent_at: list[float] = []
    commands = _commanding(harness, pub, _cmd(0.005), sent_at)
    assert harness.spin_until(lambda: sim.mechanism.sleeve_velocity > 0)
    harness.stop(commands)  # no more commands
    assert harness.spin_until(
        lambda: _values(node.diagnostics_message())['command_fresh'] == 'False')
    assert time.monotonic() - sent_at[-1] >= 0.2  # never before command_timeout_s
    assert harness.spin_until(lambda: sim.mechanism.sleeve_velocity == 0.0)
    stopped_at = sim.mechanism.catheter_position
    harness.spin_for(0.3)
    assert sim.mechanism.sleeve_velocity == 0.0
    assert sim.mechanism.catheter_position == stopped_at
    assert _values(node.diagnostics_message())['command_fresh'] == 'False'


@pytest.mark.parametrize(('msg', 'reason'), [
    (_cmd(math.nan), 'expected a finite insertion velocity, found nan'),
    (_cmd(math.inf), 'expected a finite insertion velocity, found inf'),
    (_cmd(0.006), r'expected |insertion velocity| <= 0.005 m/s, found 0.006 m/s'),
    (_cmd(0.001, name='wrong'), "expected joint 'insertion' in name, found ['wrong']"),
])
def test_bad_commands_are_rejected_and_nothing_is_sent(harness, msg, reason):
    node, sim = _rig(harness)
    pub = harness.probe.create_publisher(JointState, '/sleeve_driver/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: _driving(node))
    start = sim.mechanism.catheter_position
    _commanding(harness, pub, msg)
    assert harness.spin_until(lambda: node.rejected_commands >= 3)
    harness.spin_for(0.2)  # bad commands keep coming: still nothing moves
    assert sim.mechanism.catheter_position == start
    assert node._velocity_cmd == 0.0
    assert _values(node.diagnostics_message())['last_rejection'] == reason


def test_estop_service_holds_the_sleeve_and_reports(harness):
    node, sim = _rig(harness)
    diags = harness.collect(DiagnosticArray, '/diagnostics', conv.DIAGNOSTICS_QOS)
    pub = harness.probe.create_publisher(JointState, '/sleeve_driver/insertion_command',
                                         conv.COMMAND_QOS)
    client = harness.probe.create_client(SetBool, 'sleeve_driver/estop')
    assert harness.spin_until(lambda: _driving(node))
    result = harness.call(client, SetBool.Request(data=True))
    assert result.success and result.message == 'e-stop engaged'
    _commanding(harness, pub, _cmd(0.005))
    harness.spin_for(0.6)
    assert sim.mechanism.catheter_position == 0.0
    assert harness.spin_until(lambda: diags and diags[-1].status[0].level == DiagnosticStatus.WARN)
    status = diags[-1].status[0]
    assert status.message == 'e-stop engaged' and status.hardware_id == 'sleeve_driver'
    assert harness.spin_until(lambda: sim._stopped)  # the latch frame reached the device
    result = harness.call(client, SetBool.Request(data=False))
    assert result.message == 'e-stop released'
    assert harness.spin_until(lambda: sim.mechanism.catheter_position > 1e-4)


def test_disconnect_reported_and_recovered_with_backoff(harness):
    node, sim = _rig(harness, status_timeout_s=0.1, reconnect_backoff_initial_s=0.05,
                     reconnect_backoff_max_s=0.4)
    assert harness.spin_until(lambda: node._controller is not None)
    sim.disconnect()
    assert harness.spin_until(lambda: node.reconnects >= 3)
    diag = node.diagnostics_message().status[0]
    assert diag.level == DiagnosticStatus.ERROR
    assert diag.message.startswith('disconnected: expected DRV_STATUS within 0.1 s')
    assert node._backoff.attempts >= 3
    sim.reconnect()
    assert harness.spin_until(lambda: node.diagnostics_message().status[0].level
                              == DiagnosticStatus.OK)
    assert node._backoff.attempts == 0


def test_garbage_frames_do_not_crash_the_node(harness):
    node, sim = _rig(harness)
    assert harness.spin_until(lambda: node._controller is not None)
    for _ in range(5):
        sim.inject_garbage(20)
        harness.spin_for(0.05)
    assert harness.spin_until(lambda: node._link is not None and node._link.protocol_errors >= 90)
    assert node._controller is not None
    assert _values(node.diagnostics_message())['connected'] == 'True'


def test_stall_is_reported_in_diagnostics(harness):
    node, sim = _rig(harness)
    pub = harness.probe.create_publisher(JointState, '/sleeve_driver/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: _driving(node))
    sim.set_stall(True)
    _commanding(harness, pub, _cmd(0.005))
    assert harness.spin_until(
        lambda: node.diagnostics_message().status[0].message == 'sleeve stalled')


def test_missing_can_interface_reports_error_and_retries(harness):
    node = _node(harness, can_interface='no_such_interface', simulate_device=False,
                 reconnect_backoff_initial_s=0.05, reconnect_backoff_max_s=0.1)
    assert harness.spin_until(lambda: node._backoff.attempts >= 3)
    diag = node.diagnostics_message().status[0]
    assert diag.level == DiagnosticStatus.ERROR
    assert 'expected to open CAN no_such_interface' in diag.message
    # the node's own backoff parameters: 0.05 s doubling, capped at 0.1 s (not 0.5 / 8 s)
    assert 'retrying in 0.10 s' in diag.message, diag.message


@pytest.mark.parametrize(('params', 'error', 'match'), [
    ({'max_speed': 0.01}, InvalidParameterValueException, 'max_speed'),
    ({'stroke_max': -1.0}, ValueError, 'stroke_max must exceed stroke_min'),
    ({'command_timeout_s': 0.0}, ValueError, 'command_timeout must be a finite number > 0'),
    ({'can_interface': 'socketcan'}, ValueError,
     "simulate_device requires can_interface 'virtual', found 'socketcan'"),
    ({'reconnect_backoff_max_s': 0.1}, ValueError, 'backoff_max must be >= backoff_initial'),
])
def test_bad_parameters_raise_at_construction(harness, params, error, match):
    with pytest.raises(error, match=match):
        DriverNode(parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


def test_position_is_tracked_across_a_disconnect(harness):
    node, sim = _rig(harness, status_timeout_s=0.25, reconnect_backoff_initial_s=0.05,
                     reconnect_backoff_max_s=0.1)
    states = harness.collect(JointState, '/sleeve_driver/insertion_state', conv.SENSOR_QOS)
    pub = harness.probe.create_publisher(JointState, '/sleeve_driver/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: _driving(node))
    commands = _commanding(harness, pub, _cmd(0.005))
    assert harness.spin_until(lambda: sim.mechanism.catheter_position > 0.001)
    sim.disconnect()  # the board drives on until its own 200 ms watchdog (board time)
    pulled_at = sim.time
    assert harness.spin_until(lambda: node.reconnects >= 1
                              and sim.time > pulled_at + sim.command_timeout + 0.05)
    harness.stop(commands)
    assert sim.mechanism.sleeve_velocity == 0.0  # the board's watchdog stopped it
    # the node's watchdog too: nothing moves the catheter once the cable is back
    assert harness.spin_until(
        lambda: _values(node.diagnostics_message())['command_fresh'] == 'False')
    moved_blind = sim.mechanism.catheter_position
    sim.reconnect()
    assert harness.spin_until(lambda: node._controller is not None and states
                              and states[-1].position[0] >= moved_blind - 1e-6)
    assert states[-1].position[0] == pytest.approx(moved_blind, abs=2e-6)


def test_driver_latch_engaged_elsewhere_is_a_warning(harness):
    channel = f'drv_{uuid.uuid4().hex}'
    node, _ = _rig(harness, can_channel=channel)
    assert harness.spin_until(lambda: node._controller is not None)
    other_host = can.Bus(interface='virtual', channel=channel)
    try:
        other_host.send(DriverCodec().encode_stop(True))
        assert harness.spin_until(lambda: node.diagnostics_message().status[0].message
                                  == 'driver reports its e-stop latch engaged')
        assert node.diagnostics_message().status[0].level == DiagnosticStatus.WARN
    finally:
        other_host.shutdown()


def _state(node):
    return lifecycle_state(node)


def _own_topics(node):
    """The node's device publishers (rosout, parameter and lifecycle events aside)."""
    names = {pub.topic_name for pub in node.publishers}
    return names & {'/sleeve_driver/insertion_state', '/diagnostics'}


def test_lifecycle_configure_activate_deactivate_cleanup_configure(harness):
    """Commands move the sleeve only while active; deactivate holds it with the grippers
    closed and publishes nothing; cleanup releases the bus and the simulated device; a second
    configure + activate drives again."""
    channel = f'drv_{uuid.uuid4().hex}'
    node = harness.add(DriverNode(parameter_overrides=[Parameter('can_channel', value=channel)]))
    states = harness.collect(JointState, '/sleeve_driver/insertion_state', conv.SENSOR_QOS)
    diags = harness.collect(DiagnosticArray, '/diagnostics', conv.DIAGNOSTICS_QOS)
    pub = harness.probe.create_publisher(JointState, '/sleeve_driver/insertion_command',
                                         conv.COMMAND_QOS)
    assert _state(node) == 'unconfigured' and node.sim is None and node._link is None
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert _state(node) == 'inactive' and node.sim is not None and node._link is not None
    assert _own_topics(node) == {'/sleeve_driver/insertion_state', '/diagnostics'}
    mech = node.sim.mechanism
    # commands at 50 Hz from here to the end, through every transition
    _commanding(harness, pub, _cmd(0.005))
    # inactive: commands ignored, nothing published, both grippers held closed
    harness.spin_for(0.5)
    assert mech.catheter_position == 0.0 and states == [] and diags == []
    assert mech.moving.state == GripperState.CLOSED and mech.fixed.state == GripperState.CLOSED
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert harness.spin_until(lambda: mech.catheter_position > 0.002 and states and diags)
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert _state(node) == 'inactive'
    assert harness.spin_until(lambda: mech.sleeve_velocity == 0.0)
    harness.spin_for(0.1)  # drain messages in flight
    n_states, n_diags, stopped_at = len(states), len(diags), mech.catheter_position
    harness.spin_for(0.6)
    assert mech.catheter_position == stopped_at and mech.sleeve_velocity == 0.0
    assert mech.moving.state == GripperState.CLOSED and mech.fixed.state == GripperState.CLOSED
    assert len(states) == n_states and len(diags) == n_diags
    sim = node.sim
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert _state(node) == 'unconfigured' and node.sim is None and node._link is None
    assert sim._thread is None  # simulated device stopped, its bus closed
    assert _own_topics(node) == set()
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    mech2 = node.sim.mechanism
    assert harness.spin_until(lambda: mech2.catheter_position > 0.001
                              and len(states) > n_states)


@pytest.mark.parametrize('steps', [(), ('configure',), ('configure', 'activate'),
                                   ('configure', 'activate', 'deactivate')])
def test_shutdown_and_destroy_are_safe_in_every_state(harness, steps):
    node = DriverNode(parameter_overrides=[Parameter('can_channel',
                                                     value=f'drv_{uuid.uuid4().hex}')])
    for step in steps:
        assert getattr(node, f'trigger_{step}')() == TransitionCallbackReturn.SUCCESS
    sim = node.sim
    assert node.trigger_shutdown() == TransitionCallbackReturn.SUCCESS
    assert _state(node) == 'finalized' and node.sim is None and node._link is None
    if sim is not None:
        assert sim.mechanism.sleeve_velocity == 0.0
    node.destroy_node()


# -- parameters: read at configure, changeable only while unconfigured -----------------------

def _set_over_service(harness, node, **values):
    """Call the node's ``set_parameters`` service (as ``ros2 param set`` does)."""
    client = harness.probe.create_client(SetParameters,
                                         f'{node.get_fully_qualified_name()}/set_parameters')
    request = SetParameters.Request(parameters=[
        Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
    try:
        return harness.call(client, request).results
    finally:
        harness.probe.destroy_client(client)


def test_set_parameters_refuses_a_configure_time_parameter_while_active(harness):
    node = _node(harness)
    [result] = _set_over_service(harness, node, max_speed=0.002)
    assert not result.successful
    assert 'max_speed' in result.reason and 'found the node active' in result.reason
    assert node.relay_config.max_speed == 0.005
    [result] = _set_over_service(harness, node, autostart=False)
    assert not result.successful and 'read-only' in result.reason


def test_parameter_set_while_unconfigured_takes_effect_at_configure(harness):
    node = _node(harness)
    diags = harness.collect(DiagnosticArray, '/diagnostics', conv.DIAGNOSTICS_QOS)
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    [inactive] = _set_over_service(harness, node, hardware_id='sleeve_rig_2')
    assert not inactive.successful and 'found the node inactive' in inactive.reason
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    results = _set_over_service(harness, node, hardware_id='sleeve_rig_2', max_speed=0.002)
    assert [r.successful for r in results] == [True, True]
    [bad] = _set_over_service(harness, node, stroke_max=-1.0)
    assert not bad.successful and 'stroke_max must exceed stroke_min' in bad.reason
    [bad] = _set_over_service(harness, node, dbc_path='/nonexistent/driver.dbc')
    assert not bad.successful and 'expected a readable CAN database' in bad.reason
    assert node.relay_config.max_speed == 0.005  # not before configure
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.relay_config.max_speed == 0.002 and node.relay_config.stroke_max == 0.03
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert harness.spin_until(lambda: any(a.status[0].hardware_id == 'sleeve_rig_2'
                                          for a in diags))


def test_autostart_false_leaves_main_unconfigured_for_a_lifecycle_manager(harness):
    import os
    import signal
    import subprocess
    import sys

    ns = f'/autostart_{os.getpid()}'
    proc = subprocess.Popen(
        [sys.executable, '-c', 'from catheter_driver.nodes.driver_node import main; main()',
         '--ros-args', '-r', f'__ns:={ns}', '-p', 'autostart:=false',
         '-p', f'can_channel:=drv_{uuid.uuid4().hex}'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=dict(os.environ))
    try:
        get_state = harness.probe.create_client(GetState, f'{ns}/sleeve_driver/get_state')
        change_state = harness.probe.create_client(ChangeState,
                                                   f'{ns}/sleeve_driver/change_state')
        state = harness.call(get_state, GetState.Request(), timeout=20.0).current_state
        assert state.label == 'unconfigured'
        configure = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE))
        assert harness.call(change_state, configure).success
        assert harness.call(get_state, GetState.Request()).current_state.label == 'inactive'
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=15.0)
        assert rc == 0, proc.stdout.read()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

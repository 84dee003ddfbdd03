"""sleeve_driver node in-process: topics, QoS, watchdog, e-stop, bad commands, disconnects."""

import math
import uuid

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool

from catheter_driver.core.relay import GripperState
from catheter_driver.hw.can_protocol import DriverCodec
from catheter_driver.nodes import conversions as conv
from catheter_driver.nodes.driver_node import DriverNode


def _node(harness, **params):
    params.setdefault('can_channel', f'drv_{uuid.uuid4().hex}')
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    node = harness.add(DriverNode(parameter_overrides=overrides))
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    return node


def _cmd(velocity, name='insertion'):
    msg = JointState()
    msg.name = [name]
    msg.velocity = [velocity]
    return msg


def _publishing(pub, msg, predicate):
    """A spin_until predicate that publishes ``msg`` on every poll."""
    def step():
        pub.publish(msg)
        return predicate()
    return step


def _values(array):
    return {kv.key: kv.value for kv in array.status[0].values}


def test_topics_services_and_qos(harness):
    node = _node(harness)
    # the graph cache learns of the node's own endpoints asynchronously: wait for them
    assert harness.spin_until(lambda: all(node.get_publishers_info_by_topic(t) for t in (
        '/catheter/insertion_state', '/diagnostics')) and node.get_subscriptions_info_by_topic(
        '/catheter/insertion_command'))
    pubs = {name: node.get_publishers_info_by_topic(name) for name in
            ('/catheter/insertion_state', '/diagnostics')}
    state_qos = pubs['/catheter/insertion_state'][0].qos_profile
    assert state_qos.reliability == ReliabilityPolicy.BEST_EFFORT
    diag_qos = pubs['/diagnostics'][0].qos_profile
    assert diag_qos.reliability == ReliabilityPolicy.RELIABLE
    assert diag_qos.durability == DurabilityPolicy.VOLATILE
    subs = node.get_subscriptions_info_by_topic('/catheter/insertion_command')
    assert subs[0].qos_profile.reliability == ReliabilityPolicy.RELIABLE
    # the graph cache learns of the node's own service asynchronously: wait for it
    def services():
        return dict(node.get_service_names_and_types_by_node('sleeve_driver', '/'))
    assert harness.spin_until(lambda: '/sleeve_driver/estop' in services())
    assert services()['/sleeve_driver/estop'] == ['std_srvs/srv/SetBool']


def test_insertion_command_moves_the_catheter_and_state_reports_it(harness):
    node = _node(harness)
    states = harness.collect(JointState, 'catheter/insertion_state', conv.SENSOR_QOS)
    pub = harness.probe.create_publisher(JointState, 'catheter/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: states and node._controller.phase.name == 'DRIVE')

    def keep_commanding():
        pub.publish(_cmd(0.005))
        return states[-1].position[0] > 0.002

    assert harness.spin_until(keep_commanding, timeout=15.0)
    last = states[-1]
    assert last.name == ['insertion']
    # the catheter waits (velocity 0) while the sleeve returns between relays, so look at
    # every state: it moved, and never faster than the cap
    velocities = [m.velocity[0] for m in states]
    assert 0.0 < max(velocities) <= 0.005 + 1e-9
    assert min(velocities) >= 0.0
    assert node.sim.mechanism.catheter_position == pytest.approx(last.position[0], abs=5e-4)


def test_watchdog_stops_on_stale_commands(harness):
    node = _node(harness, command_timeout_s=0.2)
    pub = harness.probe.create_publisher(JointState, 'catheter/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: node._controller and node._controller.phase.name == 'DRIVE')
    assert harness.spin_until(_publishing(pub, _cmd(0.005),
                                          lambda: node.sim.mechanism.sleeve_velocity > 0))
    harness.spin_for(0.5)  # no more commands
    assert node.sim.mechanism.sleeve_velocity == 0.0
    diag = node.diagnostics_message()
    assert _values(diag)['command_fresh'] == 'False'


@pytest.mark.parametrize(('msg', 'reason'), [
    (_cmd(math.nan), 'expected a finite insertion velocity, found nan'),
    (_cmd(math.inf), 'expected a finite insertion velocity, found inf'),
    (_cmd(0.006), r'expected |insertion velocity| <= 0.005 m/s, found 0.006 m/s'),
    (_cmd(0.001, name='wrong'), "expected joint 'insertion' in name, found ['wrong']"),
])
def test_bad_commands_are_rejected_and_nothing_is_sent(harness, msg, reason):
    node = _node(harness)
    pub = harness.probe.create_publisher(JointState, 'catheter/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: node._controller and node._controller.phase.name == 'DRIVE')
    start = node.sim.mechanism.catheter_position
    assert harness.spin_until(_publishing(pub, msg, lambda: node.rejected_commands >= 3))
    harness.spin_for(0.2)
    assert node.sim.mechanism.catheter_position == start
    assert node._velocity_cmd == 0.0
    assert _values(node.diagnostics_message())['last_rejection'] == reason


def test_estop_service_holds_the_sleeve_and_reports(harness):
    node = _node(harness)
    diags = harness.collect(DiagnosticArray, '/diagnostics', conv.DIAGNOSTICS_QOS)
    pub = harness.probe.create_publisher(JointState, 'catheter/insertion_command',
                                         conv.COMMAND_QOS)
    client = harness.probe.create_client(SetBool, 'sleeve_driver/estop')
    assert harness.spin_until(lambda: node._controller and node._controller.phase.name == 'DRIVE')
    result = harness.call(client, SetBool.Request(data=True))
    assert result.success and result.message == 'e-stop engaged'
    harness.spin_until(_publishing(pub, _cmd(0.005), lambda: False), timeout=0.6)
    assert node.sim.mechanism.catheter_position == 0.0
    assert harness.spin_until(lambda: diags and diags[-1].status[0].level == DiagnosticStatus.WARN)
    status = diags[-1].status[0]
    assert status.message == 'e-stop engaged' and status.hardware_id == 'sleeve_driver'
    assert harness.spin_until(lambda: node.sim._stopped)  # the latch frame reached the device
    result = harness.call(client, SetBool.Request(data=False))
    assert result.message == 'e-stop released'
    assert harness.spin_until(_publishing(
        pub, _cmd(0.005), lambda: node.sim.mechanism.catheter_position > 1e-4))


def test_disconnect_reported_and_recovered_with_backoff(harness):
    node = _node(harness, status_timeout_s=0.1, reconnect_backoff_initial_s=0.05,
                 reconnect_backoff_max_s=0.4)
    assert harness.spin_until(lambda: node._controller is not None)
    node.sim.disconnect()
    assert harness.spin_until(lambda: node.reconnects >= 3, timeout=15.0)
    diag = node.diagnostics_message().status[0]
    assert diag.level == DiagnosticStatus.ERROR
    assert diag.message.startswith('disconnected: expected DRV_STATUS within 0.1 s')
    assert node._backoff.attempts >= 3
    node.sim.reconnect()
    assert harness.spin_until(lambda: node.diagnostics_message().status[0].level
                              == DiagnosticStatus.OK, timeout=15.0)
    assert node._backoff.attempts == 0


def test_garbage_frames_do_not_crash_the_node(harness):
    node = _node(harness)
    assert harness.spin_until(lambda: node._controller is not None)
    for _ in range(5):
        node.sim.inject_garbage(20)
        harness.spin_for(0.05)
    assert harness.spin_until(lambda: node._link is not None and node._link.protocol_errors >= 90)
    assert node._controller is not None
    assert _values(node.diagnostics_message())['connected'] == 'True'


def test_stall_is_reported_in_diagnostics(harness):
    node = _node(harness)
    pub = harness.probe.create_publisher(JointState, 'catheter/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: node._controller and node._controller.phase.name == 'DRIVE')
    node.sim.set_stall(True)
    assert harness.spin_until(_publishing(
        pub, _cmd(0.005),
        lambda: node.diagnostics_message().status[0].message == 'sleeve stalled'))


def test_missing_can_interface_reports_error_and_retries(harness):
    node = _node(harness, can_interface='no_such_interface', simulate_device=False,
                 reconnect_backoff_initial_s=0.05, reconnect_backoff_max_s=0.1)
    assert harness.spin_until(lambda: node._backoff.attempts >= 3)
    diag = node.diagnostics_message().status[0]
    assert diag.level == DiagnosticStatus.ERROR
    assert 'expected to open CAN no_such_interface' in diag.message


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
    # status_timeout 0.25 s: short enough to see the disconnect quickly, long enough that a
    # loaded CI machine does not declare the link lost before the first millimetre
    node = _node(harness, status_timeout_s=0.25, reconnect_backoff_initial_s=0.05,
                 reconnect_backoff_max_s=0.1)
    states = harness.collect(JointState, 'catheter/insertion_state', conv.SENSOR_QOS)
    pub = harness.probe.create_publisher(JointState, 'catheter/insertion_command',
                                         conv.COMMAND_QOS)
    assert harness.spin_until(lambda: node._controller and node._controller.phase.name == 'DRIVE',
                              timeout=15.0)
    assert harness.spin_until(_publishing(
        pub, _cmd(0.005), lambda: node.sim.mechanism.catheter_position > 0.001), timeout=15.0)
    node.sim.disconnect()  # the board drives on until its own 200 ms watchdog
    assert harness.spin_until(_publishing(pub, _cmd(0.005), lambda: node.reconnects >= 1),
                              timeout=15.0)
    harness.spin_for(0.4)
    moved_blind = node.sim.mechanism.catheter_position
    node.sim.reconnect()
    assert harness.spin_until(lambda: node._controller is not None and states
                              and states[-1].position[0] >= moved_blind - 1e-6, timeout=15.0)
    assert states[-1].position[0] == pytest.approx(moved_blind, abs=2e-6)


def test_driver_latch_engaged_elsewhere_is_a_warning(harness):
    channel = f'drv_{uuid.uuid4().hex}'
    node = _node(harness, can_channel=channel)
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
    return node._state_machine.current_state[1]


def _own_topics(node):
    """The node's device publishers (rosout, parameter and lifecycle events aside)."""
    names = {pub.topic_name for pub in node.publishers}
    return names & {'/catheter/insertion_state', '/diagnostics'}


def test_lifecycle_configure_activate_deactivate_cleanup_configure(harness):
    """Commands move the sleeve only while active; deactivate holds it with the grippers
    closed and publishes nothing; cleanup releases the bus and the simulated device; a second
    configure + activate drives again."""
    channel = f'drv_{uuid.uuid4().hex}'
    node = harness.add(DriverNode(parameter_overrides=[Parameter('can_channel', value=channel)]))
    states = harness.collect(JointState, 'catheter/insertion_state', conv.SENSOR_QOS)
    diags = harness.collect(DiagnosticArray, '/diagnostics', conv.DIAGNOSTICS_QOS)
    pub = harness.probe.create_publisher(JointState, 'catheter/insertion_command',
                                         conv.COMMAND_QOS)
    assert _state(node) == 'unconfigured' and node.sim is None and node._link is None
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert _state(node) == 'inactive' and node.sim is not None and node._link is not None
    assert _own_topics(node) == {'/catheter/insertion_state', '/diagnostics'}
    mech = node.sim.mechanism
    # inactive: commands ignored, nothing published, both grippers held closed
    harness.spin_until(_publishing(pub, _cmd(0.005), lambda: False), timeout=0.5)
    assert mech.catheter_position == 0.0 and states == [] and diags == []
    assert mech.moving.state == GripperState.CLOSED and mech.fixed.state == GripperState.CLOSED
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert harness.spin_until(_publishing(
        pub, _cmd(0.005), lambda: mech.catheter_position > 0.002 and states and diags),
        timeout=15.0)
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert _state(node) == 'inactive'
    assert harness.spin_until(lambda: mech.sleeve_velocity == 0.0, timeout=1.0)
    harness.spin_for(0.1)  # drain messages in flight
    n_states, n_diags, stopped_at = len(states), len(diags), mech.catheter_position
    harness.spin_until(_publishing(pub, _cmd(0.005), lambda: False), timeout=0.6)
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
    # generous deadline: a fresh-clone CI run once needed more than 5 s here
    assert harness.spin_until(_publishing(
        pub, _cmd(0.005), lambda: mech2.catheter_position > 0.001 and len(states) > n_states),
        timeout=15.0)


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

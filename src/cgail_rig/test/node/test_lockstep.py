"""The lockstep executor: one simulated clock, ordered causal delivery, a barrier per tick."""

from __future__ import annotations

import gc
import threading

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_sensor_data, QoSProfile
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Int64
from std_srvs.srv import Trigger

from cgail_rig.lockstep import LockstepError, LockstepExecutor

_CREATED: list = []


@pytest.fixture
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield ctx
    finally:
        _destroy_created()
        rclpy.try_shutdown(context=ctx)


def _destroy_created() -> None:
    """Destroy the nodes a test made and collect them: a leaked DDS participant can spin."""
    while _CREATED:
        _CREATED.pop().destroy_node()
    gc.collect()


def _node(ctx, name):
    node = rclpy.create_node(name, context=ctx, start_parameter_services=False,
                             enable_rosout=False)
    _CREATED.append(node)
    return node


def _graph(ctx, log, executor, prefix=''):
    """A timer at 40 Hz feeding a 3-stage relay, six listeners with 25 Hz timers."""
    nodes = [_node(ctx, f'{prefix}n{i}') for i in range(6)]
    for node in nodes:
        executor.add_node(node)
    q = QoSProfile(depth=10)
    src = nodes[0]
    pub0 = src.create_publisher(Int64, f'{prefix}x0', q)

    def on_source():
        now = src.get_clock().now().nanoseconds
        log.append(('t0', now))
        pub0.publish(Int64(data=now))

    src.create_timer(0.025, on_source)
    for i in (1, 2):
        pub = nodes[i].create_publisher(Int64, f'{prefix}x{i}', q)

        def relay(msg, pub=pub, i=i):
            log.append((f'r{i}', msg.data))
            pub.publish(msg)

        nodes[i].create_subscription(Int64, f'{prefix}x{i - 1}', relay, q)
    for i in range(3, 6):
        node = nodes[i]
        node.create_subscription(Int64, f'{prefix}x2',
                                 lambda m, i=i: log.append((f's{i}', m.data)),
                                 qos_profile_sensor_data)
        node.create_timer(0.04, lambda i=i, node=node: log.append(
            (f'T{i}', node.get_clock().now().nanoseconds)))
    return nodes


def test_every_message_of_a_tick_is_handled_before_the_tick_returns(context) -> None:
    log: list[tuple[str, int]] = []
    ex = LockstepExecutor(period_s=0.02)
    _graph(context, log, ex)
    ex.seal()
    ex.tick()  # t = 20 ms: nothing due
    assert log == []
    ex.tick()  # t = 40 ms: the 25 ms source timer and the 40 ms listener timers
    now = 40_000_000
    assert log[:6] == [('t0', now), ('r1', now), ('r2', now), ('s3', now), ('s4', now),
                       ('s5', now)]  # the source's message went through all stages, in order
    assert sorted(log[6:]) == [('T3', now), ('T4', now), ('T5', now)]
    assert ex.now_ns == now and ex.stats.ticks == 2
    assert ex.stats.published == 3 and ex.stats.messages == 5 and ex.stats.unscheduled == 0


def test_one_clock_for_every_node_and_timers_in_simulated_time(context) -> None:
    ex = LockstepExecutor(period_s=0.01, start_s=2.0)
    nodes = [_node(context, f'c{i}') for i in range(3)]
    for node in nodes:
        ex.add_node(node)
    fired: list[int] = []
    nodes[1].create_timer(0.05, lambda: fired.append(nodes[1].get_clock().now().nanoseconds))
    ex.seal()
    ex.spin_for(0.2)
    assert ex.now_ns == 2_200_000_000
    assert {n.get_clock().now().nanoseconds for n in nodes} == {2_200_000_000}
    assert fired == [2_050_000_000, 2_100_000_000, 2_150_000_000, 2_200_000_000]


def test_two_runs_give_the_same_order_of_callbacks() -> None:
    logs = []
    for _ in range(2):
        ctx = rclpy.Context()
        rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
        try:
            log: list[tuple[str, int]] = []
            ex = LockstepExecutor(period_s=0.02)
            _graph(ctx, log, ex)
            ex.seal()
            ex.spin_for(2.0)
            logs.append(log)
        finally:
            _destroy_created()
            rclpy.try_shutdown(context=ctx)
    assert len(logs[0]) > 500
    assert logs[0] == logs[1]


def test_world_hooks_step_first_and_callback_errors_do_not_stop_the_run(context) -> None:
    ex = LockstepExecutor(period_s=0.1)
    node = _node(context, 'hooked')
    ex.add_node(node)
    seen: list[tuple[str, float]] = []
    ex.add_hook(lambda dt: seen.append(('hook', ex.now_s)))

    def bad_timer():
        seen.append(('timer', ex.now_s))
        raise ValueError('boom')

    node.create_timer(0.1, bad_timer)
    ex.seal()
    ex.spin_for(0.3)
    assert [k for k, _ in seen] == ['hook', 'timer'] * 3
    assert len(ex.errors) == 3 and 'ValueError: boom' in ex.errors[0]


def test_messages_from_outside_the_graph_are_swept_and_counted(context) -> None:
    ex = LockstepExecutor(period_s=0.02)
    inside = _node(context, 'inside')
    ex.add_node(inside)
    got: list[int] = []
    inside.create_subscription(Int64, 'outside_topic', lambda m: got.append(m.data), 10)
    ex.seal()
    outsider = _node(context, 'outsider')  # not in the executor: an external publisher
    pub = outsider.create_publisher(Int64, 'outside_topic', 10)
    while pub.get_subscription_count() < 1:
        threading.Event().wait(0.01)
    pub.publish(Int64(data=7))
    ex.tick()
    assert got == [7] and ex.stats.unscheduled == 1


def test_services_are_served_in_the_tick(context) -> None:
    ex = LockstepExecutor(period_s=0.02)
    server = _node(context, 'server')
    ex.add_node(server)
    calls = []

    def serve(request, response):
        calls.append(1)
        response.success = True
        response.message = 'ok'
        return response

    server.create_service(Trigger, 'lockstep_test/trigger', serve)
    ex.seal()
    caller = _node(context, 'caller')  # outside the graph, like a user's tool
    client = caller.create_client(Trigger, 'lockstep_test/trigger')
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    ex.tick()
    spinner = SingleThreadedExecutor(context=context)
    spinner.add_node(caller)
    spinner.spin_until_future_complete(future, timeout_sec=10.0)
    assert calls == [1] and future.result().message == 'ok'


def test_refuses_guard_conditions_and_clients(context) -> None:
    ex = LockstepExecutor(period_s=0.02)
    node = _node(context, 'threaded')
    ex.add_node(node)
    node.create_guard_condition(lambda: None)
    with pytest.raises(LockstepError, match='expected no guard conditions'):
        ex.seal()
    ex2 = LockstepExecutor(period_s=0.02)
    node2 = _node(context, 'client_owner')
    ex2.add_node(node2)
    node2.create_client(Trigger, 'some_service')
    with pytest.raises(LockstepError, match='expected no service clients'):
        ex2.seal()


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'period_s': 0.0}, 'period_s must be > 0'),
    ({'period_s': 0.01, 'start_s': -1.0}, 'start_s must be >= 0')])
def test_bad_arguments(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        LockstepExecutor(**kwargs)


def test_the_phantom_steps_with_the_lockstep_clock(context, tmp_path) -> None:
    from geometry_msgs.msg import PoseStamped
    from rclpy.parameter import Parameter
    from rclpy.time import Time

    from cgail_rig.nodes.phantom_node import PhantomNode

    ex = LockstepExecutor(period_s=0.02)
    phantom = PhantomNode(context=context, enable_rosout=False, parameter_overrides=[
        Parameter('lockstep', value=True), Parameter('aurora_link', value=str(tmp_path / 'a')),
        Parameter('pose_rate_hz', value=10.0)])
    listener = _node(context, 'pose_listener')
    stamps: list[int] = []
    listener.create_subscription(
        PoseStamped, 'phantom/tip_pose',
        lambda m: stamps.append(Time.from_msg(m.header.stamp).nanoseconds),
        qos_profile_sensor_data)
    for node in (phantom, listener):
        ex.add_node(node)
    ex.add_hook(phantom.advance)
    ex.seal()
    try:
        ex.spin_for(0.5)
        assert phantom.sim_time == pytest.approx(0.5, abs=1e-12)
        # the true pose every 5th tick (10 Hz), stamped with the simulated time
        assert stamps == [100_000_000, 200_000_000, 300_000_000, 400_000_000, 500_000_000]
        # no steady-clock stepping timer: only the diagnostics and the markers (5 Hz) timers,
        # of the node clock
        assert [t.timer_period_ns for t in phantom.timers] == [1_000_000_000, 200_000_000]
        assert all(t.clock is phantom.get_clock() for t in phantom.timers)
    finally:
        phantom.destroy_node()


def _run_graph(transport: str, prefix: str) -> tuple[list[tuple[str, int]], LockstepExecutor]:
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    try:
        log: list[tuple[str, int]] = []
        ex = LockstepExecutor(period_s=0.02, transport=transport)
        _graph(ctx, log, ex, prefix)
        ex.seal()
        ex.spin_for(1.0)
        return log, ex
    finally:
        _destroy_created()
        rclpy.try_shutdown(context=ctx)


def test_the_in_process_transport_gives_the_same_run_as_dds() -> None:
    dds, ex_dds = _run_graph('dds', 'd_')
    inproc, ex_in = _run_graph('inprocess', 'i_')
    assert len(dds) > 200 and dds == inproc
    assert ex_in._routes  # the graph's volatile topics went in-process
    assert (ex_in.stats.published, ex_in.stats.messages) == (ex_dds.stats.published,
                                                              ex_dds.stats.messages)


def test_in_process_delivery_rounds_float32_as_dds_and_copies(context) -> None:
    from sensor_msgs.msg import Joy
    from std_msgs.msg import ColorRGBA

    got: dict[str, list] = {'dds': [], 'inprocess': []}
    sent = []
    for transport in ('dds', 'inprocess'):
        ex = LockstepExecutor(period_s=0.02, transport=transport)
        node = _node(context, f'f32_{transport}')
        ex.add_node(node)
        pub = node.create_publisher(Joy, f'f32_{transport}', 10)
        cpub = node.create_publisher(ColorRGBA, f'c32_{transport}', 10)
        node.create_subscription(Joy, f'f32_{transport}', got[transport].append, 10)
        node.create_subscription(ColorRGBA, f'c32_{transport}', got[transport].append, 10)
        msg = Joy(axes=[0.1, 1.0 / 3.0, -0.7], buttons=[1, 0])
        color = ColorRGBA(r=0.1, g=1.0 / 3.0, b=0.7, a=1.0)
        sent.append(msg)

        def fire(pub=pub, cpub=cpub, msg=msg, color=color):
            pub.publish(msg)
            cpub.publish(color)

        node.create_timer(0.02, fire)
        ex.seal()
        assert (id(pub) in ex._routes) == (transport == 'inprocess')
        ex.tick()
    assert len(got['dds']) == 2
    assert got['dds'] == got['inprocess']  # equal messages: the same float32 rounding
    assert got['inprocess'][1].g == float(np.float32(1.0 / 3.0)) != 1.0 / 3.0
    assert got['inprocess'][0] is not sent[1]  # a copy, as DDS delivers


def test_in_process_delivery_keeps_the_history_depth(context) -> None:
    ex = LockstepExecutor(period_s=0.02, transport='inprocess')
    node = _node(context, 'depth')
    ex.add_node(node)
    pub = node.create_publisher(Int64, 'depth_topic', 10)
    got: list[int] = []
    node.create_subscription(Int64, 'depth_topic', lambda m: got.append(m.data),
                             QoSProfile(depth=2))

    def burst():
        for k in range(5):
            pub.publish(Int64(data=k))

    node.create_timer(0.02, burst)
    ex.seal()
    ex.tick()
    assert got == [3, 4]  # KEEP_LAST 2: the oldest were dropped, as DDS drops them
    with pytest.raises(TypeError, match='Expected'):
        pub.publish('not a message')


def test_a_subscriber_outside_the_graph_gets_the_messages_through_dds(context) -> None:
    ex = LockstepExecutor(period_s=0.02, transport='inprocess')
    inside = _node(context, 'inside_pub')
    ex.add_node(inside)
    pub = inside.create_publisher(Int64, 'watched_topic', 10)
    got: list[int] = []
    inside.create_subscription(Int64, 'watched_topic', lambda m: got.append(m.data), 10)
    ex.seal()
    assert id(pub) in ex._routes
    outsider = _node(context, 'watcher')  # e.g. ros2 topic echo
    seen: list[int] = []
    outsider.create_subscription(Int64, 'watched_topic', lambda m: seen.append(m.data), 10)
    while pub.get_subscription_count() < 2:
        threading.Event().wait(0.01)
    pub.publish(Int64(data=5))
    ex.tick()
    spinner = SingleThreadedExecutor(context=context)
    spinner.add_node(outsider)
    spinner.spin_once(timeout_sec=5.0)
    assert got == [5] and seen == [5]


def test_a_latched_topic_goes_in_process_and_late_joiners_get_its_history(context) -> None:
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    latched = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ex = LockstepExecutor(period_s=0.02, transport='inprocess')
    inside = _node(context, 'latched_pub')
    ex.add_node(inside)
    pub = inside.create_publisher(Int64, 'latched_topic', latched)
    got: list[int] = []
    inside.create_subscription(Int64, 'latched_topic', lambda m: got.append(m.data), latched)
    raw: list[bytes] = []
    inside.create_subscription(Int64, 'latched_topic', raw.append, latched, raw=True)
    ex.seal()
    assert id(pub) in ex._routes
    for k in (1, 2, 3):
        pub.publish(Int64(data=k))
        ex.tick()
    assert got == [1, 2, 3] and len(raw) == 3
    late = _node(context, 'latched_late')  # e.g. a viewer: it must get the last 2 samples
    seen: list[int] = []
    late.create_subscription(Int64, 'latched_topic', lambda m: seen.append(m.data), latched)
    while pub.get_subscription_count() < 3:
        threading.Event().wait(0.01)
    ex.tick()  # (sweep_every 1) the history goes to DDS, the graph drops its copies
    assert id(pub) not in ex._routes
    spinner = SingleThreadedExecutor(context=context)
    spinner.add_node(late)
    spinner.spin_once(timeout_sec=5.0)
    spinner.spin_once(timeout_sec=0.5)
    assert seen == [2, 3] and got == [1, 2, 3] and len(raw) == 3
    pub.publish(Int64(data=4))  # through DDS from now on
    ex.tick()
    spinner.spin_once(timeout_sec=5.0)
    assert seen == [2, 3, 4] and got == [1, 2, 3, 4] and len(raw) == 4


def test_the_sweep_every_n_ticks_picks_up_outside_messages(context) -> None:
    ex = LockstepExecutor(period_s=0.02, transport='inprocess', sweep_every=3)
    inside = _node(context, 'swept')
    ex.add_node(inside)
    got: list[int] = []
    inside.create_subscription(Int64, 'swept_topic', lambda m: got.append(m.data), 10)
    ex.seal()
    outsider = _node(context, 'sweep_outsider')
    pub = outsider.create_publisher(Int64, 'swept_topic', 10)
    while pub.get_subscription_count() < 1:
        threading.Event().wait(0.01)
    pub.publish(Int64(data=9))
    ex.tick()
    ex.tick()
    assert got == []
    ex.tick()  # the third tick sweeps
    assert got == [9] and ex.stats.unscheduled == 1


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'transport': 'zenoh'}, 'transport must be one of'),
    ({'sweep_every': 0}, 'sweep_every must be an integer >= 1')])
def test_bad_transport_arguments(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        LockstepExecutor(period_s=0.02, **kwargs)


def _cdr_samples():
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import (
        Point,
        Point32,
        Polygon,
        PoseStamped,
        PoseWithCovarianceStamped,
        TransformStamped,
    )
    from nav_msgs.msg import Path
    from sensor_msgs.msg import JointState, Joy
    from std_msgs.msg import ColorRGBA, Empty, Header, String
    from tf2_msgs.msg import TFMessage
    from visualization_msgs.msg import Marker, MarkerArray

    return [PoseStamped(header=Header(frame_id='phantom')), PoseWithCovarianceStamped(),
            JointState(name=['bend_alpha', 'bend_gamma'], position=[1.0, 2.0]), JointState(),
            JointState(name=['a'], position=[1.0], effort=[3.0]),
            Joy(axes=[0.1, 0.2], buttons=[1, 0, 1]), Empty(), String(data='hello'),
            TFMessage(transforms=[TransformStamped(child_frame_id='catheter_tip')] * 2),
            MarkerArray(markers=[Marker(ns='x'), Marker(ns='yy', text='t', frame_locked=True)]),
            # sequences of messages of one primitive size (Point[], ColorRGBA[], Point32[])
            MarkerArray(markers=[Marker(ns='s', points=[Point(x=1.0), Point(y=2.0)],
                                        colors=[ColorRGBA(r=0.5)] * 3, text='after'),
                                 Marker(ns='t', points=[Point(z=3.0)])]),
            Polygon(points=[Point32(x=1.0), Point32(y=2.0), Point32(z=3.0)]),
            Path(header=Header(frame_id='p'), poses=[PoseStamped()] * 3),
            DiagnosticArray(status=[DiagnosticStatus(name='n',
                                                     values=[KeyValue(key='k', value='v')])])]


def test_zero_padding_gives_the_bytes_of_a_raw_take_from_dds(context) -> None:
    from rclpy.serialization import serialize_message

    from cgail_rig.cdr import zero_padding

    node = _node(context, 'cdr_check')
    for k, msg in enumerate(_cdr_samples()):
        msg_type = type(msg)
        sub = node.create_subscription(msg_type, f'cdr_{k}', lambda m: None, 10, raw=True)
        pub = node.create_publisher(msg_type, f'cdr_{k}', 10)
        while pub.get_subscription_count() < 1:
            threading.Event().wait(0.01)
        pub.publish(msg)
        taken = sub.handle.take_message(msg_type, True)[0]
        assert zero_padding(serialize_message(msg), msg_type) == taken, msg_type.__name__


def test_a_raw_subscriber_gets_the_same_bytes_in_process_as_through_dds(context) -> None:
    from sensor_msgs.msg import JointState

    got: dict[str, list] = {'dds': [], 'inprocess': []}
    for transport in ('dds', 'inprocess'):
        ex = LockstepExecutor(period_s=0.02, transport=transport)
        node = _node(context, f'raw_{transport}')
        ex.add_node(node)
        pub = node.create_publisher(JointState, f'raw_{transport}', 10)
        node.create_subscription(JointState, f'raw_{transport}', got[transport].append, 10,
                                 raw=True)
        node.create_timer(0.02, lambda pub=pub: pub.publish(
            JointState(name=['bend_alpha'], position=[0.25])))
        ex.seal()
        assert (id(pub) in ex._routes) == (transport == 'inprocess')
        ex.tick()
    assert len(got['dds']) == 1 and got['dds'] == got['inprocess']


def test_zero_padding_refuses_what_it_cannot_walk() -> None:
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from cgail_rig.cdr import CdrError, zero_padding

    data = serialize_message(String(data='hello'))
    with pytest.raises(CdrError, match='encapsulation header'):
        zero_padding(b'\x07\x01' + data[2:], String)
    with pytest.raises(CdrError, match='expected'):
        zero_padding(data[:9], String)  # cut inside the string


def _same_message(a, b, path='msg') -> None:
    """The same field values of the same types, recursively (== alone lets 1 equal 1.0)."""
    import array

    assert type(a) is type(b), (path, type(a), type(b))
    if hasattr(a, 'SLOT_TYPES'):
        for slot in a.__slots__:
            _same_message(getattr(a, slot), getattr(b, slot), f'{path}.{slot}')
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _same_message(x, y, f'{path}[{k}]')
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape, a.tobytes(), a.flags.writeable, a.flags.c_contiguous) == \
            (b.dtype, b.shape, b.tobytes(), b.flags.writeable, b.flags.c_contiguous), path
    elif isinstance(a, array.array):
        assert (a.typecode, a.tobytes()) == (b.typecode, b.tobytes()), path
    else:
        assert a == b, (path, a, b)


def _codec_samples():
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from sensor_msgs.msg import Joy

    cov = PoseWithCovarianceStamped()
    cov.header.frame_id = 'phant\u00f6m\x00after the NUL'  # UTF-8, cut at the NUL as rosidl does
    cov.pose.covariance = np.arange(36.0) / 7.0
    cov.pose.pose.position.x = -0.1
    return [*_cdr_samples(), cov, Joy(axes=[0.1, 1e-40, -3.3], buttons=[1, -2, 7])]


def test_the_codec_gives_rclpys_bytes_with_zero_padding_and_rclpys_messages() -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    from cgail_rig.cdr import decoder, encoder, zero_padding

    for msg in _codec_samples():
        msg_type = type(msg)
        data = serialize_message(msg)
        expected = zero_padding(data, msg_type)
        assert encoder(msg_type)(msg) == expected, msg_type.__name__
        assert encoder(msg_type)(msg) == expected  # (again: its strings' bytes cached)
        for payload in (data, expected):  # (the padding is not read)
            got = decoder(msg_type)(payload)
            _same_message(deserialize_message(payload, msg_type), got)
            assert got == msg or msg_type.__name__ in ('Joy', 'PoseWithCovarianceStamped')


def test_the_codec_leaves_to_rclpy_what_it_does_not_convert_as_rclpy() -> None:
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Header

    from cgail_rig.cdr import CdrError, decoder, encoder, Fallback, zero_padding

    msg = JointState()
    msg._position = [1.0]  # not the array.array the setter makes: rclpy's conversion
    with pytest.raises(Fallback):
        encoder(JointState)(msg)
    with pytest.raises(CdrError, match='found char'):
        encoder(type('WithChar', (), {'_fields_and_field_types': {'c': 'char'},
                                      'SLOT_TYPES': (type('BasicType', (), {
                                          'typename': 'char'})(),)}))
    with pytest.raises(Fallback):
        decoder(Header)(b'\x00\x00\x00\x00' + zero_padding(serialize_message(Header()),
                                                           Header)[4:])


def test_in_process_delivery_falls_back_to_rclpy_for_what_the_codec_refuses(context) -> None:
    from sensor_msgs.msg import JointState

    ex = LockstepExecutor(period_s=0.02, transport='inprocess')
    node = _node(context, 'codec_fallback')
    ex.add_node(node)
    pub = node.create_publisher(JointState, 'codec_fallback', 10)
    got, raw = [], []
    node.create_subscription(JointState, 'codec_fallback', got.append, 10)
    node.create_subscription(JointState, 'codec_fallback', raw.append, 10, raw=True)

    def publish() -> None:
        msg = JointState(name=['bend_alpha'])
        msg._position = [0.25]  # a list: rclpy's path (the encoder refuses it)
        pub.publish(msg)
        pub.publish(JointState(name=['bend_gamma'], position=[0.5]))

    node.create_timer(0.02, publish)
    ex.seal()
    assert id(pub) in ex._routes
    ex.tick()
    assert [(m.name, list(m.position)) for m in got] == [(['bend_alpha'], [0.25]),
                                                         (['bend_gamma'], [0.5])]
    from rclpy.serialization import deserialize_message
    assert [deserialize_message(r, JointState) for r in raw] == got

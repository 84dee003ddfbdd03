"""Recorder/player round trip in-process, SIGINT/SIGTERM during recording, bad bags."""

from collections.abc import Callable
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import QosDurability, QosReliability

from cgail_bags.bagio import BagWriter, iter_raw, open_bag, TYPESTORE
from cgail_bags.errors import BagError
from cgail_bags.play import BagPlayer, build_parser, PlayerConfig
from cgail_bags.qos import COMMAND, LATCHED, SENSOR
from cgail_bags.record import BagRecorder, RecorderConfig
from cgail_node_utils.testing import spin_until

FIXTURE = Path(__file__).resolve().parents[4] / 'bags' / 'fixtures' / 'cgail_trial'
T0 = 1_700_000_000 * 10**9
T = TYPESTORE.types


def header(ns: int, frame: str = 'phantom'):
    return T['std_msgs/msg/Header'](
        stamp=T['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9),
        frame_id=frame)


def pose(ns: int, x: float):
    return T['geometry_msgs/msg/PoseStamped'](header=header(ns), pose=T['geometry_msgs/msg/Pose'](
        position=T['geometry_msgs/msg/Point'](x=x, y=-x, z=2 * x),
        orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.6, w=0.8)))


def make_source_bag(path: Path) -> None:
    """20 poses (reliable), 20 joint states (best effort) at 50 Hz and one latched path."""
    with BagWriter(path, custom_data={'condition': 'roundtrip'}) as w:
        w.add_topic('/rt/path', 'nav_msgs/msg/Path', [LATCHED])
        w.add_topic('/rt/pose', 'geometry_msgs/msg/PoseStamped', [COMMAND])
        w.add_topic('/rt/joints', 'sensor_msgs/msg/JointState', [SENSOR])
        path_msg = T['nav_msgs/msg/Path'](header=header(T0),
                                          poses=[pose(T0, 0.001 * i) for i in range(7)])
        w.write('/rt/path', T0, TYPESTORE.serialize_cdr(path_msg, 'nav_msgs/msg/Path'))
        for i in range(20):
            ns = T0 + (i + 1) * 20_000_000
            w.write('/rt/pose', ns,
                    TYPESTORE.serialize_cdr(pose(ns, 0.01 * i), 'geometry_msgs/msg/PoseStamped'))
            joints = T['sensor_msgs/msg/JointState'](
                header=header(ns, ''), name=['bend_alpha', 'bend_gamma'],
                position=np.array([0.1 * i, -0.05 * i]), velocity=np.array([], float),
                effort=np.array([], float))
            w.write('/rt/joints', ns + 1000,
                    TYPESTORE.serialize_cdr(joints, 'sensor_msgs/msg/JointState'))


def as_plain(msg):
    """Decoded message -> nested tuples/lists (numpy arrays as lists) for equality."""
    if isinstance(msg, np.ndarray):
        return msg.tolist()
    if isinstance(msg, list | tuple):
        return [as_plain(x) for x in msg]
    if hasattr(msg, '__dataclass_fields__'):
        return {k: as_plain(getattr(msg, k)) for k in msg.__dataclass_fields__}
    return msg


def decoded(bag: Path) -> tuple[dict[str, list], dict[str, object]]:
    msgs: dict[str, list] = {}
    qos: dict[str, object] = {}
    with open_bag(bag) as reader:
        for conn in reader.connections:
            qos[conn.topic] = conn.ext.offered_qos_profiles
        for conn, _, raw in iter_raw(reader):
            msgs.setdefault(conn.topic, []).append(
                as_plain(TYPESTORE.deserialize_cdr(raw, conn.msgtype)))
    return msgs, qos


def test_play_then_record_round_trip_keeps_every_decoded_field(ros, tmp_path: Path) -> None:
    source = tmp_path / 'source'
    make_source_bag(source)
    player_node = rclpy.create_node('bag_player_rt')
    recorder_node = rclpy.create_node('bag_recorder_rt')
    executor = SingleThreadedExecutor()
    executor.add_node(recorder_node)
    recorder = BagRecorder(recorder_node, RecorderConfig(
        output=tmp_path / 'copy', topics=('rt/path', '/rt/pose', 'rt/joints'),
        discovery_period=0.1, flush_period=0.2))
    player = BagPlayer(player_node, PlayerConfig(bag=source, rate=1.0,
                                                 wait_for_subscribers=10.0))
    assert spin_until(executor, lambda: len(recorder.topics) == 3, 10.0), recorder.topics
    done = threading.Event()
    count: list[int] = []
    thread = threading.Thread(target=lambda: (count.append(player.play()), done.set()))
    thread.start()
    assert spin_until(executor, lambda: done.is_set() and recorder.received >= 41, 15.0)
    thread.join()
    # Latched: a subscriber joining after playback still gets the path.
    late: list[bytes] = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    from nav_msgs.msg import Path as PathMsg
    recorder_node.create_subscription(PathMsg, '/rt/path', late.append, latched, raw=True)
    assert spin_until(executor, lambda: len(late) == 1, 15.0)
    assert recorder.stop() == 41
    player_node.destroy_node()
    recorder_node.destroy_node()

    assert count == [41]
    original, _ = decoded(source)
    copy, qos = decoded(tmp_path / 'copy')
    assert copy == original
    assert qos['/rt/path'][0].durability == QosDurability.TRANSIENT_LOCAL
    assert qos['/rt/path'][0].reliability == QosReliability.RELIABLE
    assert qos['/rt/joints'][0].reliability == QosReliability.BEST_EFFORT
    assert late[0] == TYPESTORE.serialize_cdr(
        TYPESTORE.deserialize_cdr(late[0], 'nav_msgs/msg/Path'), 'nav_msgs/msg/Path')


def test_rate_and_start_offset_set_the_timing(ros, tmp_path: Path) -> None:
    source = tmp_path / 'source'
    make_source_bag(source)
    node = rclpy.create_node('bag_player_timing')
    fast = BagPlayer(node, PlayerConfig(bag=source, rate=4.0, topics=('rt/pose',)))
    start = time.monotonic()
    assert fast.play() == 20
    elapsed = time.monotonic() - start
    assert 0.38 / 4 <= elapsed < 1.0  # 0.38 s of poses at 4x
    offset = BagPlayer(node, PlayerConfig(bag=source, start_offset=0.2, topics=('rt/pose',)))
    assert offset.play() == 11  # poses at 0.20 .. 0.40 s
    stop = threading.Event()
    looping = BagPlayer(node, PlayerConfig(bag=source, rate=10.0, loop=True,
                                           topics=('rt/pose',)))
    timer = threading.Timer(0.3, stop.set)
    timer.start()
    assert looping.play(stop) > 20
    node.destroy_node()


def test_clock_publishes_the_bag_time_at_the_clock_rate(ros, tmp_path: Path) -> None:
    """``--clock 50 --rate 2``: a tick every 20 ms of wall time, 40 ms of bag time apart, from
    the bag's start to its last played message; a ``use_sim_time`` node follows it."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    source = tmp_path / 'source'
    make_source_bag(source)
    player_node = rclpy.create_node('bag_player_clock')
    listener = rclpy.create_node('clock_listener',
                                 parameter_overrides=[Parameter('use_sim_time', value=True)])
    executor = SingleThreadedExecutor()
    executor.add_node(listener)
    ticks: list[int] = []
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    clock_sub = listener.create_subscription(
        Clock, '/clock', lambda m: ticks.append(m.clock.sec * 10**9 + m.clock.nanosec),
        best_effort)
    poses: list[bytes] = []
    pose_sub = listener.create_subscription(PoseStamped, '/rt/pose', poses.append, 100,
                                            raw=True)
    player = BagPlayer(player_node, PlayerConfig(bag=source, rate=2.0, topics=('rt/pose',),
                                                 clock_hz=50.0))
    assert spin_until(executor, lambda: player.clock_publisher.get_subscription_count() > 0
                      and clock_sub.get_publisher_count() > 0
                      and pose_sub.get_publisher_count() > 0, 10.0)
    done = threading.Event()
    count: list[int] = []
    thread = threading.Thread(target=lambda: (count.append(player.play()), done.set()))
    start = time.monotonic()
    thread.start()
    # the bag starts at T0 (the path) and its last pose is at T0 + 0.4 s: ticks 0 .. 10
    expected = [T0 + k * 40_000_000 for k in range(11)]
    assert spin_until(executor, lambda: done.is_set() and len(ticks) == 11
                      and len(poses) == 20, 15.0), (ticks, len(poses))
    thread.join()
    assert 0.18 <= time.monotonic() - start < 5.0
    assert count == [20] and player.clock_ticks == 11
    assert ticks == expected
    assert listener.get_clock().now().nanoseconds == expected[-1]
    player_node.destroy_node()
    listener.destroy_node()


def test_clock_option_defaults_to_40_hz_as_ros2_bag_play(ros, tmp_path: Path) -> None:
    parse = build_parser().parse_args
    assert [parse(words).clock for words in (['b'], ['b', '--clock'], ['b', '--clock', '100'])] \
        == [0.0, 40.0, 100.0]
    bag = tmp_path / 'clocked'
    with BagWriter(bag) as w:
        w.add_topic('/clock', 'rosgraph_msgs/msg/Clock', [SENSOR])
        w.write('/clock', T0, TYPESTORE.serialize_cdr(
            T['rosgraph_msgs/msg/Clock'](clock=header(T0).stamp), 'rosgraph_msgs/msg/Clock'))
    node = rclpy.create_node('bag_player_clocked')
    assert BagPlayer(node, PlayerConfig(bag=bag)).clock_publisher is None
    with pytest.raises(BagError, match='the bag records /clock itself'):
        BagPlayer(node, PlayerConfig(bag=bag, clock_hz=40.0))
    node.destroy_node()


def damaged_copy(tmp_path: Path, damage: Callable[[bytes], bytes]) -> Path:
    bag = tmp_path / 'cut'
    shutil.copytree(FIXTURE, bag)
    mcap = bag / 'cgail_trial.mcap'
    mcap.write_bytes(damage(mcap.read_bytes()))
    return bag


@pytest.mark.parametrize('damage', [
    lambda b: b[: len(b) // 2],
    lambda b: b[:-40],
    lambda b: b[:8],
    lambda b: b[:30000] + bytes(x ^ 0xFF for x in b[30000:30200]) + b[30200:],
    lambda b: b[:2000] + bytes(5000) + b[7000:],
], ids=['half', 'footer', 'magic-only', 'flipped-bytes', 'zeroed-chunk'])
def test_player_reports_a_damaged_bag_clearly(ros, tmp_path: Path, damage) -> None:
    node = rclpy.create_node('bag_player_bad')
    bag = damaged_copy(tmp_path, damage)
    with pytest.raises(BagError, match=r'cut: truncated or corrupt bag'):
        BagPlayer(node, PlayerConfig(bag=bag, rate=100.0)).play()
    node.destroy_node()


def test_player_reports_missing_bags_and_topics(ros, tmp_path: Path) -> None:
    node = rclpy.create_node('bag_player_missing')
    with pytest.raises(BagError, match='no such bag'):
        BagPlayer(node, PlayerConfig(bag=tmp_path / 'missing'))
    with pytest.raises(BagError, match=r"expected topics \['/nope'\] to play, found none"):
        BagPlayer(node, PlayerConfig(bag=FIXTURE, topics=('nope',)))
    node.destroy_node()


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('rate', 0.0, 'rate must be a positive factor'),
    ('start_offset', -1.0, 'start_offset must be >= 0'),
    ('wait_for_subscribers', -1.0, 'wait_for_subscribers must be >= 0'),
    ('clock_hz', -40.0, r'clock_hz must be >= 0 Hz \(0: no /clock\), found -40.0'),
    ('clock_hz', float('inf'), 'clock_hz must be >= 0 Hz'),
])
def test_player_config_validation(field: str, value: float, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        PlayerConfig(bag=FIXTURE, **{field: value})


def test_recorder_config_validation(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match='topics must name at least one topic'):
        RecorderConfig(output=tmp_path / 'x')
    with pytest.raises(ValueError, match='flush_period must be > 0'):
        RecorderConfig(output=tmp_path / 'x', topics=('a',), flush_period=0.0)


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_signal_during_recording_leaves_a_complete_bag(ros, tmp_path: Path, signum) -> None:
    from std_msgs.msg import String

    out = tmp_path / 'rec'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'cgail_bags.record', '-o', str(out), 'sig/chatter',
         '--condition', 'cgail', '--discovery-period', '0.1', '--flush-period', '0.2'],
        env=os.environ.copy(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        node = rclpy.create_node('sig_talker')
        pub = node.create_publisher(String, 'sig/chatter', QoSProfile(
            depth=200, reliability=ReliabilityPolicy.RELIABLE))
        deadline = time.monotonic() + 20.0
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pub.get_subscription_count() == 1, 'the recorder never subscribed'
        for i in range(150):
            pub.publish(String(data=f'msg {i}'))
            time.sleep(0.002)
        # the signal comes while the recorder runs, after it wrote the last message (a flush
        # every 0.2 s): a loaded machine may deliver the burst late, never loses it
        mcap = out / 'rec.mcap'

        def written() -> bool:
            return mcap.exists() and b'msg 149' in mcap.read_bytes()
        deadline = time.monotonic() + 15.0
        while not written() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert written(), 'the recorder never wrote the last message'
        proc.send_signal(signum)
        output, _ = proc.communicate(timeout=20.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, output
    assert 'wrote 150 messages' in output
    with open_bag(out) as reader:
        from cgail_bags.bagio import bag_custom_data
        assert bag_custom_data(reader) == {'condition': 'cgail'}
        got = [TYPESTORE.deserialize_cdr(raw, c.msgtype).data for c, _, raw in iter_raw(reader)]
    assert got == [f'msg {i}' for i in range(150)]
    node.destroy_node()


def test_writer_thread_flushes_messages_to_disk_before_close(ros, tmp_path: Path) -> None:
    from std_msgs.msg import String

    node = rclpy.create_node('flush_recorder')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    pub = node.create_publisher(String, 'flush/chatter', 10)
    recorder = BagRecorder(node, RecorderConfig(output=tmp_path / 'f', topics=('flush/chatter',),
                                                flush_period=0.1, discovery_period=0.1))
    assert spin_until(executor, lambda: pub.get_subscription_count() == 1, 10.0)
    for i in range(5):
        pub.publish(String(data=f'flushed {i}'))
    assert spin_until(executor, lambda: recorder.received == 5, 15.0)
    mcap = tmp_path / 'f' / 'f.mcap'
    assert spin_until(executor, lambda: b'flushed 4' in mcap.read_bytes(), 15.0)
    assert not (tmp_path / 'f' / 'metadata.yaml').exists()  # still open: written by close
    assert recorder.stop() == 5
    assert (tmp_path / 'f' / 'metadata.yaml').exists()
    node.destroy_node()


def test_record_all_skips_ros_infrastructure(ros, tmp_path: Path) -> None:
    from std_msgs.msg import String

    node = rclpy.create_node('all_recorder')
    pub = node.create_publisher(String, 'all/chatter', 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    recorder = BagRecorder(node, RecorderConfig(output=tmp_path / 'all', all_topics=True,
                                                discovery_period=0.1))
    assert spin_until(executor, lambda: '/all/chatter' in recorder.topics, 10.0)
    pub.publish(String(data='x'))
    assert spin_until(executor, lambda: recorder.received >= 1, 15.0)
    recorder.stop()
    node.destroy_node()
    with open_bag(tmp_path / 'all') as reader:
        topics = {c.topic: c.msgcount for c in reader.connections}
    assert topics['/all/chatter'] == 1
    # The node's own /rosout and /parameter_events publishers exist but are not recorded.
    assert '/rosout' not in topics
    assert '/parameter_events' not in topics


def test_max_duration_ends_the_recording_by_itself(tmp_path: Path) -> None:
    out = tmp_path / 'timed'
    start = time.monotonic()
    result = subprocess.run(
        [sys.executable, '-m', 'cgail_bags.record', '--all', '-o', str(out),
         '--max-duration', '1'],
        env=os.environ.copy(), capture_output=True, text=True, timeout=30.0, check=False)
    assert result.returncode == 0, result.stderr
    assert time.monotonic() - start < 20.0
    assert f'wrote 0 messages on no topics to {out}' in result.stdout
    with open_bag(out) as reader:
        assert reader.message_count == 0


def test_messages_flushed_before_a_hard_kill_are_recovered(ros, tmp_path: Path) -> None:
    from std_msgs.msg import String

    from cgail_bags.recover import recover_bag

    out = tmp_path / 'killed'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'cgail_bags.record', '-o', str(out), 'kill/chatter',
         '--discovery-period', '0.1', '--flush-period', '0.2'],
        env=os.environ.copy(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        node = rclpy.create_node('kill_talker')
        pub = node.create_publisher(String, 'kill/chatter', QoSProfile(
            depth=100, reliability=ReliabilityPolicy.RELIABLE))
        deadline = time.monotonic() + 20.0
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pub.get_subscription_count() == 1, 'the recorder never subscribed'
        for i in range(30):
            pub.publish(String(data=f'kept {i}'))
        mcap = out / 'killed.mcap'
        deadline = time.monotonic() + 10.0
        while b'kept 29' not in mcap.read_bytes() and time.monotonic() < deadline:
            time.sleep(0.1)
        proc.kill()
        proc.wait(timeout=10.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    node.destroy_node()
    with pytest.raises(BagError, match='truncated or corrupt bag'), open_bag(out):
        pass
    result = recover_bag(out, tmp_path / 'recovered')
    assert result.messages == 30
    assert result.topics == ('/kill/chatter',)
    with open_bag(tmp_path / 'recovered') as reader:
        qos = reader.connections[0].ext.offered_qos_profiles
        got = [TYPESTORE.deserialize_cdr(raw, c.msgtype).data for c, _, raw in iter_raw(reader)]
    assert got == [f'kept {i}' for i in range(30)]
    assert qos[0].reliability == QosReliability.RELIABLE


def test_recover_refuses_a_file_without_a_complete_chunk(tmp_path: Path) -> None:
    from cgail_bags.recover import recover_bag

    cut = tmp_path / 'cut.mcap'
    cut.write_bytes((FIXTURE / 'cgail_trial.mcap').read_bytes()[:30000])
    with pytest.raises(BagError, match='nothing to recover'):
        recover_bag(cut, tmp_path / 'out')
    (tmp_path / 'text.mcap').write_text('not a bag')
    with pytest.raises(BagError, match='not an MCAP file'):
        recover_bag(tmp_path / 'text.mcap', tmp_path / 'out2')
    result = recover_bag(FIXTURE, tmp_path / 'copy')
    assert result.complete
    assert result.messages == 403


def test_recover_keeps_a_damaged_chunk_up_to_its_first_bad_record(tmp_path: Path,
                                                                 capsys) -> None:
    """The fixture holds one uncompressed chunk without a CRC (as rosbags writes them): a
    message record whose length runs past the chunk ends the recovery of that chunk there,
    keeping every message before it, and the tool says part of the source is lost."""
    from cgail_bags.recover import main, recover_bag

    data = bytearray((FIXTURE / 'cgail_trial.mcap').read_bytes())
    with open_bag(FIXTURE) as reader:
        original = [bytes(raw) for _, _, raw in iter_raw(reader)]
    # walk the records: the file's first chunk (opcode 6), then its records up to message 100
    pos = 8
    while data[pos] != 0x06:
        pos += 9 + int.from_bytes(data[pos + 1:pos + 9], 'little')
    header = pos + 9 + 8 + 8 + 8 + 4
    assert data[header:header + 4] == bytes(4)  # no compression
    pos, seen = header + 4 + 8, 0
    while True:
        if data[pos] == 0x05:
            if seen == 100:
                break
            seen += 1
        pos += 9 + int.from_bytes(data[pos + 1:pos + 9], 'little')
    data[pos + 1:pos + 9] = (10**9).to_bytes(8, 'little')
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(bytes(data))
    result = recover_bag(bad, tmp_path / 'kept')
    assert (result.messages, result.complete) == (100, False)
    with open_bag(tmp_path / 'kept') as reader:
        assert sorted(bytes(raw) for _, _, raw in iter_raw(reader)) == sorted(original[:100])
    assert main([str(bad), '-o', str(tmp_path / 'kept2')]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 1 and 'wrote 100 messages on 3 topics' in out[0]
    assert 'cut or damaged' in out[0]


def test_the_recorder_queue_holds_a_burst() -> None:
    """The recorder subscribes keep-last deep enough for a burst it has not taken yet (depth
    100 lost 50 of a 150-message burst on a loaded machine), and never shallower than offered."""
    from cgail_bags.qos import COMMAND, make_qos, RECORD_DEPTH, subscription_qos

    assert RECORD_DEPTH >= 1000
    assert subscription_qos([COMMAND]).depth == RECORD_DEPTH
    assert subscription_qos([make_qos(True, False, 2 * RECORD_DEPTH)]).depth == 2 * RECORD_DEPTH

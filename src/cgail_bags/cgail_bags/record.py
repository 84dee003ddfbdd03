"""``cgail bag record``: record ROS 2 topics to a rosbag2 MCAP bag (rosbags + rclpy raw
subscriptions).

    cgail bag record -o runs/cgail/t1 --condition cgail planner/goal
    cgail bag record -o runs/all_topics --all --max-duration 200

* Topics are discovered from the graph (``get_topic_names_and_types``) every
  ``--discovery-period`` s; a topic is subscribed once it has a publisher, with a QoS compatible
  with every offered profile (best effort if any publisher is, transient local only if all are,
  so latched topics deliver their last sample). The offered profiles are stored in the bag's
  ``metadata.yaml`` (``offered_qos_profiles``) for the player.
* Subscriptions are raw (``raw=True``): the CDR bytes are queued with the receive time (ns) and a
  writer thread writes them, so the executor never blocks on disk; the writer wakes every
  ``WRITE_PERIOD_S`` and writes what was queued (a wake-up per message would cost the executor
  a thread switch each), and every ``--flush-period`` s it closes the pending MCAP chunk and
  flushes the file.
* SIGINT/SIGTERM (or ``--max-duration``) stop the recording cleanly: subscriptions are drained,
  destroyed, the queue is written out and the bag is closed (MCAP summary + metadata.yaml), so
  nothing received is lost.
"""

from __future__ import annotations

import argparse
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
import sys
import threading
import time
from typing import Any

from cgail_bags.bagio import BagWriter
from cgail_bags.errors import BagError
from cgail_bags.qos import from_rclpy, subscription_qos
from cgail_bags.rosutil import get_message_class, stop_on_signals
from cgail_sim.cli_help import tool_parser

#: Topics never recorded by ``--all`` (ROS 2 infrastructure).
EXCLUDED_BY_ALL = ('/rosout', '/parameter_events')
#: Wall seconds between the writer thread's turns (module docstring).
WRITE_PERIOD_S = 0.05


@dataclass(frozen=True)
class RecorderConfig:
    """What and how to record."""

    output: Path
    """Bag directory to create (must not exist)."""
    topics: tuple[str, ...] = ()
    """Topics to record (relative or absolute names); empty with ``all_topics``."""
    all_topics: bool = False
    """Record every topic except /rosout and /parameter_events."""
    condition: str = ''
    """Trial condition label stored in custom_data (``condition``); empty: none."""
    flush_period: float = 1.0
    """Seconds between chunk flushes of the writer thread; > 0."""
    discovery_period: float = 0.5
    """Seconds between graph scans for new topics; > 0."""
    compress: bool = False
    """zstd-compress the bag's MCAP chunks (:class:`~cgail_bags.bagio.BagWriter`)."""

    def __post_init__(self) -> None:
        if not self.all_topics and not self.topics:
            raise ValueError('topics must name at least one topic (or use all_topics), found none')
        if self.flush_period <= 0.0:
            raise ValueError(f'flush_period must be > 0 s, found {self.flush_period}')
        if self.discovery_period <= 0.0:
            raise ValueError(f'discovery_period must be > 0 s, found {self.discovery_period}')


class BagRecorder:
    """Records topics of an existing node into a bag (use from a CLI or in-process in tests).

    Args:
        node: The rclpy node whose subscriptions receive the messages.
        config: What and how to record.
    """

    def __init__(self, node: Any, config: RecorderConfig) -> None:
        self._node = node
        self.config = config
        custom = {'condition': config.condition} if config.condition else {}
        self._writer = BagWriter(config.output, custom_data=custom, compress=config.compress)
        # (kind, topic, payload), or None: the end; appended by the executor, taken by the writer
        self._queue: deque[tuple[str, Any, Any] | None] = deque()
        self._stopping = threading.Event()
        self._subs: dict[str, Any] = {}
        self._recorded: list[str] = []
        # Relative names resolve against the root namespace, as for `ros2 bag record`.
        self._wanted_names = {'/' + t.lstrip('/') for t in config.topics}
        self._received = 0
        self.counts: dict[str, int] = {}
        """Messages received per topic."""
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._write_loop, name='bag_writer', daemon=True)
        self._thread.start()
        self._timer = node.create_timer(config.discovery_period, self.discover)
        self.discover()

    @property
    def received(self) -> int:
        """Messages received so far."""
        return self._received

    @property
    def topics(self) -> list[str]:
        """Topics subscribed so far."""
        return sorted(self._recorded)

    def _wanted(self, topic: str) -> bool:
        if self.config.all_topics:
            return topic not in EXCLUDED_BY_ALL
        return topic in self._wanted_names

    def discover(self) -> None:
        """Subscribe to wanted topics that now have a publisher."""
        for topic, types in self._node.get_topic_names_and_types():
            if topic in self._subs or not types or not self._wanted(topic):
                continue
            infos = self._node.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            msgtype = types[0]
            offered = [from_rclpy(info.qos_profile) for info in infos]
            try:
                msg_class = get_message_class(msgtype)
            except BagError as exc:
                self._node.get_logger().warning(f'not recording {topic}: {exc}')
                self._subs[topic] = None
                continue
            self._queue.append(('add', topic, (msgtype, offered)))

            self.counts[topic] = 0

            def callback(data: bytes, topic: str = topic) -> None:
                self._received += 1
                self.counts[topic] += 1
                self._queue.append(('msg', topic, (self._node.get_clock().now().nanoseconds,
                                                   data)))

            self._subs[topic] = self._node.create_subscription(
                msg_class, topic, callback, subscription_qos(offered), raw=True)
            self._recorded.append(topic)
            self._node.get_logger().info(f'recording {topic} [{msgtype}]')

    def _write_loop(self) -> None:
        last_flush = time.monotonic()
        items = self._queue
        while True:
            self._stopping.wait(WRITE_PERIOD_S)
            while items:
                item = items.popleft()
                if item is None:
                    return
                kind, topic, payload = item
                try:
                    if kind == 'add':
                        self._writer.add_topic(topic, payload[0], payload[1])
                    else:
                        self._writer.write(topic, payload[0], payload[1])
                except (BagError, OSError) as exc:
                    self._error = exc
                    return
            try:
                if time.monotonic() - last_flush >= self.config.flush_period:
                    self._writer.flush()
                    last_flush = time.monotonic()
            except (BagError, OSError) as exc:
                self._error = exc
                return

    def stop(self) -> int:
        """Stop recording: destroy subscriptions, write the queue out, close the bag.

        Returns:
            Number of messages written.

        Raises:
            BagError: The writer thread failed (e.g. disk full).
        """
        self._node.destroy_timer(self._timer)
        for sub in self._subs.values():
            if sub is not None:
                self._node.destroy_subscription(sub)
        self._subs.clear()
        self._queue.append(None)
        self._stopping.set()
        self._thread.join()
        self._writer.close()
        if self._error is not None:
            raise BagError(f'{self.config.output}: recording failed ({self._error})')
        return self._writer.count


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail bag record``."""
    parser = tool_parser('bag record', __doc__, details=True)
    parser.add_argument('topics', nargs='*', help='topics to record (e.g. em_tracker/tip_pose)')
    parser.add_argument('-a', '--all', action='store_true', help='record all topics')
    parser.add_argument('-o', '--output', type=Path, default=None,
                        help='bag directory to create (default: runs/bags/rosbag2_<date>-<time>)')
    parser.add_argument('--max-duration', type=float, default=0.0,
                        help='stop after this many seconds (0: until SIGINT/SIGTERM)')
    parser.add_argument('--condition', default='',
                        help='trial condition label stored in the bag metadata (e.g. cgail)')
    parser.add_argument('--flush-period', type=float, default=1.0,
                        help='seconds between flushes to disk (default 1)')
    parser.add_argument('--discovery-period', type=float, default=0.5,
                        help='seconds between scans for new topics (default 0.5)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail bag record``; returns the exit status."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from cgail_node_utils.entry_point import try_shutdown

    parser = build_parser()
    args, ros_args = parser.parse_known_args(argv)
    if args.max_duration < 0.0:
        parser.error(f'--max-duration must be >= 0 s, found {args.max_duration}')
    output = args.output or Path('runs', 'bags', time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S'))
    try:
        config = RecorderConfig(output=output, topics=tuple(args.topics), all_topics=args.all,
                                condition=args.condition, flush_period=args.flush_period,
                                discovery_period=args.discovery_period)
    except ValueError as exc:
        parser.error(str(exc))
    rclpy.init(args=ros_args, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bag_recorder')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    status = 0
    with stop_on_signals() as stop:
        try:
            recorder = BagRecorder(node, config)
        except BagError as exc:
            print(f'cgail bag record: error: {exc}', file=sys.stderr)
            node.destroy_node()
            try_shutdown()
            return 2
        print(f'cgail bag record: recording to {output}', flush=True)
        start = time.monotonic()
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)
            if args.max_duration and time.monotonic() - start >= args.max_duration:
                break
        # Drain what the middleware already delivered (until 0.2 s without a message, at most
        # 1 s: a topic that keeps publishing must not hold the shutdown).
        hard_stop = time.monotonic() + 1.0
        idle_until = time.monotonic() + 0.2
        while time.monotonic() < min(idle_until, hard_stop):
            before = recorder.received
            executor.spin_once(timeout_sec=0.02)
            if recorder.received != before:
                idle_until = time.monotonic() + 0.2
        try:
            count = recorder.stop()
            print(f'cgail bag record: wrote {count} messages on {len(recorder.topics) or "no"} '
                  f'topics to {output}', flush=True)
        except BagError as exc:
            print(f'cgail bag record: error: {exc}', file=sys.stderr)
            status = 2
        finally:
            executor.shutdown()
            node.destroy_node()
            try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())

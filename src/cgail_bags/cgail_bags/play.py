"""``cgail bag play``: play a rosbag2 MCAP bag back into live topics (rosbags + rclpy raw
publish).

    cgail bag play bags/fixtures/cgail_trial
    cgail bag play RUN --rate 2 --loop --start-offset 5
    cgail bag play RUN --topics em_tracker/tip_pose planner/path
    cgail bag play RUN --clock          # /clock at 40 Hz (--clock 100)

* Publishers are recreated with the QoS recorded in the bag's ``offered_qos_profiles``
  (reliable/transient-local only when every recorded publisher was), so a latched topic such as
  ``planner/path`` stays latched for late subscribers while the player runs.
* Messages go out in log-time order with the original spacing divided by ``--rate``; serialized
  CDR bytes are published as they are (``publisher.publish(bytes)``), nothing is decoded.
* ``--clock [HZ]`` makes the player a ROS time source, as ``ros2 bag play --clock`` does: it
  publishes ``rosgraph_msgs/Clock`` on ``/clock`` (rclcpp's ``ClockQoS``: best effort, keep
  last 1) at HZ ticks per second of wall time, 40 when no HZ is given. Tick ``k`` of a pass is
  due ``k / HZ`` s after the pass started and carries the bag time ``start + k * rate / HZ``
  (``start``: the bag's first timestamp, or ``--start-offset`` later), and it goes out before
  every message logged at or after that bag time. Nodes with ``use_sim_time`` then run on the
  bag's clock, sped up with ``--rate``; each ``--loop`` pass starts the clock again from
  ``start``. The ticks stop with the last message (ros2 bag play keeps its clock running).
  Write the bag before ``--clock`` (``cgail bag play RUN --clock``): in ``--clock RUN`` the bag
  would be read as HZ. A bag that records ``/clock`` itself is refused with ``--clock``.
* A missing, truncated or corrupt bag ends with ``cgail bag play: error: <path>: ...`` and exit
  status 2, not a traceback (:class:`~cgail_bags.errors.BagError`).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
import math
from pathlib import Path
import sys
import threading
import time
from typing import Any

from rosbags.interfaces import ConnectionExtRosbag2, Qos

from cgail_bags.bagio import iter_raw, open_bag
from cgail_bags.errors import BagError
from cgail_bags.qos import to_rclpy
from cgail_bags.rosutil import get_message_class
from cgail_sim.cli_help import tool_parser

#: ``/clock`` rate of ``--clock`` without a value (ros2 bag play's default).
DEFAULT_CLOCK_HZ = 40.0
#: The time source's topic.
CLOCK_TOPIC = '/clock'


@dataclass(frozen=True)
class PlayerConfig:
    """What and how to play."""

    bag: Path
    """Bag directory or .mcap file."""
    rate: float = 1.0
    """Playback speed factor, > 0 (2: twice as fast)."""
    loop: bool = False
    """Start again at the end until stopped."""
    start_offset: float = 0.0
    """Seconds into the bag to start from, >= 0."""
    topics: tuple[str, ...] = ()
    """Only these topics (relative names resolve to the root namespace); empty: all."""
    wait_for_subscribers: float = 0.0
    """Before publishing, wait up to this many seconds until every publisher has a matched
    subscription (0: do not wait). The ``/clock`` publisher is not waited for."""
    clock_hz: float = 0.0
    """Publish the bag time on ``/clock`` at this many ticks per second of wall time, >= 0
    (0: no clock; ``--clock`` alone: :data:`DEFAULT_CLOCK_HZ`)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate) and self.rate > 0.0):
            raise ValueError(f'rate must be a positive factor, found {self.rate}')
        if not (math.isfinite(self.start_offset) and self.start_offset >= 0.0):
            raise ValueError(f'start_offset must be >= 0 s, found {self.start_offset}')
        if not self.wait_for_subscribers >= 0.0:
            raise ValueError(f'wait_for_subscribers must be >= 0 s, '
                             f'found {self.wait_for_subscribers}')
        if not (math.isfinite(self.clock_hz) and self.clock_hz >= 0.0):
            raise ValueError(f'clock_hz must be >= 0 Hz (0: no /clock), found {self.clock_hz}')


class BagPlayer:
    """Publishes a bag's messages through publishers of an existing node.

    Args:
        node: The rclpy node that owns the publishers.
        config: What and how to play.

    Raises:
        BagError: Missing/truncated/corrupt bag, no topic to play, or an unknown message type.
    """

    def __init__(self, node: Any, config: PlayerConfig) -> None:
        self._node = node
        self.config = config
        wanted = {'/' + t.lstrip('/') for t in config.topics}
        types: dict[str, str] = {}
        offered: dict[str, list[Qos]] = {}
        with open_bag(config.bag) as reader:
            self.start_ns = reader.start_time
            self.end_ns = reader.end_time
            for conn in reader.connections:
                if wanted and conn.topic not in wanted:
                    continue
                if types.setdefault(conn.topic, conn.msgtype) != conn.msgtype:
                    raise BagError(f'{config.bag}: topic {conn.topic} recorded with two types '
                                   f'({types[conn.topic]} and {conn.msgtype})')
                if isinstance(conn.ext, ConnectionExtRosbag2):
                    offered.setdefault(conn.topic, []).extend(conn.ext.offered_qos_profiles)
        if not types:
            what = f'topics {sorted(wanted)}' if wanted else 'any topic'
            raise BagError(f'{config.bag}: expected {what} to play, found none')
        if config.clock_hz > 0.0 and CLOCK_TOPIC in types:
            raise BagError(f'{config.bag}: the bag records {CLOCK_TOPIC} itself; play it '
                           f'without --clock (or leave {CLOCK_TOPIC} out with --topics)')
        self.publishers = {
            topic: node.create_publisher(get_message_class(msgtype), topic,
                                         to_rclpy(offered.get(topic, [])))
            for topic, msgtype in sorted(types.items())
        }
        self.clock_publisher: Any = None
        """The ``/clock`` publisher (``clock_hz > 0``), else None."""
        self.clock_ticks = 0
        """``/clock`` messages published so far."""
        if config.clock_hz > 0.0:
            from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
            from rosgraph_msgs.msg import Clock

            self._clock_msg = Clock
            # rclcpp::ClockQoS, what ros2 bag play offers and rclpy's time source reads
            self.clock_publisher = node.create_publisher(Clock, CLOCK_TOPIC, QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=1,
                reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE))

    def wait_for_subscribers(self, timeout: float, stop: threading.Event) -> bool:
        """Wait until every publisher has a matched subscription; False on timeout/stop."""
        deadline = time.monotonic() + timeout
        while not stop.is_set():
            if all(p.get_subscription_count() > 0 for p in self.publishers.values()):
                return True
            if time.monotonic() >= deadline:
                return False
            stop.wait(0.05)
        return False

    def play(self, stop: threading.Event | None = None) -> int:
        """Publish the bag (again and again with ``loop``) until the end or ``stop`` is set.

        Returns:
            Number of messages published.

        Raises:
            BagError: The bag turns out to be corrupt while reading it.
        """
        halt = stop or threading.Event()
        cfg = self.config
        if cfg.wait_for_subscribers > 0.0 and not self.wait_for_subscribers(
                cfg.wait_for_subscribers, halt):
            lonely = [t for t, p in self.publishers.items() if p.get_subscription_count() == 0]
            self._node.get_logger().warning(
                f'no subscriber on {lonely} after {cfg.wait_for_subscribers:g} s; playing anyway')
        first_ns = self.start_ns + round(cfg.start_offset * 1e9)
        published = 0
        while not halt.is_set():
            wall0 = time.monotonic()
            tick = 0
            with open_bag(cfg.bag) as reader:
                start = first_ns if cfg.start_offset > 0.0 else None
                for conn, log_ns, raw in iter_raw(reader, list(self.publishers), start):
                    if self.clock_publisher is not None:
                        tick = self._clock_until(log_ns - first_ns, first_ns, wall0, tick, halt)
                    due = wall0 + (log_ns - first_ns) * 1e-9 / cfg.rate
                    if not _wait_until(due, halt):
                        break
                    self.publishers[conn.topic].publish(bytes(raw))
                    published += 1
            if not cfg.loop:
                break
        return published

    def _clock_until(self, elapsed_ns: int, first_ns: int, wall0: float, tick: int,
                     halt: threading.Event) -> int:
        """Publish the clock ticks from ``tick`` on up to bag time ``first_ns + elapsed_ns``,
        each at its wall time; returns the next tick (stops early when ``halt`` is set)."""
        hz, rate = self.config.clock_hz, self.config.rate
        while (bag_ns := round(tick * rate * 1e9 / hz)) <= elapsed_ns:
            if not _wait_until(wall0 + tick / hz, halt):
                break
            stamp = first_ns + bag_ns
            msg = self._clock_msg()
            msg.clock.sec, msg.clock.nanosec = divmod(stamp, 10**9)
            self.clock_publisher.publish(msg)
            self.clock_ticks += 1
            tick += 1
        return tick


def _wait_until(due: float, halt: threading.Event) -> bool:
    """Sleep until ``time.monotonic()`` reaches ``due``; False when ``halt`` was set first."""
    delay = due - time.monotonic()
    return not (delay > 0.0 and halt.wait(delay)) and not halt.is_set()


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail bag play``."""
    parser = tool_parser('bag play', __doc__, details=True)
    parser.add_argument('bag', type=Path, help='bag directory or .mcap file')
    parser.add_argument('-r', '--rate', type=float, default=1.0, help='speed factor (default 1)')
    parser.add_argument('-l', '--loop', action='store_true', help='play again and again')
    parser.add_argument('--start-offset', type=float, default=0.0,
                        help='seconds into the bag to start from')
    parser.add_argument('--topics', nargs='+', default=[], help='only these topics')
    parser.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='TIMEOUT',
                        help='wait up to TIMEOUT s for a subscriber on every topic first')
    parser.add_argument('--clock', type=float, nargs='?', const=DEFAULT_CLOCK_HZ, default=0.0,
                        metavar='HZ',
                        help='publish the bag time on /clock at HZ ticks per second of wall '
                             f'time (default {DEFAULT_CLOCK_HZ:g} Hz), as a ROS time source')
    parser.add_argument('--linger', type=float, default=1.0,
                        help='seconds to keep publishers alive after the last message so '
                             'reliable/latched samples are delivered (default 1)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail bag play``; returns the exit status (2 on a bad bag)."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from cgail_bags.rosutil import stop_on_signals
    from cgail_node_utils.entry_point import try_shutdown

    parser = build_parser()
    args, ros_args = parser.parse_known_args(argv)
    try:
        config = PlayerConfig(bag=args.bag, rate=args.rate, loop=args.loop,
                              start_offset=args.start_offset, topics=tuple(args.topics),
                              wait_for_subscribers=args.wait_for_subscribers,
                              clock_hz=args.clock)
    except ValueError as exc:
        parser.error(str(exc))
    rclpy.init(args=ros_args, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bag_player')
    status = 0
    with stop_on_signals() as stop:
        try:
            player = BagPlayer(node, config)
            clock = f', {CLOCK_TOPIC} at {config.clock_hz:g} Hz' if config.clock_hz else ''
            print(f'cgail bag play: playing {config.bag} ({", ".join(player.publishers)}) at '
                  f'rate {config.rate:g}{clock}', flush=True)
            count = player.play(stop)
            print(f'cgail bag play: published {count} messages', flush=True)
            stop.wait(max(0.0, args.linger))
        except BagError as exc:
            print(f'cgail bag play: error: {exc}', file=sys.stderr)
            status = 2
        finally:
            node.destroy_node()
            try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())

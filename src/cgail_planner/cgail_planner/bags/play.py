"""``bag_play``: play a rosbag2 MCAP bag back into live topics (rosbags + rclpy raw publish).

    scripts/ros2run cgail_planner bag_play bags/fixtures/cgail_trial
    scripts/ros2run cgail_planner bag_play RUN --rate 2 --loop --start-offset 5
    scripts/ros2run cgail_planner bag_play RUN --topics em_tracker/tip_pose planner/path

* Publishers are recreated with the QoS recorded in the bag's ``offered_qos_profiles``
  (reliable/transient-local only when every recorded publisher was), so a latched topic such as
  ``planner/path`` stays latched for late subscribers while the player runs.
* Messages go out in log-time order with the original spacing divided by ``--rate``; serialized
  CDR bytes are published as they are (``publisher.publish(bytes)``), nothing is decoded.
* A missing, truncated or corrupt bag ends with ``bag_play: error: <path>: ...`` and exit
  status 2, not a traceback (:class:`~cgail_planner.bags.errors.BagError`).
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

from cgail_planner.bags.bagio import iter_raw, open_bag
from cgail_planner.bags.errors import BagError
from cgail_planner.bags.qos import to_rclpy
from cgail_planner.bags.rosutil import get_message_class


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
    subscription (0: do not wait)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate) and self.rate > 0.0):
            raise ValueError(f'rate must be a positive factor, found {self.rate}')
        if not (math.isfinite(self.start_offset) and self.start_offset >= 0.0):
            raise ValueError(f'start_offset must be >= 0 s, found {self.start_offset}')
        if not self.wait_for_subscribers >= 0.0:
            raise ValueError(f'wait_for_subscribers must be >= 0 s, '
                             f'found {self.wait_for_subscribers}')


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
        self.publishers = {
            topic: node.create_publisher(get_message_class(msgtype), topic,
                                         to_rclpy(offered.get(topic, [])))
            for topic, msgtype in sorted(types.items())
        }

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
            with open_bag(cfg.bag) as reader:
                start = first_ns if cfg.start_offset > 0.0 else None
                for conn, log_ns, raw in iter_raw(reader, list(self.publishers), start):
                    due = wall0 + (log_ns - first_ns) * 1e-9 / cfg.rate
                    delay = due - time.monotonic()
                    if delay > 0.0 and halt.wait(delay):
                        break
                    self.publishers[conn.topic].publish(bytes(raw))
                    published += 1
            if not cfg.loop:
                break
        return published


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``bag_play``."""
    parser = argparse.ArgumentParser(prog='bag_play', description=__doc__.splitlines()[0])
    parser.add_argument('bag', type=Path, help='bag directory or .mcap file')
    parser.add_argument('-r', '--rate', type=float, default=1.0, help='speed factor (default 1)')
    parser.add_argument('-l', '--loop', action='store_true', help='play again and again')
    parser.add_argument('--start-offset', type=float, default=0.0,
                        help='seconds into the bag to start from')
    parser.add_argument('--topics', nargs='+', default=[], help='only these topics')
    parser.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='TIMEOUT',
                        help='wait up to TIMEOUT s for a subscriber on every topic first')
    parser.add_argument('--linger', type=float, default=1.0,
                        help='seconds to keep publishers alive after the last message so '
                             'reliable/latched samples are delivered (default 1)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``bag_play``; returns the exit status (2 on a bad bag)."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from cgail_planner.bags.rosutil import stop_on_signals
    from cgail_planner.nodes import try_shutdown

    parser = build_parser()
    args, ros_args = parser.parse_known_args(argv)
    try:
        config = PlayerConfig(bag=args.bag, rate=args.rate, loop=args.loop,
                              start_offset=args.start_offset, topics=tuple(args.topics),
                              wait_for_subscribers=args.wait_for_subscribers)
    except ValueError as exc:
        parser.error(str(exc))
    rclpy.init(args=ros_args, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bag_player')
    status = 0
    with stop_on_signals() as stop:
        try:
            player = BagPlayer(node, config)
            print(f'bag_play: playing {config.bag} ({", ".join(player.publishers)}) at '
                  f'rate {config.rate:g}', flush=True)
            count = player.play(stop)
            print(f'bag_play: published {count} messages', flush=True)
            stop.wait(max(0.0, args.linger))
        except BagError as exc:
            print(f'bag_play: error: {exc}', file=sys.stderr)
            status = 2
        finally:
            node.destroy_node()
            try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())

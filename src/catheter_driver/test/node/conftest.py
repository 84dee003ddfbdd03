"""In-process node test helpers: one rclpy context per test (the ``ros`` fixture of
:mod:`cgail_node_utils.testing`), an executor and a spin-until.

Rules that keep these tests true on an idle machine as well as a loaded one:

* nothing is sent from a busy loop: inputs come from timers of the probe node at a realistic
  rate (:meth:`Harness.repeat`), so the executor sleeps in ``rcl_wait`` between callbacks and a
  device thread of the node under test is never starved of the GIL;
* waits for something to happen spin with a real timeout and a generous deadline (15 s);
  only checks that something does *not* happen use short windows (:meth:`Harness.spin_for`);
* rclpy installs no signal handlers (``SignalHandlerOptions.NO``), so SIGTERM ends the test
  process (``timeout`` works) and SIGINT raises ``KeyboardInterrupt`` as usual.
"""

from collections.abc import Callable, Iterator
import time

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.timer import Timer

from cgail_node_utils.testing import ros  # noqa: F401

WAIT_S = 15.0
"""Default deadline of a wait for something that must happen, s."""


class Harness:
    """Owns the executor and a probe node for publishers/subscribers under test."""

    def __init__(self) -> None:
        self.executor = SingleThreadedExecutor()
        self.probe = Node('probe')
        self.executor.add_node(self.probe)
        self.nodes: list[Node] = [self.probe]
        self.closers: list[Callable[[], None]] = []

    def add(self, node: Node) -> Node:
        self.executor.add_node(node)
        self.nodes.append(node)
        return node

    def spin_until(self, predicate: Callable[[], bool], timeout: float = WAIT_S) -> bool:
        """Spin until ``predicate()`` holds (True) or ``timeout`` s passed (False)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def spin_for(self, seconds: float) -> None:
        """Spin for ``seconds`` (a window in which something must *not* happen)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)

    def repeat(self, period_s: float, callback: Callable[[], object]) -> Timer:
        """Call ``callback`` every ``period_s`` from a timer of the probe node (stop it with
        :meth:`stop`)."""
        return self.probe.create_timer(period_s, callback)

    def stop(self, timer: Timer) -> None:
        """Stop a timer made by :meth:`repeat`."""
        self.probe.destroy_timer(timer)

    def collect(self, msg_type, topic: str, qos) -> list:
        received: list = []
        self.probe.create_subscription(msg_type, topic, received.append, qos)
        return received

    def call(self, client, request, timeout: float = WAIT_S):
        assert client.wait_for_service(timeout_sec=timeout)
        future = client.call_async(request)
        assert self.spin_until(future.done, timeout)
        return future.result()


@pytest.fixture
def harness(ros: None) -> Iterator[Harness]:  # noqa: F811  (the imported fixture)
    h = Harness()
    try:
        yield h
    finally:
        for node in reversed(h.nodes):
            h.executor.remove_node(node)
            node.destroy_node()
        h.executor.shutdown()
        for close in reversed(h.closers):
            close()

"""In-process node test helpers: one rclpy context per test, an executor and a spin-until."""

from collections.abc import Callable
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node


class Harness:
    """Owns the executor and a probe node for publishers/subscribers under test."""

    def __init__(self) -> None:
        self.executor = SingleThreadedExecutor()
        self.probe = Node('probe')
        self.executor.add_node(self.probe)
        self.nodes: list[Node] = [self.probe]

    def add(self, node: Node) -> Node:
        self.executor.add_node(node)
        self.nodes.append(node)
        return node

    def spin_until(self, predicate: Callable[[], bool], timeout: float = 15.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)

    def collect(self, msg_type, topic: str, qos) -> list:
        received: list = []
        self.probe.create_subscription(msg_type, topic, received.append, qos)
        return received

    def call(self, client, request, timeout: float = 5.0):
        assert client.wait_for_service(timeout_sec=timeout)
        future = client.call_async(request)
        assert self.spin_until(future.done, timeout)
        return future.result()


@pytest.fixture
def harness():
    rclpy.init()
    h = Harness()
    try:
        yield h
    finally:
        for node in reversed(h.nodes):
            h.executor.remove_node(node)
            node.destroy_node()
        h.executor.shutdown()
        rclpy.try_shutdown()

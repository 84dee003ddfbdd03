"""lifecycle_state in-process: it follows every transition, agrees with ``~/get_state`` over
DDS, and refuses nodes that cannot tell their state."""

from __future__ import annotations

import time

from lifecycle_msgs.srv import GetState
import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn
from rclpy.node import Node

from cgail_node_utils.lifecycle import lifecycle_state, PRIMARY_STATES


class Device(LifecycleNode):
    """A lifecycle node whose configure succeeds, fails or raises, as told, and that records
    the state it reads from inside its own transition callbacks."""

    def __init__(self, name: str = 'device', *, configure: str = 'success', **kwargs) -> None:
        super().__init__(name, **kwargs)
        self.configure = configure
        self.seen: list[str] = []

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        self.seen.append(lifecycle_state(self))
        if self.configure == 'raise':
            raise RuntimeError('device absent')
        if self.configure == 'failure':
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        self.seen.append(lifecycle_state(self))
        return super().on_activate(state)

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self.seen.append(lifecycle_state(self))
        return TransitionCallbackReturn.SUCCESS


def test_the_state_follows_every_transition(ros: None) -> None:
    node = Device()
    try:
        assert lifecycle_state(node) == 'unconfigured'
        steps = [(node.trigger_configure, 'inactive'), (node.trigger_activate, 'active'),
                 (node.trigger_deactivate, 'inactive'), (node.trigger_cleanup, 'unconfigured'),
                 (node.trigger_configure, 'inactive'), (node.trigger_shutdown, 'finalized')]
        for trigger, expected in steps:
            assert trigger() == TransitionCallbackReturn.SUCCESS
            assert lifecycle_state(node) == expected, trigger.__name__
        # read from inside the callbacks: the transition states
        assert node.seen == ['configuring', 'activating', 'configuring']
        assert {'unconfigured', 'inactive', 'active', 'finalized'} == set(PRIMARY_STATES)
    finally:
        node.destroy_node()


def test_a_failed_configure_stays_unconfigured_and_an_error_is_processed(ros: None) -> None:
    failing = Device('failing', configure='failure')
    raising = Device('raising', configure='raise')
    try:
        assert failing.trigger_configure() == TransitionCallbackReturn.FAILURE
        assert lifecycle_state(failing) == 'unconfigured'
        assert raising.trigger_configure() == TransitionCallbackReturn.ERROR
        assert raising.seen == ['configuring', 'errorprocessing']
        assert lifecycle_state(raising) == 'unconfigured'  # on_error succeeded
    finally:
        failing.destroy_node()
        raising.destroy_node()


def test_it_agrees_with_the_get_state_service_over_dds(ros: None) -> None:
    node = Device('served', namespace='/rig')
    manager = Node('manager')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(manager)
    client = manager.create_client(GetState, '/rig/served/get_state')
    try:
        assert client.wait_for_service(timeout_sec=10.0)
        for trigger in (None, node.trigger_configure, node.trigger_activate):
            if trigger is not None:
                trigger()
            future = client.call_async(GetState.Request())
            deadline = time.monotonic() + 15.0
            while not future.done() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.1)
            assert future.done(), 'no get_state reply in 15 s'
            assert future.result().current_state.label == lifecycle_state(node)
        assert lifecycle_state(node) == 'active'
    finally:
        executor.shutdown()
        manager.destroy_node()
        node.destroy_node()


def test_a_renamed_node_is_read_too(ros: None) -> None:
    node = Device(cli_args=['--ros-args', '-r', '__node:=sleeve', '-r', '__ns:=/rig'])
    try:
        assert node.get_fully_qualified_name() == '/rig/sleeve'
        node.trigger_configure()
        assert lifecycle_state(node) == 'inactive'
    finally:
        node.destroy_node()


def test_a_plain_node_is_refused(ros: None) -> None:
    node = Node('plain')
    try:
        with pytest.raises(ValueError, match=r"^lifecycle_state: expected a lifecycle node, "
                                             r"found Node '/plain'$"):
            lifecycle_state(node)
    finally:
        node.destroy_node()


def test_a_node_without_lifecycle_services_is_refused(ros: None) -> None:
    node = Device('lean', enable_communication_interface=False)
    try:
        node.trigger_configure()  # the state machine works; only nothing public reports it
        with pytest.raises(ValueError, match=r"^lifecycle_state: expected the get_state service "
                                             r"of lifecycle node '/lean', found 0 GetState "
                                             r'services \(a node built with '
                                             r'enable_communication_interface=False has none\)$'):
            lifecycle_state(node)
    finally:
        node.destroy_node()

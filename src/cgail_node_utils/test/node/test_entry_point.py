"""spin and try_shutdown: a console entry point stops cleanly whenever the Ctrl-C comes."""

from __future__ import annotations

import threading
import time

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from cgail_node_utils import entry_point
from cgail_node_utils.entry_point import RCLError, spin, try_shutdown


def test_spin_returns_at_once_when_ctrl_c_came_before_it() -> None:
    """The race of the console entry point: rclpy's SIGINT handler shut the context down after
    the node had started but before the spin; ``spin`` returns instead of failing on rclpy's
    cleared global executor."""
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    node = Node('spin_after_shutdown', context=ctx)
    ctx.shutdown()
    t0 = time.monotonic()
    spin(node)
    assert time.monotonic() - t0 < 5.0
    node.destroy_node()


def test_spin_runs_callbacks_until_the_context_is_shut_down() -> None:
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    node = Node('spinning', context=ctx)
    ticks: list[float] = []

    def tick() -> None:
        ticks.append(time.monotonic())
        if len(ticks) == 3:  # as Ctrl-C would, from another thread
            threading.Thread(target=ctx.shutdown).start()

    node.create_timer(0.05, tick)
    done = threading.Event()
    thread = threading.Thread(target=lambda: (spin(node), done.set()), daemon=True)
    thread.start()
    assert done.wait(timeout=30.0), 'spin did not return after the context was shut down'
    assert len(ticks) >= 3
    node.destroy_node()


def test_try_shutdown_shuts_down_and_tolerates_a_context_already_down(
        monkeypatch: pytest.MonkeyPatch) -> None:
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try_shutdown()
    assert not rclpy.ok()
    try_shutdown()  # nothing to do

    # the race with rclpy's SIGINT handler: down between try_shutdown's check and its call
    def already_down() -> None:
        raise RCLError('rcl_shutdown already called on the given context')

    monkeypatch.setattr(entry_point.rclpy, 'try_shutdown', already_down)
    try_shutdown()  # no error


def test_other_errors_of_try_shutdown_are_not_swallowed(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken() -> None:
        raise RuntimeError('not an rcl error')

    monkeypatch.setattr(entry_point.rclpy, 'try_shutdown', broken)
    with pytest.raises(RuntimeError, match=r'^not an rcl error$'):
        try_shutdown()

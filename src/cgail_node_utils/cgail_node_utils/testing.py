"""Test helpers every package's tests share (like ``numpy.testing``): imported by tests only.

* :func:`require_localhost_discovery`: each package's ``test/conftest.py`` calls it from its
  ``pytest_configure``, so no test runs unless DDS discovery is confined to this machine;
* :func:`ros`: the fixture of the in-process node tests (``test/node/conftest.py`` imports it:
  ``from cgail_node_utils.testing import ros  # noqa: F401``);
* :func:`spin_until`: spin an executor until something happens, with a real deadline.

Rules that keep node tests true on an idle machine as well as a loaded one: inputs come from
timers at realistic rates (never published on every spin pass), waits for something to happen
spin with a real timeout and a generous deadline, and only checks that something does *not*
happen use short windows.

Test code (test/test_package_deps.py): its imports may be ``<test_depend>`` s of this package,
and no product module imports it (test/test_import_layers.py). rclpy is imported inside
:func:`ros`, so the packages without ROS (``cgail_sim``) call the guard without it.
"""

from collections.abc import Callable, Iterator
import gc
import os
import time
from typing import Any

import pytest


def require_localhost_discovery() -> None:
    """Refuse to run the tests unless ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is ``LOCALHOST``.

    Raises:
        pytest.UsageError: another discovery range (or none): the tests were not started
            through ``scripts/ws`` or ``scripts/test.sh``.
    """
    if os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'LOCALHOST':
        raise pytest.UsageError(
            'expected ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, found '
            f'{os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")!r}: run the tests through '
            'scripts/ws or scripts/test.sh (they source scripts/env.sh)')


@pytest.fixture
def ros() -> Iterator[None]:
    """rclpy initialised for one test, shut down afterwards.

    No rclpy signal handlers (``SignalHandlerOptions.NO``): SIGTERM ends the test process, so
    ``timeout`` works, and SIGINT raises ``KeyboardInterrupt`` as usual. A node whose
    constructor raised is only reachable from the exception's traceback cycle; the collection
    before shutdown destroys it, so its DDS participant (and that participant's threads) does
    not outlive the test.
    """
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield
    finally:
        gc.collect()
        rclpy.try_shutdown()


def spin_until(executor: Any, predicate: Callable[[], bool], timeout: float = 30.0) -> bool:
    """Spin ``executor`` (20 ms waits) until ``predicate()`` holds or ``timeout`` wall seconds
    have passed (a generous deadline: a loaded machine is slow); returns whether it holds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=0.02)
    return predicate()

"""In-process node tests: one rclpy context per test, without rclpy's signal handlers.

Rules that keep these tests true on an idle machine as well as a loaded one: inputs come from
timers at realistic rates (never published on every spin pass), waits for something to happen
spin with a real timeout and a generous deadline, and only checks that something does *not*
happen use short windows.
"""

from collections.abc import Iterator
import gc

import pytest
import rclpy
from rclpy.signals import SignalHandlerOptions


@pytest.fixture
def ros() -> Iterator[None]:
    """rclpy initialised for one test, shut down afterwards.

    No rclpy signal handlers (``SignalHandlerOptions.NO``): SIGTERM ends the test process, so
    ``timeout`` works, and SIGINT raises ``KeyboardInterrupt`` as usual. A node whose
    constructor raised is only reachable from the exception's traceback cycle; the collection
    before shutdown destroys it, so its DDS participant (and that participant's threads) does
    not outlive the test.
    """
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield
    finally:
        gc.collect()
        rclpy.try_shutdown()

"""Cross-package tests: refuse to run unless DDS discovery is confined to this machine."""

import os

import pytest


def pytest_configure(config: pytest.Config) -> None:
    if os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'LOCALHOST':
        raise pytest.UsageError(
            'expected ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, found '
            f'{os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")!r}: run the tests through '
            'scripts/ws or scripts/test.sh (they source scripts/env.sh)')


@pytest.fixture
def rclpy_context():
    """rclpy initialised for one test, shut down afterwards (yields the rclpy module).

    No rclpy signal handlers (``SignalHandlerOptions.NO``): SIGTERM ends the test process, so
    ``timeout`` works, and SIGINT raises ``KeyboardInterrupt`` as usual. A node whose
    constructor raised is only reachable from the exception's traceback cycle; the collection
    before shutdown destroys it, so its DDS participant does not outlive the test.
    """
    import gc

    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield rclpy
    finally:
        gc.collect()
        rclpy.try_shutdown()


@pytest.fixture(scope='session')
def prepared_anatomy(tmp_path_factory: pytest.TempPathFactory):
    """A prepared anatomy directory ``p07`` holding the default aorta (``lumen.stl`` and
    ``lumen.yaml``, as ``prepare_anatomy`` writes them)."""
    from cgail_sim.anatomy import build_anatomy, save_anatomy_mesh

    d = tmp_path_factory.mktemp('patients') / 'p07'
    d.mkdir()
    save_anatomy_mesh(build_anatomy('default'), d / 'lumen.stl')
    return d

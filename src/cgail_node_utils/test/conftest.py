"""cgail_node_utils tests: refuse to run unless DDS discovery is confined to this machine."""

import os

import pytest


def pytest_configure(config: pytest.Config) -> None:
    if os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'LOCALHOST':
        raise pytest.UsageError(
            'expected ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, found '
            f'{os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")!r}: run the tests through '
            'scripts/ws or scripts/test.sh (they source scripts/env.sh)')

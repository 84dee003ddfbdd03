"""pam_controller tests: refuse to run unless DDS discovery is confined to this machine."""

import pytest

from cgail_node_utils.testing import require_localhost_discovery


def pytest_configure(config: pytest.Config) -> None:
    require_localhost_discovery()

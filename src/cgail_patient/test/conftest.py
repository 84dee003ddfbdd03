"""cgail_patient tests: refuse to run unless DDS discovery is confined to this machine; the
fixtures ``bad_anatomy`` and ``prepared`` (:mod:`cgail_sim.testing`)."""

import pytest

from cgail_node_utils.testing import require_localhost_discovery
from cgail_sim.testing import bad_anatomy, prepared  # noqa: F401


def pytest_configure(config: pytest.Config) -> None:
    require_localhost_discovery()

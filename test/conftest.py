"""Cross-package tests: refuse to run unless DDS discovery is confined to this machine."""

from types import ModuleType

import pytest

from cgail_node_utils.testing import require_localhost_discovery, ros  # noqa: F401


def pytest_configure(config: pytest.Config) -> None:
    require_localhost_discovery()


@pytest.fixture
def rclpy_context(ros: None) -> ModuleType:  # noqa: F811  (the imported fixture)
    """rclpy initialised for one test, shut down afterwards (yields the rclpy module): the
    ``ros`` fixture of :mod:`cgail_node_utils.testing`."""
    import rclpy

    return rclpy


@pytest.fixture(scope='session')
def prepared_anatomy(tmp_path_factory: pytest.TempPathFactory):
    """A prepared anatomy directory ``p07`` holding the default aorta (``lumen.stl`` and
    ``lumen.yaml``, as ``prepare_anatomy`` writes them)."""
    from cgail_sim.anatomy import build_anatomy, save_anatomy_mesh

    d = tmp_path_factory.mktemp('patients') / 'p07'
    d.mkdir()
    save_anatomy_mesh(build_anatomy('default'), d / 'lumen.stl')
    return d

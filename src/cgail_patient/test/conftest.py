"""cgail_planner tests: refuse to run unless DDS discovery is confined to this machine."""

import os
from pathlib import Path

import pytest


def pytest_configure(config: pytest.Config) -> None:
    if os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'LOCALHOST':
        raise pytest.UsageError(
            'expected ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, found '
            f'{os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")!r}: run the tests through '
            'scripts/ws or scripts/test.sh (they source scripts/env.sh)')


@pytest.fixture(params=['missing', 'not prepared', 'mesh fails to load'])
def bad_anatomy(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, str]:
    """A bad ``--anatomy``/``anatomy`` argument, one of each kind, and the text its one-line
    error must hold: no such path, a directory that is not a prepared anatomy, a prepared
    directory whose mesh fails to load."""
    if request.param == 'missing':
        return tmp_path / 'nowhere', f"found '{tmp_path / 'nowhere'}': no such file or directory"
    if request.param == 'not prepared':
        d = tmp_path / 'empty'
        d.mkdir()
        return d, (f'anatomy {d}: expected a prepared anatomy directory holding lumen.stl and '
                   'lumen.yaml (cgail prepare-anatomy makes one), found no lumen.stl and no '
                   'lumen.yaml')
    d = tmp_path / 'junk'
    d.mkdir()
    (d / 'lumen.stl').write_text('solid junk\nendsolid junk\n')
    (d / 'lumen.yaml').write_text('units: mm\n')
    return d, f'expected a triangle mesh in {d / "lumen.stl"}, found a Trimesh with 0 faces'


@pytest.fixture(scope='module')
def prepared(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A prepared anatomy directory ``p07`` (``lumen.stl`` + ``lumen.yaml``, as
    ``prepare_anatomy`` writes them) holding a built-in aorta: the test module's
    ``PREPARED_FROM`` (default ``'default'``)."""
    from cgail_sim.anatomy import build_anatomy, save_anatomy_mesh

    d = tmp_path_factory.mktemp('patients') / 'p07'
    d.mkdir()
    save_anatomy_mesh(build_anatomy(getattr(request.module, 'PREPARED_FROM', 'default')),
                      d / 'lumen.stl')
    return d

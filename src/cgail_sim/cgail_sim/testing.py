"""Test helpers of the packages that use the simulator (like ``numpy.testing``): tests only.

Fixtures, imported into a package's ``test/conftest.py``
(``from cgail_sim.testing import bad_anatomy, prepared  # noqa: F401``):

* :func:`bad_anatomy`: a bad ``--anatomy``/``anatomy`` argument of each kind and its error;
* :func:`prepared`: a prepared anatomy directory holding a built-in aorta.

Test code (test/test_package_deps.py): its imports may be ``<test_depend>`` s of this package,
and no product module imports it (test/test_import_layers.py).
"""

from pathlib import Path

import pytest

from cgail_sim.anatomy import build_anatomy, save_anatomy_mesh


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
    d = tmp_path_factory.mktemp('patients') / 'p07'
    d.mkdir()
    save_anatomy_mesh(build_anatomy(getattr(request.module, 'PREPARED_FROM', 'default')),
                      d / 'lumen.stl')
    return d


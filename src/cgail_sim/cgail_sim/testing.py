"""Test helpers of the packages that use the simulator (like ``numpy.testing``): tests only.

Fixtures, imported into a package's ``test/conftest.py``
(``from cgail_sim.testing import bad_anatomy, prepared  # noqa: F401``):

* :func:`bad_anatomy`: a bad ``--anatomy``/``anatomy`` argument of each kind and its error;
* :func:`prepared`: a prepared anatomy directory holding a built-in aorta.

And the curved-descending-aorta case of issue 12 (:data:`CURVED_PARAMS`,
:func:`curved_anatomy`, :func:`curved_world`), imported by the tests that use it.

Test code (test/test_package_deps.py): its imports may be ``<test_depend>`` s of this package,
and no product module imports it (test/test_import_layers.py).
"""

import functools
import math
from pathlib import Path

import pytest

from cgail_sim.anatomy import (
    Anatomy,
    AnatomyParams,
    build_anatomy,
    build_anatomy_from_params,
    save_anatomy_mesh,
)
from cgail_sim.centerline import compute_centerlines
from cgail_sim.scenarios import build_scenarios, World


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


#: A synthetic aorta whose descending part curves near its open end (issue 12's case): the
#: default aorta with its lowest 60 mm of descending aorta turning through 30 deg towards the
#: patient's right-anterior. Its start 2 (53 mm above start 0) then points straight up the
#: descending aorta while the lumen below it bends away: a straight introducer behind it would
#: run outside the wall and cross the exit plane outside the cap, as in the patient mesh of the
#: issue.
CURVED_PARAMS = AnatomyParams(descending_bend=math.radians(30.0), descending_bend_length=0.060)


@functools.cache
def curved_anatomy() -> Anatomy:
    """The curved-descending-aorta anatomy (name ``curved``), built once per process (and
    cached on disk, as every anatomy)."""
    return build_anatomy_from_params(CURVED_PARAMS, "curved")


@functools.cache
def curved_world() -> World:
    """Its world: centerlines and scenario set (as ``load_world`` builds them)."""
    anatomy = curved_anatomy()
    centerlines = compute_centerlines(anatomy)
    return World(anatomy=anatomy, centerlines=centerlines,
                 scenarios=build_scenarios(anatomy, centerlines))

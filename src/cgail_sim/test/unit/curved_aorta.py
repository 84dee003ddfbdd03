"""A synthetic aorta whose descending part curves near its open end (issue 12's case).

The default aorta with its lowest 60 mm of descending aorta turning through 30 deg towards the
patient's right-anterior. Its start 2 (53 mm above start 0) then points straight up the
descending aorta while the lumen below it bends away: a straight introducer behind it would run
outside the wall and cross the exit plane outside the cap, as in the patient mesh of the issue.
Built once per process (and cached on disk, as every anatomy).
"""

import functools
import math

from cgail_sim.anatomy import Anatomy, AnatomyParams, build_anatomy_from_params
from cgail_sim.centerline import compute_centerlines
from cgail_sim.scenarios import build_scenarios, World

#: The parameters of the curved anatomy.
CURVED_PARAMS = AnatomyParams(descending_bend=math.radians(30.0), descending_bend_length=0.060)


@functools.cache
def curved_anatomy() -> Anatomy:
    """The curved-descending-aorta anatomy (name ``curved``)."""
    return build_anatomy_from_params(CURVED_PARAMS, "curved")


@functools.cache
def curved_world() -> World:
    """Its world: centerlines and scenario set (as ``load_world`` builds them)."""
    anatomy = curved_anatomy()
    centerlines = compute_centerlines(anatomy)
    return World(anatomy=anatomy, centerlines=centerlines,
                 scenarios=build_scenarios(anatomy, centerlines))

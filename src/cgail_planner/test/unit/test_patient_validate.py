"""validate_anatomy: the checks of a prepared anatomy, each failing with one clear line."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from cgail_planner.patient.validate import bend_radii, validate_anatomy
from cgail_planner.sim.anatomy import Anatomy, build_anatomy


def _scaled(anatomy: Anatomy, factor: float) -> Anatomy:
    """The anatomy shrunk about the annulus (landmarks with it)."""
    fields = {f.name: getattr(anatomy, f.name) for f in dataclasses.fields(anatomy)
              if f.name != "_mesh"}
    for key in ("vertices", "exit_point", "annulus_center", "start_point"):
        fields[key] = np.asarray(fields[key]) * factor
    fields["ostia"] = {k: np.asarray(v) * factor for k, v in anatomy.ostia.items()}
    fields["name"] = f"{anatomy.name}_x{factor}"
    return Anatomy(**fields)


def test_bend_radius_of_a_circle() -> None:
    t = np.linspace(0.0, math.pi, 400)
    circle = 0.03 * np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    s, r = bend_radii(circle)
    assert np.allclose(r, 0.03, rtol=1e-3)
    assert 0.005 <= s[0] < 0.0055  # the first point with half an arc before it
    _, straight = bend_radii(np.outer(np.linspace(0.0, 0.1, 50), [0.0, 0.0, 1.0]))
    assert np.isinf(straight).all()


def test_builtin_anatomy_passes_every_check() -> None:
    v = validate_anatomy(build_anatomy("default"))
    assert [c.name for c in v.errors] == []
    names = [c.name for c in v.checks]
    assert names == ["mesh", "vertex count", "face quality", "landmarks", "centrelines",
                     "lumen radius", "tightest bend", "targets", "starts and introducers",
                     "deformable wall"]
    assert 10.0 < v.figures["radius_profile"]["left"]["median"] < 16.0
    assert v.figures["wall_max_displacement_mm"] < 15.0


def test_lumen_narrower_than_the_catheter_is_an_error() -> None:
    v = validate_anatomy(_scaled(build_anatomy("default"), 0.3), wall=False)
    lumen = next(c for c in v.checks if c.name == "lumen radius")
    assert lumen.status == "error"
    assert lumen.message.startswith("expected a lumen wider than the catheter (radius 3.5 mm), "
                                    "found an inscribed radius of ")


def test_absurd_ostia_are_an_error() -> None:
    a = build_anatomy("default")
    fields = {f.name: getattr(a, f.name) for f in dataclasses.fields(a) if f.name != "_mesh"}
    # The left ostium put on the descending aorta's wall.
    fields["ostia"] = {"left": np.asarray(a.vertices[np.argmin(a.vertices[:, 2])]),
                       "right": np.asarray(a.ostia["right"])}
    v = validate_anatomy(Anatomy(**fields), wall=False)
    landmarks = next(c for c in v.checks if c.name == "landmarks")
    assert landmarks.status == "error"
    assert "expected ostia 5-30 mm above the annulus, found left -" in landmarks.message

"""validate_anatomy: the checks of a prepared anatomy, each failing with one clear line."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cgail_patient.validate import bend_radii, validate_anatomy
from cgail_sim.anatomy import Anatomy, build_anatomy


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


def test_a_start_with_its_introducer_along_the_centerline_is_usable() -> None:
    """Where a straight introducer would leave the lumen (the curved descending aorta's start
    2), the simulator lays it along the centerline; the check measures that one (AVT D13 was
    refused for a straight introducer it never uses)."""
    from cgail_sim.scenarios import introducer_tail, tube_clearance
    from cgail_sim.testing import curved_anatomy, curved_world

    anatomy, starts = curved_anatomy(), curved_world().scenarios.starts
    s2 = starts[2]
    assert s2.bent
    tail = introducer_tail(anatomy, s2.position, s2.rotation)
    straight, _ = tube_clearance(anatomy, np.stack([tail, s2.position]))
    assert straight < 0.0035  # (the straight one would touch the wall)
    v = validate_anatomy(anatomy, wall=False)
    check = next(c for c in v.checks if c.name == "starts and introducers")
    assert check.status == "ok", check.message
    bent = min(tube_clearance(anatomy, np.vstack([s.introducer, s.position]))[0]
               for s in starts)
    assert v.figures["introducer_clearance_mm"] == pytest.approx(bent * 1e3, abs=1e-9)
    assert 3.5 <= v.figures["introducer_clearance_mm"] < 15.0


def test_a_collision_is_placed_on_the_centreline_and_a_tight_bend_is_diagnosed() -> None:
    """The expert check's error says where the catheter hit the wall (arc length, bend radius,
    lumen radius) and, when every miss is a collision in a bend tighter than L / theta_max,
    why the anatomy cannot be used."""
    from types import SimpleNamespace

    from cgail_patient.validate import _diagnosis, centerline_place, ExpertTrial
    from cgail_sim.config import CatheterConfig

    s = np.arange(0.0, 0.1001, 0.001)  # 100 mm: 40 straight, then a 15 mm-radius turn
    th = np.clip(s - 0.04, 0.0, None) / 0.015
    pts = np.column_stack([np.where(s < 0.04, 0.0, 0.015 * (1 - np.cos(th))),
                           np.where(s < 0.04, s, 0.04 + 0.015 * np.sin(th)), np.zeros_like(s)])
    cl = SimpleNamespace(points=pts, radii=np.full(len(s), 0.010))
    text, bend = centerline_place(cl, pts[60] + [0.0, 0.0, 0.005])
    assert text == '60 mm along the centreline, where it bends with a 15 mm radius in a lumen ' \
                   'of 10 mm radius'
    assert bend == pytest.approx(15.0, abs=0.5)
    text, bend = centerline_place(cl, pts[10])
    assert text == '10 mm along the centreline in a lumen of 10 mm radius' and math.isinf(bend)

    def trial(outcome: str, bend_mm: float) -> ExpertTrial:
        return ExpertTrial(mode='static', target=0, target_mm=(0.0, 0.0, 20.0), height_mm=20.0,
                           start=0, outcome=outcome, steps=300, final_distance_mm=120.0,
                           closest_mm=100.0, max_wall_mm=0.0, contact_steps=0, detail='',
                           collision_bend_mm=bend_mm)

    env = SimpleNamespace(unwrapped=SimpleNamespace(engine=SimpleNamespace(
        config=SimpleNamespace(catheter=CatheterConfig()))))
    tight = [(trial('collision', 11.0), [trial('collision', 11.0), trial('collision', 14.0)])]
    assert _diagnosis(tight, env).startswith(
        ': every miss is a collision where the centreline bends with a 11-14 mm radius, '
        "against the catheter's smallest bend radius of 31.8 mm")
    assert _diagnosis([(trial('collision', 10.2), [trial('collision', 9.8)])], env).startswith(
        ': every miss is a collision where the centreline bends with a 10 mm radius, ')
    assert _diagnosis([(trial('timeout', math.inf), [trial('timeout', math.inf)])], env) == ''
    assert _diagnosis([(trial('collision', 40.0), [trial('collision', 40.0)])], env) == ''

"""The anatomy population: deterministic draws within their sourced ranges, the arch-type and
root-tilt distributions, validated builds, and one-line errors."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cgail_sim.anatomy import AnatomyError, AnatomyParams
from cgail_sim.population import (
    ARCH_TYPE_FREQUENCIES,
    arch_type_ratio,
    MAX_DRAWS,
    population_draw,
    population_name,
    ROOT_TILT_RANGE_DEG,
    sample_anatomy,
    sample_anatomy_params,
    sample_population,
)

MM = 1e-3
DEG = math.pi / 180.0

#: The sampled range of every drawn field (module docstring of sim.population), m / rad.
RANGES = {
    "annulus_diameter": (17 * MM, 30 * MM),
    "sinus_diameter": (19 * MM, 45 * MM),
    "stj_diameter": (17 * MM, 33 * MM),
    "stj_height": (17 * MM, 28.5 * MM),
    "ascending_diameter": (22 * MM, 45 * MM),
    "proximal_arch_diameter": (18 * MM, 40 * MM),
    "arch_proximal_diameter": (18 * MM, 40 * MM),
    "arch_distal_diameter": (18 * MM, 40 * MM),
    "isthmus_diameter": (18 * MM, 40 * MM),
    "descending_diameter": (18 * MM, 40 * MM),
    "ascending_length": (35 * MM, 90 * MM),
    "root_tilt": (ROOT_TILT_RANGE_DEG[0] * DEG, ROOT_TILT_RANGE_DEG[1] * DEG),
    "arch_width": (55 * MM, 110 * MM),
    "arch_height": (25 * MM, 80 * MM),
    "arch_rotation": (40 * DEG, 80 * DEG),
    "descending_length": (90 * MM, 180 * MM),
    "descending_bend": (0.0, 45 * DEG),
    "descending_bend_length": (40 * MM, 80 * MM),
    "annulus_to_brachiocephalic": (60 * MM, 140 * MM),
    "brachiocephalic_to_carotid": (8 * MM, 35 * MM),
    "carotid_to_subclavian": (8 * MM, 35 * MM),
    "brachiocephalic_diameter": (7 * MM, 19 * MM),
    "carotid_diameter": (5 * MM, 13 * MM),
    "subclavian_diameter": (6 * MM, 15 * MM),
    "brachiocephalic_angle": (5 * DEG, 70 * DEG),
    "carotid_angle": (5 * DEG, 70 * DEG),
    "subclavian_angle": (5 * DEG, 70 * DEG),
    "left_ostium_height": (8 * MM, 26 * MM),
    "right_ostium_height": (8 * MM, 26 * MM),
    "ostia_angle": (95 * DEG, 155 * DEG),
    "left_ostium_diameter": (2.5 * MM, 7 * MM),
    "right_ostium_diameter": (2.5 * MM, 7 * MM),
}
#: Fields the population keeps at the built-in default (model choices).
FIXED = ("branch_stub_length", "coronary_stub_length", "edge_length")


@pytest.fixture(scope="module")
def draws() -> list:
    return [population_draw(s) for s in range(400)]


def test_same_seed_same_params_and_different_seeds_differ() -> None:
    a, b = sample_anatomy_params(7), sample_anatomy_params(7)
    assert a == b and repr(a) == repr(b)
    assert sample_anatomy_params(np.int64(7)) == a
    others = {repr(sample_anatomy_params(s)) for s in range(8)}
    assert len(others) == 8
    assert population_draw(7) == population_draw(7)


def test_params_are_rounded_so_they_do_not_depend_on_the_host() -> None:
    p = sample_anatomy_params(3)
    for f in dataclasses.fields(AnatomyParams):
        value = getattr(p, f.name)
        if f.name in RANGES and f.name not in ("root_tilt", "arch_rotation", "descending_bend",
                                                "brachiocephalic_angle", "carotid_angle",
                                                "subclavian_angle", "ostia_angle"):
            assert value == round(value, 5), f.name     # 0.01 mm
        elif f.name in RANGES:
            assert math.degrees(value) == pytest.approx(round(math.degrees(value), 2),
                                                        abs=1e-9), f.name


def test_every_drawn_parameter_is_within_its_sourced_range(draws: list) -> None:
    default = AnatomyParams()
    for d in draws:
        for name, (lo, hi) in RANGES.items():
            value = getattr(d.params, name)
            assert lo - 1e-9 <= value <= hi + 1e-9, (d.seed, name, value)
        for name in FIXED:
            assert getattr(d.params, name) == getattr(default, name)
        p = d.params
        assert p.sinus_diameter >= max(p.annulus_diameter, p.stj_diameter) + 2 * MM
        assert max(p.left_ostium_height, p.right_ostium_height) <= p.stj_height - 2 * MM
        assert 25.0 <= d.age <= 90.0 and d.sex in ("female", "male")
        assert 1 <= d.draws <= MAX_DRAWS


def test_arch_type_is_realised_by_the_brachiocephalic_position(draws: list) -> None:
    for d in draws[:60]:
        ratio = arch_type_ratio(d.params)
        lo, hi = {1: (0.2, 1.0), 2: (1.0, 2.0), 3: (2.0, 3.0)}[d.arch_type]
        assert lo - 0.05 <= ratio <= hi + 0.05, (d.seed, d.arch_type, ratio)


def test_arch_types_and_tilt_tails_roughly_as_specified(draws: list) -> None:
    types = np.bincount([d.arch_type for d in draws], minlength=4)[1:] / len(draws)
    np.testing.assert_allclose(types, ARCH_TYPE_FREQUENCIES, atol=0.07)
    tilt = np.array([d.root_tilt_deg for d in draws])
    assert 41.0 <= tilt.mean() <= 49.0
    assert np.mean(tilt > 55.0) >= 0.12 and np.mean(tilt < 30.0) >= 0.05


@pytest.mark.slow  # (2,000 parameter draws: ~8 s on an idle core, ~15 s on a busy one)
def test_arch_type_frequencies_and_root_tilt_distribution() -> None:
    n = 2000
    ds = [population_draw(s) for s in range(1000, 1000 + n)]
    types = np.bincount([d.arch_type for d in ds], minlength=4)[1:] / n
    np.testing.assert_allclose(types, ARCH_TYPE_FREQUENCIES, atol=0.04)
    tilt = np.array([d.root_tilt_deg for d in ds])
    # 65 % N(49.4, 9.4), 15 % U(18, 35), 20 % U(52, 60): mean ~45, the tails weighted.
    assert 42.0 <= tilt.mean() <= 48.0
    assert 42.0 <= float(np.median(tilt)) <= 50.0
    assert np.mean(tilt < 30.0) >= 0.07         # a N(49.4, 9.4) alone: 2 %
    assert np.mean(tilt > 55.0) >= 0.15         # steep roots (the hard cases): ~21 %
    assert tilt.min() >= 18.0 and tilt.max() <= 60.0
    age = np.array([d.age for d in ds])
    by_type = [age[np.array([d.arch_type for d in ds]) == k].mean() for k in (1, 2, 3)]
    assert by_type[0] < by_type[1] < by_type[2]         # 55 / 61 / 65 years
    draws = np.array([d.draws for d in ds])
    assert np.mean(draws == 1) >= 0.85


def test_bad_seeds_give_one_line() -> None:
    for bad in (-1, 1.5, "3", True, None):
        with pytest.raises(AnatomyError, match=r"^seed must be a non-negative int, found"):
            sample_anatomy_params(bad)  # type: ignore[arg-type]
    with pytest.raises(AnatomyError, match="seed must be a non-negative int, found -2"):
        sample_anatomy(-2)
    assert population_name(12) == "population-12"


def test_a_sample_builds_and_validates_like_a_patient_anatomy() -> None:
    smp = sample_population(0)
    assert smp.anatomy.name == "population-0"
    assert not smp.validation.errors
    assert {c.name for c in smp.validation.checks} >= {
        "mesh", "landmarks", "centrelines", "lumen radius", "starts and introducers",
        "deformable wall"}
    assert smp.draw.params == sample_anatomy_params(0) or smp.draw.draws > 1
    assert sample_anatomy(0) is smp.anatomy
    assert smp.anatomy.mesh.is_watertight


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(1, 9))
def test_more_samples_validate(seed: int) -> None:
    smp = sample_population(seed)
    assert not smp.validation.errors
    assert smp.anatomy.name == f"population-{seed}"

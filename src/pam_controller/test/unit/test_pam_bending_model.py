"""Bend <-> pressure model: round trip, hysteresis loop, limits, rejection."""

import math

import numpy as np
import pytest

from pam_controller.core.bending_model import (
    BendingModel,
    BendingModelConfig,
    CHAMBER_LABELS,
    check_bend,
)
from pam_controller.core.hysteresis import HysteresisConfig
from pam_controller.errors import CommandRejectedError


def random_bends(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    radius = math.pi / 2 * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(-math.pi, math.pi, n)
    return np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)


def test_chamber_order_is_documented_order():
    assert CHAMBER_LABELS == ('alpha_pos', 'alpha_neg', 'gamma_pos', 'gamma_neg')


def test_round_trip_bend_pressures_bend_over_random_sequence():
    """Commands -> pressures -> a separate forward model fed the pressures -> same bend."""
    command_side = BendingModel()
    plant = BendingModel()
    for bend in random_bends(500):
        p = command_side.pressures_for_bend(bend)
        assert np.all(p >= 0.0) and np.all(p <= 300e3)
        np.testing.assert_allclose(plant.bend_from_pressures(p), bend, atol=1e-9)


def test_straight_command_from_virgin_state_gives_bias_everywhere():
    p = BendingModel().pressures_for_bend([0.0, 0.0])
    np.testing.assert_array_equal(p, [150e3, 150e3, 150e3, 150e3])


def test_positive_alpha_pressurises_alpha_pos_and_relieves_alpha_neg():
    p = BendingModel().pressures_for_bend([0.5, 0.0])
    assert p[0] > 150e3 > p[1]
    assert p[2] == p[3] == 150e3
    assert p[0] - 150e3 == pytest.approx(150e3 - p[1])


def test_full_bend_reachable_from_both_sides_within_pressure_cap():
    model, plant = BendingModel(), BendingModel()
    for target in ([math.pi / 2, 0.0], [-math.pi / 2, 0.0], [math.pi / 2, 0.0]):
        p = model.pressures_for_bend(target)
        assert p.max() <= 300e3 and p.min() >= 0.0
        np.testing.assert_allclose(plant.bend_from_pressures(p), target, atol=1e-9)


def test_hysteresis_loop_branches_differ_and_loop_closes():
    model = BendingModel()
    dp = np.concatenate([np.linspace(0, 300e3, 61), np.linspace(300e3, -300e3, 121),
                         np.linspace(-300e3, 300e3, 121)])
    bias = 150e3
    alpha = np.array([model.bend_from_pressures([bias + d / 2, bias - d / 2, bias, bias])[0]
                      for d in dp])
    down = alpha[61:182]   # 300 kPa -> -300 kPa
    up = alpha[182:]       # -300 kPa -> 300 kPa
    # Same inputs (reversed order): the unloading branch lies above the loading one.
    gap = down[::-1] - up
    assert gap[60] == pytest.approx(model.config.hysteresis.major_loop_width(), rel=1e-9)
    assert np.all(gap[1:-1] > 0.0)
    # The loop closes: both ends meet (rate-independent, closed major loop).
    assert up[-1] == pytest.approx(down[0], abs=1e-12)
    assert up[0] == pytest.approx(down[-1], abs=1e-12)
    # A second cycle retraces the first exactly.
    again = np.array([model.bend_from_pressures([bias + d / 2, bias - d / 2, bias, bias])[0]
                      for d in dp[61:]])
    np.testing.assert_allclose(again, alpha[61:], atol=1e-12)


def test_loop_width_is_about_ten_percent_of_bend_range_with_defaults():
    width = BendingModelConfig().hysteresis.major_loop_width()
    assert 0.08 < width / math.pi < 0.12


def test_without_hysteresis_model_is_linear():
    cfg = BendingModelConfig(hysteresis=HysteresisConfig(hysteresis_fraction=0.0))
    model = BendingModel(cfg)
    bend = model.bend_from_pressures([200e3, 100e3, 100e3, 200e3])
    np.testing.assert_allclose(bend, [cfg.hysteresis.gain * 100e3, -cfg.hysteresis.gain * 100e3])


def test_pressure_cap_holds_with_small_range_even_when_bend_falls_short():
    cfg = BendingModelConfig(max_pressure_pa=100e3, bias_pressure_pa=50e3)
    model = BendingModel(cfg)
    p = model.pressures_for_bend([math.pi / 2, 0.0])
    np.testing.assert_array_equal(p, [100e3, 0.0, 50e3, 50e3])


@pytest.mark.parametrize('bend', [
    [float('nan'), 0.0], [0.0, float('inf')], [1.2, 1.2], [math.pi / 2 + 1e-6, 0.0],
    [0.0, -1.6], [0.1],
])
def test_bad_bends_rejected_and_state_untouched(bend):
    model = BendingModel()
    model.pressures_for_bend([0.3, -0.2])
    state = model._command.state
    with pytest.raises(CommandRejectedError, match='expected'):
        model.pressures_for_bend(bend)
    np.testing.assert_array_equal(model._command.state, state)


def test_bend_cap_parameter_applies():
    with pytest.raises(CommandRejectedError, match=r'<= 0.500000 rad'):
        check_bend([0.4, 0.4], max_bend_rad=0.5)


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'max_pressure_pa': 500e3}, 'max_pressure_pa must be <= 400000'),
    ({'min_pressure_pa': -1.0}, 'min_pressure_pa must be in'),
    ({'bias_pressure_pa': 300e3}, 'bias_pressure_pa must be in'),
    ({'max_bend_rad': 2.0}, 'max_bend_rad must be in'),
    ({'max_bend_rad': float('nan')}, 'max_bend_rad must be a finite number'),
])
def test_bad_model_config_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BendingModelConfig(**kwargs)

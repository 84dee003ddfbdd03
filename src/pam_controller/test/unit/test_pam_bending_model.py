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


PER_AXIS = BendingModelConfig(bend_offset_rad=(0.12, -0.07), gain_scale=(1.3, 0.8),
                              coupling=(-0.08, 0.15))
"""A model with every per-axis parameter away from nominal (offsets, gains, coupling)."""


def test_per_axis_model_forward_is_offset_plus_k_times_the_operators():
    from pam_controller.core.hysteresis import PrandtlIshlinskii

    model = BendingModel(PER_AXIS)
    pi = PrandtlIshlinskii(PER_AXIS.hysteresis, channels=2)
    k = np.array([[1.3, -0.08], [0.15, 0.8]])
    np.testing.assert_array_equal(PER_AXIS.axis_matrix, k)
    for dp in ([0.0, 0.0], [80e3, -30e3], [-120e3, 60e3]):
        p = model.differential_to_pressures(dp)
        expected = np.array([0.12, -0.07]) + k @ pi.apply(dp)
        np.testing.assert_allclose(model.bend_from_pressures(p), expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize('config', [
    PER_AXIS,
    BendingModelConfig(bend_offset_rad=(-0.3, 0.2)),
    BendingModelConfig(gain_scale=(0.6, 1.7), coupling=(0.3, -0.4)),
])
def test_round_trip_with_offsets_gains_and_coupling(config):
    """The inverse stays exact: commands -> pressures -> a separate forward model -> same bend,
    over a random sequence (every target within the pressure range of this model)."""
    command_side, plant = BendingModel(config), BendingModel(config)
    for bend in random_bends(400, seed=1) * 0.6:
        p = command_side.pressures_for_bend(bend)
        assert np.all(p >= 0.0) and np.all(p <= 300e3)
        np.testing.assert_allclose(plant.bend_from_pressures(p), bend, atol=1e-9)


def test_default_per_axis_parameters_reproduce_the_decoupled_model_exactly():
    """Nominal offsets (0), gains (1) and coupling (0) give today's pressures bit for bit."""
    from pam_controller.core.hysteresis import PrandtlIshlinskii

    model = BendingModel()
    pi = PrandtlIshlinskii(HysteresisConfig(), channels=2)
    lim = BendingModelConfig().max_differential_pa
    for bend in random_bends(200, seed=2):
        dp = np.clip(pi.solve(bend), -lim, lim)
        pi.apply(dp)
        expected = np.clip([150e3 + dp[0] / 2, 150e3 - dp[0] / 2, 150e3 + dp[1] / 2,
                            150e3 - dp[1] / 2], 0.0, 300e3)
        np.testing.assert_array_equal(model.pressures_for_bend(bend), expected)


@pytest.mark.parametrize('config', [
    PER_AXIS,
    BendingModelConfig(bend_offset_rad=(0.5, -0.5), gain_scale=(0.5, 0.5), coupling=(0.35, 0.35)),
    BendingModelConfig(gain_scale=(2.0, 0.5), coupling=(-0.5, 0.5)),
])
def test_caps_hold_whatever_the_per_axis_parameters(config):
    """Pressure caps always; the bend cap on the command, before the model."""
    model = BendingModel(config)
    for bend in random_bends(300, seed=3):
        p = model.pressures_for_bend(bend)
        assert np.all(p >= config.min_pressure_pa) and np.all(p <= config.max_pressure_pa)
    with pytest.raises(CommandRejectedError, match='expected total bend'):
        model.pressures_for_bend([1.2, 1.2])


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'bend_offset_rad': (0.6, 0.0)}, r'bend_offset_rad must be 2 numbers in \[-0.5, 0.5\]'),
    ({'bend_offset_rad': (0.0, float('nan'))}, 'bend_offset_rad must be 2 numbers'),
    ({'gain_scale': (0.4, 1.0)}, r'gain_scale must be 2 numbers in \[0.5, 2.0\]'),
    ({'coupling': (0.0, -0.6)}, r'coupling must be 2 numbers in \[-0.5, 0.5\]'),
    ({'gain_scale': (0.5, 0.5), 'coupling': (0.4, 0.4)}, r'coupling must keep det K'),
    ({'coupling': (0.1,)}, 'coupling must be 2 numbers'),
])
def test_bad_per_axis_parameters_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BendingModelConfig(**kwargs)

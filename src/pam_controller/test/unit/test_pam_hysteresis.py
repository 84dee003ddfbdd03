"""Prandtl-Ishlinskii operator: exact values, inverse, loop shape."""

import numpy as np
import pytest

from pam_controller.core.hysteresis import HysteresisConfig, PrandtlIshlinskii


def small() -> HysteresisConfig:
    # w0 = 0.5, plays r = 1, 2 with equal weights 0.25 each (density_decay 0).
    return HysteresisConfig(gain=1.0, hysteresis_fraction=0.5, play_count=2, max_threshold=2.0,
                            density_decay=0.0)


def test_weights_and_thresholds_exact():
    cfg = small()
    w0, w = cfg.weights()
    assert w0 == 0.5
    np.testing.assert_array_equal(w, [0.25, 0.25])
    np.testing.assert_array_equal(cfg.thresholds(), [1.0, 2.0])
    assert cfg.major_loop_width() == pytest.approx(2 * (0.25 * 1 + 0.25 * 2))


def test_virgin_loading_and_unloading_exact_values():
    pi = PrandtlIshlinskii(small())
    # Loading from 0 to 3: plays z1 = 2, z2 = 1 -> y = 1.5 + 0.5 + 0.25 = 2.25.
    assert pi.apply([3.0])[0] == pytest.approx(2.25)
    # Unloading to 2: plays stay (2 within [1, 3] and 1 within [0, 4]) -> y = 1 + 0.75.
    assert pi.apply([2.0])[0] == pytest.approx(1.75)
    # Loading back to 2 from 0 the virgin way gives 1 + 0.25 + 0 = 1.25: branches differ.
    fresh = PrandtlIshlinskii(small())
    assert fresh.apply([2.0])[0] == pytest.approx(1.25)


def test_solve_is_exact_inverse_from_any_state():
    pi = PrandtlIshlinskii(HysteresisConfig(), channels=2)
    rng = np.random.default_rng(1)
    for _ in range(300):
        y = rng.uniform(-2.0, 2.0, 2)
        u = pi.solve(y)
        np.testing.assert_allclose(pi.output_for(u), y, atol=1e-12)
        pi.apply(u)


def test_solve_does_not_change_state_and_output_for_neither():
    pi = PrandtlIshlinskii(HysteresisConfig(), channels=1)
    pi.apply([150e3])
    before = pi.state
    pi.solve([0.3])
    pi.output_for([-50e3])
    np.testing.assert_array_equal(pi.state, before)


def test_output_is_strictly_increasing_in_input():
    pi = PrandtlIshlinskii(HysteresisConfig())
    pi.apply([120e3])
    pi.apply([-30e3])
    u = np.linspace(-300e3, 300e3, 601)
    y = np.array([pi.output_for([x])[0] for x in u])
    assert np.all(np.diff(y) > 0)


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('gain', 0.0, 'gain must be'),
    ('gain', float('nan'), 'gain must be'),
    ('hysteresis_fraction', 0.99, 'hysteresis_fraction must be in'),
    ('play_count', 0, 'play_count must be in'),
    ('max_threshold', -1.0, 'max_threshold must be'),
    ('density_decay', -0.1, 'density_decay must be in'),
])
def test_bad_config_raises(field, value, match):
    with pytest.raises(ValueError, match=match):
        HysteresisConfig(**{field: value})


def test_wrong_input_shape_and_nan_raise():
    pi = PrandtlIshlinskii(HysteresisConfig(), channels=2)
    with pytest.raises(ValueError, match='u must have 2 values'):
        pi.apply([1.0])
    with pytest.raises(ValueError, match='u must be finite'):
        pi.apply([1.0, float('nan')])

"""The phantom's true plant: hysteresis loop, dead zone, lag, coupling, slip, backlash, tip."""

import math

from flat_wall import FlatWall
import numpy as np
import pytest

from cgail_rig.core.phantom import PhantomConfig, PhantomPhysics
from cgail_rig.core.plant import (
    bouc_wen_update,
    CatheterPlant,
    IdealPlant,
    make_plant,
    MISALIGNMENT_RANGE,
    MUSCLE_GAIN_RANGE,
    PARAM_RANGES,
    PlantParams,
)

BIAS = 150e3


def pair(d_alpha: float, d_gamma: float = 0.0) -> np.ndarray:
    """Antagonistic pressures around the controller's 150 kPa bias."""
    return np.array([BIAS + d_alpha / 2, BIAS - d_alpha / 2, BIAS + d_gamma / 2,
                     BIAS - d_gamma / 2])


def plant(**changes) -> CatheterPlant:
    return CatheterPlant(PlantParams().with_values(**changes))


def test_a_slow_sweep_gives_a_major_loop_2h_wide_with_the_bouc_wen_area() -> None:
    """Two slow cycles of +-220 kPa differential (both chambers above the dead zone): the
    second loop is 2 H wide at zero pressure and its area in the (anhysteretic bend, bend)
    plane is 2 H (2 X - 2 / rho) for sigma = 1 (X: the anhysteretic amplitude)."""
    h, turn = 0.08, 0.95
    rho = turn / (2 * h)  # a sharp turn, so the branches saturate well inside the sweep
    pl = plant(hysteresis_half_width_rad=h, hysteresis_turn=turn, hysteresis_shape=1.0,
               lag_s=0.0)
    up = np.linspace(-220e3, 220e3, 2001)
    cycle = np.concatenate([up, up[::-1][1:], up[1:]])
    for d in cycle:  # first cycle: onto the major loop
        pl.bend(pair(d), 0.01)
    xs, ys = [], []
    for d in cycle[len(up) - 1:len(up) - 1 + 2 * (len(up) - 1) + 1]:  # one closed cycle
        pl.bend(pair(d), 0.01)
        xs.append(pl.static_bend[0])
        ys.append(pl.hysteretic_bend[0])
    xs, ys = np.array(xs), np.array(ys)
    n = len(up)
    down_x, down_y = xs[:n][::-1], ys[:n][::-1]  # the first half descends: sort ascending
    up_x, up_y = xs[n - 1:], ys[n - 1:]
    width = np.interp(0.0, down_x, down_y) - np.interp(0.0, up_x, up_y)
    assert width == pytest.approx(2 * h, rel=0.01)
    amplitude = float(xs.max())
    area = 0.5 * abs(float(np.dot(xs[:-1], ys[1:]) - np.dot(xs[1:], ys[:-1])))
    assert area == pytest.approx(2 * h * (2 * amplitude - 2 / rho), rel=0.01)
    # counter-clockwise: the bend lags the pressure (the rising branch lies below)
    assert np.interp(0.0, up_x, up_y) < 0.0 < np.interp(0.0, down_x, down_y)


def test_the_plant_loop_is_not_the_controllers() -> None:
    """Same sweep through the controller's nominal model (IdealPlant): a different loop."""
    true_pl, ideal = plant(lag_s=0.0), IdealPlant()
    diffs = []
    for d in np.concatenate([np.linspace(0, 200e3, 201), np.linspace(200e3, -200e3, 401)]):
        a = true_pl.bend(pair(d), 0.01)[0]
        b = ideal.bend(pair(d), 0.01)[0]
        diffs.append(abs(a - b))
    assert max(diffs) > 0.05


def test_bouc_wen_is_rate_independent_and_bounded() -> None:
    w_one = bouc_wen_update(-0.7, 0.5, 8.0, 1.3)
    w = -0.7
    for _ in range(500):
        w = bouc_wen_update(w, 0.001, 8.0, 1.3)
    assert w == pytest.approx(w_one, abs=1e-9)
    assert bouc_wen_update(0.99, 100.0, 8.0, 1.3) == pytest.approx(1.0)
    assert bouc_wen_update(0.3, -100.0, 8.0, 0.5) == pytest.approx(-1.0)
    assert bouc_wen_update(0.3, 0.0, 8.0, 1.0) == 0.3


def test_below_the_dead_zone_a_muscle_does_not_bend_the_segment() -> None:
    pl = plant(dead_zone_pa=20e3)
    assert pl.static_pair_bend([19e3, 0.0, 0.0, 0.0]) == pytest.approx([0.0, 0.0], abs=1e-15)
    assert pl.static_pair_bend([19e3, 19e3, 19e3, 19e3]) == pytest.approx([0.0, 0.0], abs=1e-15)
    above = pl.static_pair_bend([30e3, 0.0, 0.0, 0.0])
    stiffness = pl.params.inverse_g0 + pl.params.beta * 10e3  # (its own common mode)
    assert above[0] == pytest.approx(10e3 / stiffness, rel=0.01)
    assert above[1] == 0.0


def test_common_mode_pressure_stiffens_the_pair() -> None:
    """McKibben pair: at the reference common mode the small-signal gain is gain_rad_per_pa;
    a higher common mode bends less for the same differential."""
    pl = plant(dead_zone_pa=0.0)
    small = pl.static_pair_bend(pair(1e3))[0]
    assert small / 1e3 == pytest.approx(pl.params.gain_rad_per_pa, rel=1e-3)
    stiff = pl.static_pair_bend(pair(50e3) + 50e3)[0]
    soft = pl.static_pair_bend(pair(50e3) - 50e3)[0]
    assert soft > pl.static_pair_bend(pair(50e3))[0] > stiff > 0.0


def test_the_lag_is_first_order_with_time_constant_tau() -> None:
    tau, dt = 0.2, 0.01
    pl = plant(hysteresis_half_width_rad=0.0, lag_s=tau)
    final = pl.static_pair_bend(pair(100e3))[0]
    out = [pl.bend(pair(100e3), dt)[0] for _ in range(100)]
    assert out[19] / final == pytest.approx(1 - math.exp(-1.0), rel=1e-6)   # t = tau
    assert out[59] / final == pytest.approx(1 - math.exp(-3.0), rel=1e-6)   # t = 3 tau
    assert np.all(np.diff(out) > 0.0)                                       # monotone


@pytest.mark.parametrize(('phi_a', 'phi_g'), [(0.1, -0.05), (-0.08, 0.06)])
def test_cross_coupling_has_the_sign_and_size_of_the_misalignment(phi_a, phi_g) -> None:
    pl = plant(hysteresis_half_width_rad=0.0, lag_s=0.0, misalignment_rad=(phi_a, phi_g))
    alpha, gamma = pl.bend(pair(100e3, 0.0), 0.01)
    assert gamma / alpha == pytest.approx(math.tan(phi_a), rel=1e-9)
    pl.reset()
    alpha, gamma = pl.bend(pair(0.0, 100e3), 0.01)
    assert alpha / gamma == pytest.approx(-math.tan(phi_g), rel=1e-9)


def test_gain_spread_bends_the_segment_at_equal_pressures() -> None:
    pl = plant(muscle_gain=(1.05, 0.95, 1.0, 1.0))
    bend = pl.static_pair_bend(pair(0.0))
    assert bend[0] > 0.0 and bend[1] == 0.0


def test_slip_grows_with_the_tip_load_and_never_helps_retraction() -> None:
    pl = plant(insertion_efficiency=0.95, slip_per_newton=0.15, backlash_m=0.0)
    assert pl.advance(0.001, load=0.0) == pytest.approx(0.00095, rel=1e-9)
    assert pl.advance(0.001, load=0.5) == pytest.approx(0.000875, rel=1e-9)
    assert pl.advance(0.001, load=0.8) < pl.advance(0.001, load=0.5)
    assert pl.advance(0.001, load=100.0) == 0.0                    # fully slipping
    assert pl.advance(-0.001, load=100.0) == pytest.approx(-0.00095, rel=1e-9)


def test_a_reversal_first_takes_up_the_backlash() -> None:
    b = 0.001
    pl = plant(insertion_efficiency=1.0, slip_per_newton=0.0, backlash_m=b)
    assert pl.advance(0.002) == pytest.approx(0.002 - b / 2, abs=1e-12)  # slack starts centred
    assert pl.advance(0.001) == pytest.approx(0.001, abs=1e-12)
    assert pl.advance(-0.0006) == pytest.approx(0.0, abs=1e-12)          # taking up the slack
    assert pl.advance(-0.001) == pytest.approx(-0.0006, abs=1e-12)
    assert pl.advance(0.0008) == pytest.approx(0.0, abs=1e-12)           # and back again
    assert pl.gripper == pytest.approx(0.0022, abs=1e-12)
    assert pl.gripper - pl.tip > 0.0                                      # the tip lags


def test_tip_deflection_is_the_cantilever_slope_and_bounded() -> None:
    pl = plant(flexural_rigidity_nm2=2.5e-3, max_tip_deflection_rad=0.35)
    assert pl.tip_deflection(0.0, 0.0) == 0.0
    assert pl.tip_deflection(1e-4, 0.0) == pytest.approx(1.5 * 1e-4 / 0.05, rel=1e-9)
    assert pl.tip_deflection(0.0, 0.1) == pytest.approx(0.1 * 0.05 ** 2 / 5e-3, rel=1e-9)
    assert pl.tip_deflection(0.1, 10.0) == 0.35
    assert pl.contact_load(1e-3, 0.2) == pytest.approx(0.2 + 3 * 2.5e-3 / 0.05 ** 3 * 1e-3)


def test_a_compliant_tip_turns_away_from_the_wall_within_its_bound() -> None:
    pl = CatheterPlant(PlantParams(max_tip_deflection_rad=0.2))
    ph = PhantomPhysics(PhantomConfig(), FlatWall(), pl)
    ph.reset(np.zeros(3), np.eye(3), np.array([0.0, -0.02, 0.0]))
    inward = []
    for _ in range(100):  # 50 mm bending towards +z into the wall
        ph.move(0.0005, (1.5, 0.0))
        inward.append(-float(ph.tip_rotation[:, 1][2]))
        assert ph.tip_position[2] <= 0.002 - ph.radius + 1e-12
    assert ph.contacts > 0
    assert max(inward) > 0.0                              # it turned away from the wall
    assert max(inward) <= math.sin(0.2) + 1e-9            # never beyond its bound
    assert ph.load > 0.0 or ph.contacts > 0


def test_sample_draws_every_parameter_in_its_range_per_seed() -> None:
    a = PlantParams.sample(np.random.default_rng(3))
    assert a == PlantParams.sample(np.random.default_rng(3))
    assert a != PlantParams.sample(np.random.default_rng(4))
    for name, (low, high) in PARAM_RANGES.items():
        assert low <= getattr(a, name) <= high
    assert all(MUSCLE_GAIN_RANGE[0] <= g <= MUSCLE_GAIN_RANGE[1] for g in a.muscle_gain)
    assert all(MISALIGNMENT_RANGE[0] <= p <= MISALIGNMENT_RANGE[1] for p in a.misalignment_rad)
    for name, (low, high) in PARAM_RANGES.items():  # the nominal lies in its range
        assert low <= getattr(PlantParams.nominal(), name) <= high


@pytest.mark.parametrize(('field', 'value'), [('dead_zone_pa', -1.0), ('lag_s', math.nan),
                                              ('braid_angle_rad', 1.2),
                                              ('muscle_gain', (1.0, 1.0, 1.0)),
                                              ('misalignment_rad', (0.0, 0.9)),
                                              ('gain_rad_per_pa', 1e-4)])
def test_params_reject_bad_values(field, value) -> None:
    with pytest.raises(ValueError, match=field):
        PlantParams(**{field: value})


def test_ideal_plant_is_the_controllers_nominal_model() -> None:
    from pam_controller.core.bending_model import BendingModel

    ideal, model = IdealPlant(), BendingModel()
    for d in (50e3, 150e3, 20e3, -80e3):
        assert ideal.bend(pair(d, d / 2), 0.02) == pytest.approx(
            tuple(model.bend_from_pressures(pair(d, d / 2))), abs=1e-15)
    assert ideal.advance(0.001, load=5.0) == 0.001
    assert ideal.tip_deflection(0.01, 1.0) == 0.0


def test_make_plant() -> None:
    assert isinstance(make_plant('ideal', 0), IdealPlant)
    assert make_plant('nominal', 0).params == PlantParams()
    assert make_plant('true', 7).params == PlantParams.sample(np.random.default_rng(7))
    with pytest.raises(ValueError, match="plant must be 'true', 'nominal' or 'ideal'"):
        make_plant('perfect', 0)


@pytest.mark.parametrize('turn,sigma,h', [(0.8, 1.0, 0.15), (0.95, 1.5, 0.25), (0.5, 0.6, 0.08)])
def test_the_bend_never_moves_against_the_pressure_after_a_reversal(turn, sigma, h) -> None:
    """Up to +220 kPa, then down: the hysteretic bend follows the anhysteretic one's direction
    at every step (the first draft's free rho let it keep rising after the reversal)."""
    pl = plant(hysteresis_half_width_rad=h, hysteresis_turn=turn, hysteresis_shape=sigma,
               lag_s=0.0)
    sweep = np.concatenate([np.linspace(-220e3, 220e3, 801), np.linspace(220e3, -220e3, 801)])
    prev_s = prev_h = None
    for d in sweep:
        pl.bend(pair(d), 0.01)
        s, hb = float(pl.static_bend[0]), float(pl.hysteretic_bend[0])
        if prev_s is not None:
            assert (hb - prev_h) * (s - prev_s) >= -1e-12
        prev_s, prev_h = s, hb
    assert pl.params.hysteresis_rate_per_rad == pytest.approx(turn / (2 * sigma * h))

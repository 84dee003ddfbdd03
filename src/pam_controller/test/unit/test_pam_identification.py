"""Bench identification of the bending model: excitation, bend from the EM pose, the fit."""

import math

import numpy as np
import pytest

from pam_controller.core import identification as idf
from pam_controller.core.bending_model import BendingModel, BendingModelConfig
from pam_controller.core.hysteresis import HysteresisConfig, PrandtlIshlinskii

DT = 0.05  # 20 Hz: pam_node's control rate in the session


def test_excitation_schedule_segments_and_exact_peaks() -> None:
    cfg = idf.ExcitationConfig()
    sch = idf.excitation_schedule(cfg, 0.025)
    assert sch.t.size == round(cfg.duration_s / 0.025)
    # rest, settle, sweeps alpha, sweeps gamma, multisine, settle: in that order
    changes = sch.segment[np.flatnonzero(np.diff(sch.segment)) + 1]
    assert [idf.SEGMENTS[s] for s in [sch.segment[0], *changes]] == [
        'rest', 'settle', 'sweep_alpha', 'sweep_gamma', 'multisine', 'settle']
    for seg, axis in ((idf.SWEEP_ALPHA, 0), (idf.SWEEP_GAMMA, 1)):
        dp = sch.dp[sch.segment == seg]
        assert np.max(dp[:, axis]) == 200e3 and np.min(dp[:, axis]) == -200e3
        assert np.all(dp[:, 1 - axis] == 0.0)
    ms = sch.dp[sch.segment == idf.MULTISINE]
    assert np.max(np.abs(ms)) <= 0.7 * 200e3 + 1e-6
    assert np.max(np.abs(ms)) > 0.69 * 200e3
    assert abs(np.corrcoef(ms[:, 0], ms[:, 1])[0, 1]) < 0.05  # odd vs even harmonics
    assert np.all(sch.dp[sch.segment == idf.REST] == 0.0)


def test_excitation_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match='levels must be increasing'):
        idf.ExcitationConfig(levels=(0.5, 0.25))
    with pytest.raises(ValueError, match='amplitude_pa must be in'):
        idf.ExcitationConfig(amplitude_pa=500e3)
    with pytest.raises(ValueError, match='multisine_max_hz must be >='):
        idf.ExcitationConfig(multisine_f0_hz=1.0, multisine_max_hz=1.5)


def test_bend_from_rotations_reads_a_rotation_vector() -> None:
    from scipy.spatial.transform import Rotation

    base = Rotation.from_rotvec([0.2, -0.4, 1.0]).as_matrix()
    tips = np.stack([base @ Rotation.from_rotvec([0.3, 0.0, -0.1]).as_matrix(), base])
    np.testing.assert_allclose(idf.bend_from_rotations(base, tips), [[0.3, -0.1], [0.0, 0.0]],
                               atol=1e-12)
    assert np.allclose(idf.base_rotation(np.stack([base, base])), base)


def synthetic(config: HysteresisConfig | BendingModelConfig, noise: float = 0.0,
              excitation=None, seed: int = 0) -> idf.IdentificationData:
    """Data from a known model on the excitation's pressures (plus Gaussian bend noise)."""
    sch = idf.excitation_schedule(excitation or idf.SHORT_EXCITATION, DT)
    on = sch.segment != idf.REST
    dp = sch.dp[on]
    bend = idf.predict(config, dp)
    bend = bend + np.random.default_rng(seed).normal(0.0, noise, bend.shape)
    seg = sch.segment[on]
    return idf.IdentificationData(t=sch.t[on], dp=dp, bend=bend,
                                  fit=(seg == idf.SWEEP_ALPHA) | (seg == idf.SWEEP_GAMMA),
                                  validation=seg == idf.MULTISINE)


def test_predict_equals_the_controllers_operator() -> None:
    cfg = HysteresisConfig(gain=5e-6, hysteresis_fraction=0.6, density_decay=2.0,
                           max_threshold=60e3)
    data = synthetic(cfg)
    pi = PrandtlIshlinskii(cfg, channels=2)
    expected = np.array([pi.apply(u) for u in data.dp])
    np.testing.assert_allclose(idf.predict(cfg, data.dp), expected, rtol=0, atol=1e-12)


def test_predict_equals_the_controllers_estimate_path_with_per_axis_parameters() -> None:
    """The fit's model is the controller's: ``BendingModel.bend_from_pressures`` on a record."""
    cfg = BendingModelConfig(
        hysteresis=HysteresisConfig(gain=5e-6, hysteresis_fraction=0.6, max_threshold=60e3),
        bend_offset_rad=(0.1, -0.05), gain_scale=(1.2, 1 / 1.2), coupling=(0.04, -0.07))
    data = synthetic(cfg)
    model = BendingModel(cfg)
    expected = np.array([model.bend_from_pressures(model.differential_to_pressures(u))
                         for u in data.dp])
    np.testing.assert_allclose(idf.predict(cfg, data.dp), expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize('known', [
    HysteresisConfig(gain=5e-6, hysteresis_fraction=0.6, density_decay=2.0, max_threshold=60e3),
    HysteresisConfig(gain=8e-6, hysteresis_fraction=0.3, density_decay=0.5,
                     max_threshold=150e3),
])
def test_fit_recovers_known_parameters(known: HysteresisConfig) -> None:
    data = synthetic(known)
    result = idf.fit_bending_model(data)
    got = result.config.hysteresis
    assert got.gain == pytest.approx(known.gain, rel=1e-3)
    assert got.hysteresis_fraction == pytest.approx(known.hysteresis_fraction, abs=2e-3)
    assert got.density_decay == pytest.approx(known.density_decay, abs=2e-2)
    assert got.max_threshold == pytest.approx(known.max_threshold, rel=2e-3)
    np.testing.assert_allclose(result.config.bend_offset_rad, 0.0, atol=1e-4)
    np.testing.assert_allclose(result.config.gain_scale, 1.0, atol=1e-3)
    np.testing.assert_allclose(result.config.coupling, 0.0, atol=1e-3)
    assert result.errors['identified']['all'] < 1e-4
    assert result.errors['nominal']['all'] > 0.02


@pytest.mark.parametrize(('offset', 'scale', 'coupling'), [
    ((0.12, -0.07), 1.15, (0.0, 0.07)),
    ((-0.08, 0.03), 0.9, (-0.05, 0.1)),
])
def test_fit_recovers_known_per_axis_parameters(offset, scale, coupling) -> None:
    """Offsets, a gain per axis and the coupling, with the hysteresis, from the sweeps alone:
    the held-out multisine is predicted as well."""
    known = BendingModelConfig(
        hysteresis=HysteresisConfig(gain=5e-6, hysteresis_fraction=0.6, density_decay=2.0,
                                    max_threshold=60e3),
        bend_offset_rad=offset, gain_scale=(scale, 1.0 / scale), coupling=coupling)
    data = synthetic(known)
    result = idf.fit_bending_model(data)
    got = result.config
    np.testing.assert_allclose(got.bend_offset_rad, offset, atol=1e-4)
    np.testing.assert_allclose(got.gain_scale, known.gain_scale, rtol=1e-3)
    np.testing.assert_allclose(got.coupling, coupling, atol=1e-3)
    assert got.hysteresis.gain == pytest.approx(5e-6, rel=1e-3)
    assert got.hysteresis.max_threshold == pytest.approx(60e3, rel=2e-3)
    assert result.errors['identified']['validation'] < 1e-4
    assert result.improvement < 0.01
    assert result.lag_s < 0.01  # no lag in the data


def test_fit_lag_measures_a_first_order_lag_on_the_sweeps() -> None:
    known = BendingModelConfig(hysteresis=HysteresisConfig(gain=5e-6, hysteresis_fraction=0.0))
    data = synthetic(known, excitation=idf.ExcitationConfig(levels=(1.0,), multisine_periods=1))
    lagged = idf.IdentificationData(
        t=data.t, dp=data.dp, bend=idf.first_order_lag(data.bend, data.t, 0.2), fit=data.fit,
        validation=data.validation)
    tau, errors = idf.fit_lag(known, lagged)
    assert tau == pytest.approx(0.2, abs=2e-3)
    assert errors['all'] < 1e-4


def test_fit_with_em_noise_reaches_the_noise_floor() -> None:
    known = HysteresisConfig(gain=5e-6, hysteresis_fraction=0.6, density_decay=2.0,
                             max_threshold=60e3)
    data = synthetic(known, noise=0.005)  # the Aurora's angle noise, rad RMS
    result = idf.fit_bending_model(data)
    assert result.config.hysteresis.gain == pytest.approx(known.gain, rel=0.02)
    assert result.errors['identified']['fit'] < 0.0055
    assert result.improvement < 0.5


def test_align_measures_the_base_while_vented_and_interpolates() -> None:
    from scipy.spatial.transform import Rotation

    base = Rotation.from_rotvec([0.0, 0.0, 0.5]).as_matrix()
    pt = np.arange(0.0, 20.0, DT)
    p = np.zeros((pt.size, 4))
    p[pt >= 1.0] = [160e3, 140e3, 150e3, 150e3]  # dp_alpha = 20 kPa
    et = np.arange(0.0, 20.0, 0.025)
    alpha = np.where(et >= 1.0, 0.2, 0.0)
    rot = np.stack([base @ Rotation.from_rotvec([a, 0.0, 0.0]).as_matrix() for a in alpha])
    data = idf.align(pt, p, et, rot)
    assert data.t[0] == pytest.approx(1.0)
    np.testing.assert_allclose(data.dp, np.tile([20e3, 0.0], (data.t.size, 1)))
    np.testing.assert_allclose(data.bend[:, 0], 0.2, atol=1e-12)
    with pytest.raises(idf.IdentificationError, match='found the bank vented throughout'):
        idf.align(pt, np.zeros_like(p), et, rot)
    with pytest.raises(idf.IdentificationError, match='expected EM poses while every chamber'):
        idf.align(pt, p, et[et > 2.0], rot[et > 2.0])
    with pytest.raises(idf.IdentificationError, match=r'expected measured pressures \(pam/'):
        idf.align([], np.zeros((0, 4)), et, rot)
    with pytest.raises(idf.IdentificationError, match=r'expected EM tip poses'):
        idf.align(pt, p, [], np.zeros((0, 3, 3)))


def test_check_excitation_refuses_short_small_and_saturated_data() -> None:
    model = BendingModelConfig()
    good = synthetic(HysteresisConfig())
    idf.check_excitation(good, model)
    n = good.t.size
    short = idf.IdentificationData(t=good.t, dp=good.dp, bend=good.bend,
                                   fit=np.arange(n) < 50, validation=good.validation)
    with pytest.raises(idf.IdentificationError, match='at least 100 samples of sweeps, found 50'):
        idf.check_excitation(short, model)
    small = synthetic(HysteresisConfig(), excitation=idf.ExcitationConfig(
        amplitude_pa=10e3, levels=(1.0,), multisine_periods=0, sweep_rate_pa_s=1e3))
    with pytest.raises(idf.IdentificationError, match='span of at least 40 kPa on alpha'):
        idf.check_excitation(small, model)
    big = synthetic(HysteresisConfig(), excitation=idf.ExcitationConfig(
        amplitude_pa=400e3, levels=(1.0,), multisine_periods=0, sweep_rate_pa_s=100e3))
    clipped = idf.IdentificationData(t=big.t, dp=np.clip(big.dp, -300e3, 300e3),
                                     bend=np.clip(big.bend, -1.0, 1.0), fit=big.fit,
                                     validation=big.validation)
    with pytest.raises(idf.IdentificationError, match='a saturated excitation'):
        idf.check_excitation(clipped, model)


def test_identified_parameters_are_the_yaml_keys() -> None:
    cfg = BendingModelConfig(
        hysteresis=HysteresisConfig(gain=5e-6, hysteresis_fraction=0.25, density_decay=3.0,
                                    max_threshold=80e3),
        bend_offset_rad=(0.1, -0.2), gain_scale=(1.25, 0.8), coupling=(0.05, -0.03))
    assert idf.identified_parameters(cfg) == {
        'hysteresis_gain_rad_per_pa': 5e-6, 'hysteresis_fraction': 0.25,
        'hysteresis_density_decay': 3.0, 'hysteresis_max_threshold_pa': 80e3,
        'bend_offset_alpha_rad': 0.1, 'bend_offset_gamma_rad': -0.2, 'gain_scale_alpha': 1.25,
        'gain_scale_gamma': 0.8, 'coupling_alpha_from_gamma': 0.05,
        'coupling_gamma_from_alpha': -0.03}
    assert tuple(idf.identified_parameters(cfg)) == idf.IDENTIFIED_KEYS
    assert math.isnan(idf.rms([]))

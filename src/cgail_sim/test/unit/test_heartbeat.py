"""Heartbeat waveform and annulus displacement (Plonek 2018 / Wei 2019 defaults)."""

import math

import numpy as np
import pytest

from cgail_sim.heartbeat import Heartbeat, HeartbeatConfig, waveform


def test_defaults_match_the_documented_sources():
    c = HeartbeatConfig()
    assert c.axial_amplitude == 0.010
    assert c.inplane_amplitude == 0.005
    assert c.heart_rate == 70.0
    assert c.period == pytest.approx(60.0 / 70.0)


def test_waveform_key_points_and_range():
    fs, fr = 1 / 3, 1 / 3
    assert waveform(0.0, fs, fr) == 0.0
    assert waveform(fs, fs, fr) == pytest.approx(1.0)
    assert waveform(fs / 2, fs, fr) == pytest.approx(0.5)
    assert waveform(fs + fr, fs, fr) == pytest.approx(0.0, abs=1e-15)
    assert waveform(0.9, fs, fr) == 0.0  # diastasis
    phi = np.linspace(-2, 3, 5001)
    s = waveform(phi, fs, fr)
    assert s.min() >= 0.0 and s.max() <= 1.0
    np.testing.assert_allclose(waveform(phi + 1.0, fs, fr), s, atol=1e-12)  # periodic
    assert np.abs(np.diff(s)).max() < 0.01  # continuous (no jumps on a 1e-3 grid)


def test_displacement_peaks_at_end_systole_with_both_amplitudes():
    axis = np.array([0.0, 0.0, 1.0])
    hb = Heartbeat(axis)
    t_peak = hb.config.period * hb.config.systole_fraction
    d = hb.displacement(t_peak)
    assert d @ axis == pytest.approx(-0.010)  # downward along -root_axis
    inplane = d - (d @ axis) * axis
    assert np.linalg.norm(inplane) == pytest.approx(0.005)
    np.testing.assert_allclose(hb.displacement(0.0), 0.0)
    np.testing.assert_allclose(hb.displacement(t_peak + 3 * hb.config.period), d, atol=1e-12)


def test_inplane_direction_is_perpendicular_and_rotates():
    axis = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    e0 = Heartbeat(axis, HeartbeatConfig(inplane_angle=0.0)).inplane_direction
    e1 = Heartbeat(axis, HeartbeatConfig(inplane_angle=math.pi / 2)).inplane_direction
    assert e0 @ axis == pytest.approx(0.0, abs=1e-12)
    assert e0 @ e1 == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(np.cross(e0, e1), axis, atol=1e-12)


def test_disabled_heartbeat_does_not_move():
    hb = Heartbeat(np.array([0.0, 0.0, 1.0]), HeartbeatConfig(enabled=False))
    for t in np.linspace(0, 2, 17):
        np.testing.assert_array_equal(hb.displacement(t), 0.0)


@pytest.mark.parametrize("field, value, match", [
    ("axial_amplitude", -0.001, "axial_amplitude must be in"),
    ("inplane_amplitude", 0.05, "inplane_amplitude must be in"),
    ("heart_rate", 0.0, "heart_rate must be in"),
    ("heart_rate", float("nan"), "heart_rate must be in"),
    ("systole_fraction", 1.0, "systole_fraction must be in"),
    ("return_fraction", 0.8, r"systole_fraction \+ return_fraction"),
    ("phase_offset", 1.0, "phase_offset must be in"),
    ("enabled", 1, "enabled must be a bool"),
])
def test_bad_config_raises(field, value, match):
    with pytest.raises(ValueError, match=match):
        HeartbeatConfig(**{field: value})


def test_bad_axis_raises():
    with pytest.raises(ValueError, match="root_axis must be a non-zero"):
        Heartbeat(np.zeros(3))

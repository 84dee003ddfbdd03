"""Pivot calibration and the sensor -> tip transform (pure numpy)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from synthetic_phantom import hidden_offset, PIVOT, pivoting

from em_tracker.core.calibration import (
    pivot_calibration,
    PivotConfig,
    sensor_to_tip_transform,
)
from em_tracker.core.errors import CalibrationError


@pytest.mark.parametrize('seed', range(4))
@pytest.mark.parametrize('n', [30, 60])
def test_pivot_recovers_hidden_offset(seed, n):
    rng = np.random.default_rng(seed)
    offset = hidden_offset(rng)
    result = pivot_calibration(*pivoting(rng, offset, n, tilt_deg=30.0))
    # per-axis standard error ~0.2 mm (PivotConfig.min_spread_rad); of 600 draws the
    # largest 3-D error was 0.67 mm
    assert np.linalg.norm(result.tip_offset_m - offset) < 1e-3
    assert np.linalg.norm(result.pivot_m - PIVOT) < 1e-3
    assert 0.2e-3 < result.residual_rms_m < 0.8e-3  # the Aurora's 0.48 mm and a little
    assert not result.residual_too_high
    assert math.radians(10) < result.spread_rad < math.radians(30)


def test_pivot_exact_without_noise():
    rng = np.random.default_rng(5)
    offset = hidden_offset(rng)
    result = pivot_calibration(*pivoting(rng, offset, 10, tilt_deg=20.0, noise=False))
    assert result.tip_offset_m == pytest.approx(offset, abs=1e-12)
    assert result.pivot_m == pytest.approx(PIVOT, abs=1e-12)
    assert result.residual_rms_m == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize('kwargs', [
    {'tilt_deg': 1.0},  # barely moved
    {'tilt_deg': 30.0, 'axes': 1, 'spin_deg': 0.0},  # rocked about one axis only
])
def test_pivot_refuses_a_small_spread(kwargs):
    rng = np.random.default_rng(0)
    poses = pivoting(rng, hidden_offset(rng), 40, **kwargs)
    with pytest.raises(CalibrationError, match=r'turn too little to fix the tip offset: '
                       r'expected a rotation spread of at least 5.0 deg, found \d'):
        pivot_calibration(*poses)


def test_pivot_flags_a_slipping_tip():
    rng = np.random.default_rng(1)
    rot, pos = pivoting(rng, hidden_offset(rng), 40, tilt_deg=30.0)
    pos[::2] += rng.normal(0.0, 0.003, (20, 3))
    assert pivot_calibration(rot, pos).residual_too_high


@pytest.mark.parametrize('rot,pos,match', [
    (np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3)), 'at least 3 pivoting poses, found 2'),
    (np.tile(np.eye(3), (4, 1, 1)), np.zeros((3, 3)), r'expected \(N, 3, 3\) rotations'),
    (np.tile(np.diag([1.0, 1.0, -1.0]), (4, 1, 1)), np.zeros((4, 3)),
     'found pose 0 is not'),
    (np.tile(np.eye(3), (4, 1, 1)), np.full((4, 3), math.nan), 'expected finite poses'),
])
def test_pivot_rejects_bad_poses(rot, pos, match):
    with pytest.raises(CalibrationError, match=match):
        pivot_calibration(rot, pos)


def test_pivot_config_validation():
    with pytest.raises(ValueError, match='min_spread_rad must be in'):
        PivotConfig(min_spread_rad=0.0)


@pytest.mark.parametrize('axis', [[0, 1, 0], [0, 0, 2], [1, 1, 1], [0, -1, 0], [0.3, -1, 0]])
def test_tip_frame_y_runs_along_the_shaft(axis):
    offset = np.array([0.001, -0.002, 0.015])
    t = sensor_to_tip_transform(offset, axis)
    unit = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    assert t[:3, 1] == pytest.approx(unit, abs=1e-12)
    assert t[:3, :3] @ t[:3, :3].T == pytest.approx(np.eye(3), abs=1e-12)
    assert np.linalg.det(t[:3, :3]) == pytest.approx(1.0)
    assert t[:3, 3].tolist() == offset.tolist()
    assert t[3].tolist() == [0.0, 0.0, 0.0, 1.0]


def test_tip_frame_keeps_the_sensor_axes_when_the_shaft_is_sensor_y():
    assert sensor_to_tip_transform([0, 0.01, 0], [0, 1, 0])[:3, :3] == pytest.approx(np.eye(3))


def test_tip_pose_composes_to_the_pivot():
    rng = np.random.default_rng(2)
    offset = hidden_offset(rng)
    rot, pos = pivoting(rng, offset, 5, tilt_deg=20.0, noise=False)
    t = sensor_to_tip_transform(offset, offset)
    for r, p in zip(rot, pos, strict=True):
        sensor = np.eye(4)
        sensor[:3, :3], sensor[:3, 3] = r, p
        tip = sensor @ t
        assert tip[:3, 3] == pytest.approx(PIVOT, abs=1e-12)
        # heading: from the sensor towards the tip
        assert tip[:3, 1] == pytest.approx((PIVOT - p) / np.linalg.norm(PIVOT - p), abs=1e-12)


def test_tip_transform_rejects_a_zero_axis():
    with pytest.raises(CalibrationError, match='non-zero shaft axis'):
        sensor_to_tip_transform([0, 0, 0.01], [0, 0, 0])

"""The published tip pose: T_phantom_aurora @ T_aurora_sensor @ T_sensor_tip, and its
covariance from the RMS error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from em_tracker.core.calibration import sensor_to_tip_transform
from em_tracker.core.config import TrackerConfig
from em_tracker.core.pose import (
    convert_sample,
    ORIENTATION_VARIANCE_UNKNOWN_RAD2,
    pose_covariance,
    Registration,
    tip_pose_in_phantom,
)


def _rotation(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion, written out (independent of scipy)."""
    x, y, z, w = q_xyzw / np.linalg.norm(q_xyzw)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _homogeneous(q_xyzw: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = _rotation(q_xyzw)
    m[:3, 3] = t
    return m


def _random_pose(rng: np.random.Generator, scale: float) -> tuple[np.ndarray, np.ndarray]:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q), rng.uniform(-scale, scale, size=3)


@pytest.mark.parametrize('seed', range(5))
def test_composition_equals_the_4x4_product(seed):
    rng = np.random.default_rng(seed)
    q_reg, t_reg = _random_pose(rng, 0.3)
    q_s, p_s = _random_pose(rng, 0.2)
    q_tool, t_tool = _random_pose(rng, 0.02)
    registration = Registration.from_flat([*t_reg, *q_reg])
    tool = Registration.from_flat([*t_tool, *q_tool], name='tool_transform')

    expected = (_homogeneous(q_reg, t_reg) @ _homogeneous(q_s, p_s)
                @ _homogeneous(q_tool, t_tool))
    position, quat = tip_pose_in_phantom(p_s, q_s, registration, tool)

    assert position == pytest.approx(expected[:3, 3], abs=1e-12)
    assert _rotation(quat) == pytest.approx(expected[:3, :3], abs=1e-12)
    assert quat[3] >= 0.0


def test_convert_sample_applies_the_tool_transform_after_units_and_ndi_order():
    # Sensor at (100, 0, -200) mm, turned +90 deg about z (NDI order w, x, y, z);
    # tip 10 mm along the sensor's +x, tip frame turned -90 deg about z (so tip +y = sensor +x).
    s = math.sqrt(0.5)
    tool = Registration.from_flat([0.010, 0.0, 0.0, 0.0, 0.0, -s, s])
    pose = convert_sample((s, 0.0, 0.0, s), (100.0, 0.0, -200.0), 0.2, Registration.identity(),
                          max_abs_position_m=1.0, tool_transform=tool)
    # sensor +x is aurora +y: the tip is 10 mm further along +y
    assert pose.position_m == pytest.approx([0.100, 0.010, -0.200], abs=1e-12)
    # Rz(90) Rz(-90) = identity: the tip's +y (the shaft) is the sensor's +x = aurora +y
    assert pose.quat_xyzw == pytest.approx([0.0, 0.0, 0.0, 1.0], abs=1e-12)
    assert pose.rms_error_m == pytest.approx(2e-4)


def test_identity_tool_transform_is_the_sensor_pose():
    args = ((0.5, 0.5, 0.5, 0.5), (10.0, -20.0, -150.0), 0.3,
            Registration.from_flat([1.0, 2.0, 3.0, 0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]))
    without = convert_sample(*args, max_abs_position_m=1.0)
    with_identity = convert_sample(*args, max_abs_position_m=1.0,
                                   tool_transform=Registration.identity())
    assert with_identity.position_m.tolist() == without.position_m.tolist()
    assert with_identity.quat_xyzw.tolist() == without.quat_xyzw.tolist()


def test_pivot_calibrated_tool_keeps_the_tip_on_the_pivot():
    """Sensor poses pivoting about a fixed point: with the calibrated tool transform every
    published position is the pivot, and the tip's +y is the shaft direction."""
    rng = np.random.default_rng(7)
    offset = np.array([0.002, 0.001, 0.030])  # sensor -> tip, sensor frame, m
    pivot = np.array([0.05, -0.02, -0.25])    # aurora frame, m
    tool = Registration(sensor_to_tip_transform(offset, offset))
    for _ in range(10):
        q_s, _ = _random_pose(rng, 0.0)
        rot_s = _rotation(q_s)
        p_s = pivot - rot_s @ offset
        q_ndi = (q_s[3], q_s[0], q_s[1], q_s[2])
        pose = convert_sample(q_ndi, p_s * 1e3, 0.1, Registration.identity(),
                              max_abs_position_m=1.0, tool_transform=tool)
        assert pose.position_m == pytest.approx(pivot, abs=1e-12)
        shaft = _rotation(pose.quat_xyzw) @ [0.0, 1.0, 0.0]
        assert shaft == pytest.approx(rot_s @ offset / np.linalg.norm(offset), abs=1e-12)


def test_tool_transform_errors_name_it():
    with pytest.raises(ValueError, match='tool_transform quaternion must have unit norm'):
        Registration.from_flat([0, 0, 0, 0, 0, 0, 2], name='tool_transform')
    with pytest.raises(ValueError, match='tool_transform must have 16 values'):
        Registration.from_flat([0, 0, 0], name='tool_transform')
    with pytest.raises(ValueError, match='tool_transform rotation must be orthonormal'):
        Registration.from_flat([2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
                               name='tool_transform')


def test_config_default_tool_transform_is_identity():
    assert TrackerConfig().tool_transform.matrix.tolist() == np.eye(4).tolist()


# ---- covariance of em_tracker/tip_pose_cov ------------------------------------------------
@pytest.mark.parametrize('rms_m', [0.0, 3e-4, 1.5e-3])
def test_pose_covariance_spreads_the_rms_over_three_axes(rms_m):
    cov = pose_covariance(rms_m)
    assert cov.shape == (6, 6)
    assert np.diag(cov)[:3].tolist() == [rms_m ** 2 / 3.0] * 3
    assert float(np.trace(cov[:3, :3])) == pytest.approx(rms_m ** 2, abs=1e-24)  # E|e|^2
    assert np.diag(cov)[3:].tolist() == [ORIENTATION_VARIANCE_UNKNOWN_RAD2] * 3
    assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0


@pytest.mark.parametrize('rms_m', [-1e-4, float('nan'), float('inf')])
def test_pose_covariance_rejects(rms_m):
    with pytest.raises(ValueError, match='expected a finite, non-negative RMS error'):
        pose_covariance(rms_m)

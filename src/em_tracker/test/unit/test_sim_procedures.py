"""The simulated rig's scripted motions, phantom, hidden truths and error measures (no pty)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from em_tracker.core.pose import Registration
from em_tracker.hw.sim_aurora import pose_matrix
from em_tracker.sim.procedures import (
    BOX_MAX_MM,
    BOX_MIN_MM,
    example_truth,
    FIDUCIALS,
    PHANTOM_CENTRE_MM,
    PIVOT_DIVOT_MM,
    pivot_motion,
    registration_errors,
    tool_errors,
    touch_motion,
)


def _shaft(quat_wxyz) -> np.ndarray:
    """The tip's +y axis (the shaft, towards the tip) in the phantom frame."""
    return pose_matrix([0.0, 0.0, 0.0], quat_wxyz)[:3, 1]


def _angle_deg(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def test_pivot_keeps_the_tip_in_the_divot_and_sweeps_30_deg_in_two_planes():
    motion = pivot_motion(PIVOT_DIVOT_MM, (0.0, 1.0, 0.0), 5.0)
    down = np.array([0.0, -1.0, 0.0])
    tilts, planes = [], set()
    for t in np.linspace(0.0, 5.0, 201):
        pos, quat = motion(float(t))
        assert pos.tolist() == PIVOT_DIVOT_MM.tolist()
        shaft = _shaft(quat)
        tilts.append(_angle_deg(shaft, down))
        if tilts[-1] > 1.0:
            planes.add(int(np.argmax(np.abs(shaft - down * shaft @ down))))
    assert max(tilts) == pytest.approx(30.0, abs=1e-6)  # the peaks at 1/8, 3/8 ... of the run
    assert len(planes) == 2


@pytest.mark.parametrize('fiducial', FIDUCIALS, ids=[f.name for f in FIDUCIALS])
def test_touch_holds_the_tip_in_the_divot_leaning_15_deg(fiducial):
    motion = touch_motion(fiducial, azimuth_rad=1.0)
    into = -np.asarray(fiducial.normal)
    for t in np.linspace(0.0, 0.5, 21):
        pos, quat = motion(float(t))
        assert pos.tolist() == list(fiducial.position_mm)
        assert 15.0 - 3.0 - 1e-9 <= _angle_deg(_shaft(quat), into) <= 15.0 + 3.0 + 1e-9


def test_fiducials_are_on_their_faces_of_the_box_and_spread_out():
    for f in FIDUCIALS:
        n = np.asarray(f.normal)
        face = BOX_MAX_MM if n.sum() > 0 else BOX_MIN_MM
        axis = int(np.argmax(np.abs(n)))
        assert f.position_mm[axis] == face[axis], f.name
        pos = np.asarray(f.position_mm)
        assert np.all(pos >= BOX_MIN_MM) and np.all(pos <= BOX_MAX_MM)
    points = np.array([f.position_mm for f in FIDUCIALS]) - PHANTOM_CENTRE_MM
    assert np.linalg.svd(points - points.mean(axis=0), compute_uv=False)[-1] > 50.0  # 3-D


def test_example_truth_mounts_the_sensor_on_the_shaft_in_the_aurora_volume():
    for seed in range(5):
        truth = example_truth(seed)
        tool = truth.tool_transform_m()
        offset = tool[:3, 3]
        assert 10e-3 <= np.linalg.norm(offset) <= 15e-3
        # on the axis: the offset points along the tip's +y seen from the sensor
        assert _angle_deg(offset / np.linalg.norm(offset), tool[:3, 1]) < 1e-6
        centre = truth.phantom_in_tracker @ np.append(PHANTOM_CENTRE_MM, 1.0)
        assert -330.0 <= centre[2] <= -230.0 and np.all(np.abs(centre[:2]) <= 60.0)
        assert truth.position_noise_mm == pytest.approx(0.48)
        assert truth.orientation_noise_deg == pytest.approx(0.30)
    assert example_truth(1, noise=False).position_noise_mm == 0.0


def test_error_measures_on_known_offsets():
    truth = example_truth(4)
    tool = truth.tool_transform_m()
    reg = truth.registration_m()
    assert tool_errors(truth, Registration(tool)) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert registration_errors(truth, Registration(reg)) == pytest.approx((0.0, 0.0), abs=1e-9)
    shifted = tool.copy()
    shifted[:3, 3] += [1e-3, 0.0, 0.0]
    assert tool_errors(truth, Registration(shifted)).tip_offset_mm == pytest.approx(1.0)
    moved = reg.copy()
    moved[:3, 3] += [0.0, 2e-3, 0.0]
    assert registration_errors(truth, Registration(moved)) == pytest.approx((2.0, 0.0))
    # turned 1 deg about the phantom's centre: no error there, 1 deg of rotation
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler('z', 1.0, degrees=True).as_matrix()
    centre = PHANTOM_CENTRE_MM * 1e-3
    turn[:3, 3] = centre - turn[:3, :3] @ centre
    assert registration_errors(truth, Registration(turn @ reg)) == pytest.approx((0.0, 1.0),
                                                                                abs=1e-9)

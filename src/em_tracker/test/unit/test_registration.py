"""Paired-point registration, its degeneracy checks and ICP on a lumen wall (pure numpy)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from synthetic_phantom import (
    apply_transform,
    ARCH_LENGTH,
    centreline,
    fiducials,
    hidden_transform,
    perturbed,
    pose_errors,
    RADIUS,
    touch,
    traced,
    tube_mesh,
)

from em_tracker.core.errors import CalibrationError
from em_tracker.core.pose import Registration
from em_tracker.core.registration import (
    IcpConfig,
    LumenSurface,
    PairedPointConfig,
    refine_icp,
    register_paired_points,
    rigid_fit,
)


def test_rigid_fit_exact_and_never_reflects():
    rng = np.random.default_rng(1)
    truth = hidden_transform(rng)
    src = rng.normal(size=(5, 3))
    assert rigid_fit(src, apply_transform(truth, src)) == pytest.approx(truth, abs=1e-12)
    # a mirrored target: the best rotation is still a rotation
    planar = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    fit = rigid_fit(planar, planar * [1, 1, -1] + [[0, 0, 0.1], [0, 0, -0.1], [0] * 3, [0] * 3])
    assert np.linalg.det(fit[:3, :3]) == pytest.approx(1.0)


@pytest.mark.parametrize('seed', range(5))
@pytest.mark.parametrize('n', [6, 8])
def test_paired_points_recover_hidden_transform(seed, n):
    rng = np.random.default_rng(seed)
    truth = hidden_transform(rng)
    model = fiducials(rng, n)
    result = register_paired_points(model, touch(model, truth, rng))
    # at the phantom centre (over 400 draws: 99 % under 0.85 mm, rotation under 0.45 deg)
    pos_err, ang_err = pose_errors(result.registration.matrix, truth, np.zeros((1, 3)))
    assert pos_err < 1e-3 and ang_err < 1.0
    # FRE^2 ~ (1 - 2/N) FLE^2 and LOO-TRE errs high: both of the Aurora's order
    assert 0.1e-3 < result.fre_m < 1.0e-3
    assert result.fre_m < result.tre_m < 2.0e-3
    assert not result.fre_too_high
    assert result.residuals_m.shape == result.loo_errors_m.shape == (n,)


def test_fre_flag_on_a_mistouched_fiducial():
    rng = np.random.default_rng(3)
    truth = hidden_transform(rng)
    model = fiducials(rng, 6)
    tracker = touch(model, truth, rng)
    tracker[2] += [0.01, 0.0, 0.0]  # touched the neighbouring divot
    result = register_paired_points(model, tracker)
    assert result.fre_too_high and result.fre_m > 2e-3
    assert int(np.argmax(result.loo_errors_m)) == 2


def test_three_fiducials_register_without_tre():
    model = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.08, 0]])
    result = register_paired_points(model, model + 0.01)
    assert result.fre_m == pytest.approx(0.0, abs=1e-12)
    assert math.isnan(result.tre_m)


@pytest.mark.parametrize('model,tracker,match', [
    (np.zeros((2, 3)), np.zeros((2, 3)), 'expected at least 3 fiducials, found 2'),
    (np.zeros((4, 3)), np.zeros((5, 3)), 'expected as many tracker as model fiducials'),
    (np.zeros((4, 2)), np.zeros((4, 2)), r'expected an \(N, 3\) array'),
    ([[0, 0, 0], [1, 0, 0], [0, 1, math.nan]], np.eye(3), 'NaN/inf at row 2'),
])
def test_paired_points_rejects_bad_arrays(model, tracker, match):
    with pytest.raises(CalibrationError, match=match):
        register_paired_points(model, tracker)


@pytest.mark.parametrize('off_line_m', [0.0, 0.002])
def test_collinear_fiducials_refused(off_line_m):
    model = np.array([[x, 0.0, 0.0] for x in np.linspace(-0.07, 0.07, 6)])
    model[::2, 1] += off_line_m  # alternate sides: RMS 2 mm from the line
    model[1::2, 1] -= off_line_m
    with pytest.raises(CalibrationError, match=r'model fiducials: fiducials \(nearly\) '
                       r'collinear: expected .* at least 10.0 mm, found \d'):
        register_paired_points(model, model)
    with pytest.raises(ValueError):  # CalibrationError is a ValueError
        register_paired_points(model, model)
    # a looser, explicit limit accepts the 2 mm case
    if off_line_m:
        register_paired_points(model, model, PairedPointConfig(min_line_distance_m=0.001))


def test_config_validation():
    with pytest.raises(ValueError, match='max_fre_m must be in'):
        PairedPointConfig(max_fre_m=0.0)
    with pytest.raises(ValueError, match='reject_sigmas must be in'):
        IcpConfig(reject_sigmas=0.5)


# ------------------------------------------------------------------------------------ ICP
@pytest.fixture(scope='module')
def mesh_surface() -> LumenSurface:
    return LumenSurface.from_mesh(*tube_mesh())


@pytest.mark.parametrize('seed', range(3))
def test_icp_converges_from_a_perturbed_guess(seed, mesh_surface):
    rng = np.random.default_rng(seed)
    truth = hidden_transform(rng)
    on_wall = traced(rng)
    points = touch(on_wall, truth, rng)
    start = perturbed(truth, on_wall.mean(axis=0), rng)
    result = refine_icp(points, mesh_surface, start)
    pos_err, ang_err = pose_errors(result.registration.matrix, truth, on_wall)
    assert pos_err < 1e-3 and ang_err < 1.0, (pos_err, ang_err)
    assert result.converged and result.iterations < 60
    assert result.rms_m < 1e-3  # the wall is fitted to about the Aurora's noise
    assert result.inliers.mean() > 0.9
    assert 3e-3 < result.correction_m < 12e-3 and result.correction_rad > math.radians(3)


def test_icp_rejects_outliers_and_takes_a_point_cloud(mesh_surface):
    rng = np.random.default_rng(7)
    truth = hidden_transform(rng)
    on_wall = traced(rng)
    c, _ = centreline(np.linspace(0.005, ARCH_LENGTH - 0.005, 200))
    outward = (on_wall - c) / RADIUS
    on_wall[::20] += 0.006 * outward[::20]  # 10 readings 6 mm outside the wall (distortion)
    points = touch(on_wall, truth, rng)
    cloud = LumenSurface.from_points(mesh_surface.points_m[::4])
    result = refine_icp(points, cloud, perturbed(truth, on_wall.mean(axis=0), rng))
    pos_err, ang_err = pose_errors(result.registration.matrix, truth, on_wall)
    assert pos_err < 1e-3 and ang_err < 1.0, (pos_err, ang_err)
    assert not result.inliers[::20].any() and result.inliers.sum() >= 180


def test_icp_refuses_a_far_start(mesh_surface):
    rng = np.random.default_rng(0)
    on_wall = traced(rng)
    start = Registration.from_flat([0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    with pytest.raises(CalibrationError, match=r'expected at least 100 of 200 points within '
                       r'10 mm of the wall, found \d+'):
        refine_icp(on_wall, mesh_surface, start)


def test_mesh_in_millimetres_refused():
    verts, faces = tube_mesh()
    with pytest.raises(CalibrationError, match='mesh not in metres'):
        LumenSurface.from_mesh(verts * 1e3, faces)

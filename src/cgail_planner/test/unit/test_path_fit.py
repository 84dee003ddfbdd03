"""B-spline fit, arc-length resampling, closest points and curvature against exact geometry."""

import numpy as np
import pytest

from cgail_planner.core.path_fit import (
    closest_points,
    discrete_curvature,
    drop_duplicates,
    fit_path,
    PathFitConfig,
    PathFitError,
    polyline_length,
    resample_by_arc_length,
)


def arc(radius: float, angle: float, n: int) -> np.ndarray:
    phi = np.linspace(0.0, angle, n)
    return np.column_stack([radius * np.cos(phi), radius * np.sin(phi), np.zeros(n)])


def test_straight_line_is_resampled_uniformly_and_exactly() -> None:
    way = np.array([[0.0, 0.0, 0.0], [0.03, 0.0, 0.0], [0.1, 0.0, 0.0]])
    out = fit_path(way, PathFitConfig(spacing=0.01))
    np.testing.assert_allclose(out[:, 0], np.linspace(0.0, 0.1, 11), atol=1e-12)
    np.testing.assert_allclose(out[:, 1:], 0.0, atol=1e-12)


def test_fit_of_a_circular_arc_stays_on_the_circle() -> None:
    out = fit_path(arc(0.05, np.pi / 2, 25), PathFitConfig(spacing=0.5e-3))
    radius = np.linalg.norm(out[:, :2], axis=1)
    np.testing.assert_allclose(radius, 0.05, atol=2e-6)
    step = np.linalg.norm(np.diff(out, axis=0), axis=1)
    np.testing.assert_allclose(step, step[0], rtol=1e-3)
    assert polyline_length(out) == pytest.approx(0.05 * np.pi / 2, rel=1e-5)
    np.testing.assert_allclose(out[0], [0.05, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out[-1], [0.0, 0.05, 0.0], atol=1e-12)


@pytest.mark.parametrize('count', [2, 3, 4])
def test_few_waypoints_lower_the_degree(count: int) -> None:
    way = np.column_stack([np.linspace(0, 0.02, count), np.zeros(count), np.zeros(count)])
    out = fit_path(way, PathFitConfig(spacing=1e-3))
    assert len(out) == 21
    np.testing.assert_allclose(out[-1], [0.02, 0.0, 0.0], atol=1e-12)


def test_duplicate_waypoints_are_dropped_before_fitting() -> None:
    way = np.array([[0, 0, 0], [0, 0, 0], [0.01, 0, 0], [0.01, 0, 0], [0.02, 0.0, 0]], float)
    assert len(drop_duplicates(way)) == 3
    assert polyline_length(fit_path(way)) == pytest.approx(0.02, rel=1e-9)


@pytest.mark.parametrize(('way', 'match'), [
    (np.zeros((1, 3)), 'at least 2 distinct waypoints, found 1'),
    (np.zeros((5, 3)), 'at least 2 distinct waypoints, found 1'),
    (np.zeros((4, 2)), r'shape \(N, 3\), found \(4, 2\)'),
    (np.array([[0, 0, 0], [np.nan, 0, 0]]), 'finite'),
])
def test_bad_waypoints_raise(way: np.ndarray, match: str) -> None:
    with pytest.raises(PathFitError, match=match):
        fit_path(way)


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('spacing', 0.0, 'spacing must be a positive'),
    ('smoothing', -1.0, 'smoothing must be >= 0'),
    ('degree', 6, 'degree must be in 1..5'),
    ('oversample', 1, 'oversample must be >= 2'),
])
def test_config_validation(field: str, value: float, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        PathFitConfig(**{field: value})


def test_closest_points_on_a_polyline_are_exact_projections() -> None:
    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    queries = np.array([[0.5, 0.2, 0.0], [1.3, 0.5, 0.0], [-1.0, 0.0, 0.0], [0.5, 0.0, 0.4],
                        [2.0, 2.0, 0.0]])
    dist, proj = closest_points(queries, line)
    np.testing.assert_allclose(dist, [0.2, 0.3, 1.0, 0.4, np.sqrt(2.0)], atol=1e-12)
    np.testing.assert_allclose(proj, [[0.5, 0, 0], [1, 0.5, 0], [0, 0, 0], [0.5, 0, 0],
                                      [1, 1, 0]], atol=1e-12)


def test_closest_points_to_a_resampled_circle_are_radial() -> None:
    path = fit_path(arc(0.06, np.pi / 2, 40))
    phi = np.linspace(0.1, 1.4, 50)
    q = np.column_stack([0.063 * np.cos(phi), 0.063 * np.sin(phi), np.full(50, 0.002)])
    dist, _ = closest_points(q, path)
    np.testing.assert_allclose(dist, np.hypot(0.003, 0.002), atol=1e-6)


def test_resample_keeps_end_points_and_spacing() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0095]])
    out = resample_by_arc_length(pts, 0.001)
    assert len(out) == 11
    np.testing.assert_allclose(out[-1], pts[-1])
    with pytest.raises(PathFitError, match='at least 2 distinct points'):
        resample_by_arc_length(np.zeros((3, 3)), 0.001)


def test_menger_curvature_is_exact_on_a_circle_and_zero_on_a_line() -> None:
    np.testing.assert_allclose(discrete_curvature(arc(0.02, 1.0, 30)), 50.0, rtol=1e-9)
    line = np.column_stack([np.linspace(0, 1, 5), np.zeros(5), np.zeros(5)])
    np.testing.assert_allclose(discrete_curvature(line), 0.0, atol=1e-12)
    assert discrete_curvature(line[:2]).shape == (0,)

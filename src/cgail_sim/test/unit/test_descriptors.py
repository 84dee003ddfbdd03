"""Anatomy descriptors on shapes whose answer is known: arcs, straight tubes, a U-shaped arch,
a branch at a known angle, a known root tilt, and the built-in aorta against its generator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cgail_sim.anatomy import anatomy_params, AnatomyError, AortaGeometry, build_anatomy
from cgail_sim.descriptors import (
    anatomy_descriptors,
    AnatomyDescriptors,
    arch_limits,
    branch_takeoff,
    DescriptorConfig,
    DESCRIPTORS,
    root_tilt,
    segment_shape,
    SegmentShape,
    Trunk,
)

MM = 1e-3
STEP = 0.5 * MM


def _arc_length(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _circular_arc(radius: float, angle: float) -> np.ndarray:
    """A planar arc (tilted out of every axis plane) of ``radius`` through ``angle`` rad."""
    t = np.linspace(0.0, angle, int(radius * angle / STEP) + 1)
    u = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    v = np.array([-1.0, 1.0, 2.0]) / math.sqrt(6.0)
    return radius * (np.outer(np.cos(t), u) + np.outer(np.sin(t), v))


def _line(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = int(np.linalg.norm(b - a) / STEP) + 1
    return a + np.outer(np.linspace(0.0, 1.0, n), b - a)


def _u_arch(rise: float, width: float, drop: float) -> np.ndarray:
    """Up ``rise`` along +z from the origin, a half circle of diameter ``width`` over +x, and
    down ``drop`` below the origin's level."""
    r = 0.5 * width
    up = _line(np.zeros(3), np.array([0.0, 0.0, rise]))
    th = np.linspace(0.0, math.pi, int(math.pi * r / STEP) + 1)
    top = np.stack([r - r * np.cos(th), np.zeros_like(th), rise + r * np.sin(th)], axis=1)
    down = _line(np.array([width, 0.0, rise]), np.array([width, 0.0, -drop]))
    return np.vstack([up, top[1:], down[1:]])


@pytest.mark.parametrize("tilt_deg", [0.0, 25.0, 49.4, 90.0])
@pytest.mark.parametrize("azimuth_deg", [0.0, 135.0, 290.0])
def test_root_tilt_of_a_known_rotation(tilt_deg: float, azimuth_deg: float) -> None:
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    axis = np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)])
    assert root_tilt(3.0 * axis) == pytest.approx(t, abs=1e-9)


def test_root_tilt_refuses_a_zero_axis() -> None:
    with pytest.raises(ValueError, match="root_axis must be a non-zero 3-vector"):
        root_tilt(np.zeros(3))


@pytest.mark.parametrize("radius_mm, angle_deg", [(20.0, 90.0), (40.0, 180.0), (60.0, 120.0)])
def test_circular_arc_has_curvature_one_over_r_and_known_tortuosity(
        radius_mm: float, angle_deg: float) -> None:
    r, th = radius_mm * MM, math.radians(angle_deg)
    pts = _circular_arc(r, th)
    radii = np.full(len(pts), 7.0 * MM)
    shape = segment_shape(pts, radii, 0.0, float(_arc_length(pts)[-1]), window=10 * MM)
    assert shape.length == pytest.approx(r * th, rel=1e-4)
    assert shape.tortuosity == pytest.approx(th / (2.0 * math.sin(th / 2.0)) - 1.0, abs=1e-3)
    assert shape.curvature_mean == pytest.approx(1.0 / r, rel=1e-3)
    assert shape.curvature_max == pytest.approx(1.0 / r, rel=1e-3)
    assert shape.radius_p50 == pytest.approx(7.0 * MM)


def test_half_circle_tortuosity_is_pi_over_two_minus_one() -> None:
    pts = _circular_arc(30 * MM, math.pi)
    shape = segment_shape(pts, np.ones(len(pts)), 0.0, float(_arc_length(pts)[-1]), 10 * MM)
    assert shape.tortuosity == pytest.approx(math.pi / 2.0 - 1.0, abs=1e-3)


def test_straight_tube_has_no_curvature_and_no_tortuosity() -> None:
    pts = _line(np.zeros(3), np.array([0.03, -0.04, 0.12]))
    radii = np.linspace(10 * MM, 12 * MM, len(pts))
    shape = segment_shape(pts, radii, 0.0, float(_arc_length(pts)[-1]), window=10 * MM)
    assert shape.tortuosity == pytest.approx(0.0, abs=1e-9)
    assert shape.curvature_mean == pytest.approx(0.0, abs=1e-6)
    assert shape.curvature_max == pytest.approx(0.0, abs=1e-6)
    assert shape.radius_p10 == pytest.approx(10.2 * MM, abs=0.01 * MM)
    assert shape.radius_p90 == pytest.approx(11.8 * MM, abs=0.01 * MM)


def test_a_piece_sees_only_its_own_points_and_ignores_nan_radii() -> None:
    # straight 60 mm, then a 90 deg arc of 25 mm radius: the straight piece, away from the arc
    # by more than the window, is straight; the arc's piece has curvature 1/25 mm
    straight = _line(np.array([0.0, 0.0, -0.06]), np.zeros(3))
    t = np.linspace(0.0, math.pi / 2, int(0.025 * math.pi / 2 / STEP) + 1)
    arc = np.stack([0.025 * (1 - np.cos(t)), np.zeros_like(t), 0.025 * np.sin(t)], axis=1)
    pts = np.vstack([straight, arc[1:]])
    radii = np.where(np.arange(len(pts)) < 10, np.nan, 9 * MM)
    flat = segment_shape(pts, radii, 0.0, 0.045, window=10 * MM)
    assert flat.curvature_max == pytest.approx(0.0, abs=1e-6)
    assert flat.radius_p10 == pytest.approx(9 * MM)
    bent = segment_shape(pts, radii, 0.075, 0.06 + 0.025 * math.pi / 2, window=10 * MM)
    assert bent.curvature_mean == pytest.approx(40.0, rel=1e-3)
    # a corner at the first point is not measured from curved_from=1 on
    kinked = np.vstack([[0.03, 0.0, -0.09], pts])
    radii_k = np.concatenate([[np.nan], radii])
    s0 = float(np.linalg.norm(kinked[1] - kinked[0]))
    corner = segment_shape(kinked, radii_k, 0.0, s0 + 0.045, window=10 * MM)
    assert corner.curvature_max > 10.0
    after = segment_shape(kinked, radii_k, 0.0, s0 + 0.045, window=10 * MM, curved_from=1)
    assert after.curvature_max == pytest.approx(0.0, abs=1e-6)
    assert math.isnan(segment_shape(pts, radii, 0.05, 0.05, 10 * MM).length)


@pytest.mark.parametrize("rise_mm, width_mm", [(40.0, 60.0), (70.0, 90.0)])
def test_u_shaped_arch_limits_width_height_and_segments(rise_mm: float, width_mm: float) -> None:
    rise, width, drop, depth = rise_mm * MM, width_mm * MM, 0.08, 0.05
    r = 0.5 * width
    pts = _u_arch(rise, width, drop=drop)
    ones = np.ones(len(pts))
    limits = arch_limits(pts, depth)
    # the arch level (50 mm below the apex) crosses both straight limbs
    assert limits.width == pytest.approx(width, abs=1e-6)
    assert limits.height == pytest.approx(rise + r, abs=1e-6)
    assert limits.s_apex == pytest.approx(rise + 0.5 * math.pi * r, abs=STEP)
    assert limits.s_start == pytest.approx(rise + r - depth, abs=1e-6)
    arch_len = math.pi * r + 2.0 * (depth - r)
    assert limits.s_end - limits.s_start == pytest.approx(arch_len, rel=1e-5)   # (chords)
    ascending = segment_shape(pts, ones, 0.0, limits.s_start, 5 * MM)
    assert ascending.tortuosity == pytest.approx(0.0, abs=1e-9)
    arch = segment_shape(pts, ones, limits.s_start, limits.s_end, 5 * MM)
    assert arch.tortuosity == pytest.approx(arch_len / width - 1.0, abs=1e-4)
    assert arch.curvature_max == pytest.approx(1.0 / r, rel=1e-3)
    descending = segment_shape(pts, ones, limits.s_end, float(_arc_length(pts)[-1]), 5 * MM)
    assert descending.length == pytest.approx(rise + r - depth + drop, abs=1e-6)
    assert descending.tortuosity == pytest.approx(0.0, abs=1e-9)


def test_a_trunk_that_stops_above_the_arch_level_has_no_arch_end() -> None:
    pts = _u_arch(0.04, 0.06, drop=0.0)[:-40]      # stops 20 mm above the start's level
    limits = arch_limits(pts, depth=0.06)
    assert limits.s_start == pytest.approx(0.01, abs=1e-6)
    assert math.isnan(limits.s_end) and math.isnan(limits.width)
    assert limits.height == pytest.approx(0.07, abs=1e-6)


@pytest.mark.parametrize("angle_deg", [45.0, 90.0, 130.0])
def test_branch_takeoff_position_and_angle_of_a_straight_branch(angle_deg: float) -> None:
    # trunk along +x (downstream) with a 10 mm lumen; the branch leaves its centreline at
    # s = 70 mm, so its mouth (where it crosses the 10 mm radius) lies r cot(angle) downstream
    r = 10 * MM
    trunk_pts = _line(np.zeros(3), np.array([0.15, 0.0, 0.0]))
    trunk = Trunk(points=trunk_pts, radii=np.full(len(trunk_pts), r))
    a = math.radians(angle_deg)
    take_off = np.array([0.07, 0.0, 0.0])
    out = take_off + 0.04 * np.array([math.cos(a), 0.0, math.sin(a)])
    branch = np.vstack([_line(np.array([0.15, 0.0, 0.0]), take_off), _line(take_off, out)[1:]])
    s0, angle = branch_takeoff(trunk, branch, probe=(5 * MM, 15 * MM), window=10 * MM)
    assert s0 == pytest.approx(0.07 + r / math.tan(a), abs=1.5 * STEP)
    assert angle == pytest.approx(a, abs=1e-6)


def test_branch_takeoff_refuses_a_branch_ending_inside_the_trunk() -> None:
    trunk_pts = _line(np.zeros(3), np.array([0.15, 0.0, 0.0]))
    trunk = Trunk(points=trunk_pts, radii=np.full(len(trunk_pts), 10 * MM))
    with pytest.raises(AnatomyError, match="ending inside it"):
        branch_takeoff(trunk, trunk_pts[::-1][:100], probe=(5 * MM, 15 * MM), window=10 * MM)


def test_values_are_flat_in_descriptor_order_with_nan_for_a_missing_branch() -> None:
    seg = SegmentShape(0.1, 0.2, 10.0, 20.0, 0.01, 0.012, 0.014)
    d = AnatomyDescriptors(root_tilt=0.5, arch_width=0.05, arch_height=0.09, ascending=seg,
                           arch=seg, descending=seg, branch_positions=(0.09, 0.11),
                           branch_angles=(1.5, 1.2))
    values = d.values()
    assert list(values) == [x.key for x in DESCRIPTORS]
    assert values["branch_count"] == 2.0
    assert values["branch2_position"] == 0.11 and values["descending_radius_p90"] == 0.014
    assert math.isnan(values["branch3_position"]) and math.isnan(values["branch3_angle"])


@pytest.mark.parametrize("field, value", [("arch_depth", 0.005), ("spacing", 0.0),
                                          ("curvature_window", 0.1),
                                          ("branch_probe_to", 0.006),
                                          ("coronary_gap", True)])
def test_config_refuses_out_of_range_fields(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=f"{field} must be in"):
        DescriptorConfig(**{field: value})


def test_builtin_aorta_matches_its_generator() -> None:
    """The default aorta's descriptors, measured from its mesh, against the generator's spine
    (within the medial centreline's accuracy)."""
    params = anatomy_params("default")
    g = AortaGeometry(params)
    d = anatomy_descriptors(build_anatomy("default"))
    assert math.degrees(d.root_tilt) == pytest.approx(25.0, abs=1e-6)
    spine = g.spine[(g.arc >= 0.0) & (g.arc <= g.s_exit - 0.02)]
    limits = arch_limits(spine, DescriptorConfig().arch_depth)
    assert d.arch_height == pytest.approx(limits.height, abs=1 * MM)
    assert d.arch_width == pytest.approx(limits.width, abs=2 * MM)
    assert d.descending.tortuosity == pytest.approx(0.0, abs=0.002)
    assert d.descending.radius_p50 == pytest.approx(0.5 * params.descending_diameter,
                                                    abs=0.5 * MM)
    assert d.branch_count == 3

    def angle_to(direction: np.ndarray, at: float) -> float:
        """Angle between a direction and the spine's downstream tangent at arc length ``at``."""
        t = (g.spine[np.argmin(np.abs(g.arc - at - 0.01))]
             - g.spine[np.argmin(np.abs(g.arc - at + 0.01))])
        return math.acos(t @ direction / np.linalg.norm(t))

    for tube, s_mouth, angle in zip(g.tubes[:3], d.branch_positions, d.branch_angles,
                                    strict=True):
        # the mouth: r cot(angle) downstream of the stub's origin on the spine
        s = g.s_branches[tube.name]
        r = float(g.radius[np.argmin(np.abs(g.arc - s))])
        assert s_mouth == pytest.approx(s + r / math.tan(angle_to(tube.direction, s)),
                                        abs=6 * MM)
        # the stub's direction against the spine's tangent at the mouth
        assert math.degrees(angle) == pytest.approx(
            math.degrees(angle_to(tube.direction, s_mouth)), abs=3.0)

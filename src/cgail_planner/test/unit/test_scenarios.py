"""Start configurations and targets (paper section IV-A) on the built-in anatomy."""

import numpy as np
import pytest

from cgail_planner.sim.anatomy import build_anatomy
from cgail_planner.sim.centerline import compute_centerlines
from cgail_planner.sim.scenarios import build_targets, load_world, ScenarioError

WORLD = load_world("default")
SC = WORLD.scenarios
ANATOMY = WORLD.anatomy


def _arc(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def test_three_starts_within_53_mm_along_the_descending_aorta() -> None:
    assert len(SC.starts) == 3
    assert [s.arc_offset for s in SC.starts] == pytest.approx([0.0, 0.0265, 0.053])
    pos = np.array([s.position for s in SC.starts])
    assert ANATOMY.contains(pos).all()
    # consecutive starts are <= 26.5 mm apart (arc), and all lie on the left centerline
    gaps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert np.all(gaps <= 0.0265 + 1e-9)
    cl = WORLD.centerlines["left"].points
    dist = np.min(np.linalg.norm(cl[None] - pos[:, None], axis=2), axis=1)
    assert np.all(dist < 0.003)
    for s in SC.starts:
        rot = s.rotation
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0)
        # heading points cranially (away from the exit), the introducer ends outside the exit
        assert float(rot[:, 1] @ ANATOMY.exit_normal) < -0.5
        assert float((s.introducer_tail - ANATOMY.exit_point) @ ANATOMY.exit_normal) \
            == pytest.approx(0.005, abs=1e-9)


def test_five_targets_inside_lumen_near_ostia() -> None:
    assert len(SC.targets) == 5
    centre = 0.5 * (ANATOMY.ostia["left"] + ANATOMY.ostia["right"])
    pos = np.array([t.position for t in SC.targets])
    assert ANATOMY.contains(pos).all()
    assert np.all(np.linalg.norm(pos - centre, axis=1) <= 0.030)
    for t in SC.targets:
        np.testing.assert_allclose(ANATOMY.vertices[t.vertex] + t.offset, t.position,
                                   atol=1e-15)
        # attached to the nearest wall vertex
        wall_ids = np.unique(ANATOMY.faces[ANATOMY.wall_face_mask])
        nearest = wall_ids[np.argmin(np.linalg.norm(ANATOMY.vertices[wall_ids] - t.position,
                                                    axis=1))]
        assert t.vertex == nearest
        assert t.branch == min(("left", "right"),
                               key=lambda b: np.linalg.norm(t.position - ANATOMY.ostia[b]))
    sep = np.linalg.norm(pos[:, None] - pos[None], axis=2) + np.eye(5)
    assert sep.min() >= 0.005


def test_targets_are_seeded() -> None:
    a = build_targets(ANATOMY, seed=0)
    b = build_targets(ANATOMY, seed=0)
    c = build_targets(ANATOMY, seed=1)
    np.testing.assert_array_equal([t.position for t in a], [t.position for t in b])
    assert not np.allclose([t.position for t in a], [t.position for t in c])
    np.testing.assert_array_equal([t.position for t in a], [t.position for t in SC.targets])


def test_impossible_targets_raise() -> None:
    with pytest.raises(ScenarioError, match="expected 5 targets"):
        build_targets(ANATOMY, target_clearance=0.05, max_candidates=512)


def test_normalisers() -> None:
    verts = ANATOMY.vertices
    starts = np.array([s.position for s in SC.starts])
    for t in SC.targets:
        assert np.all(np.linalg.norm(starts - t.position, axis=1) <= SC.d_max)
        assert np.linalg.norm(verts - t.position, axis=1).max() <= SC.d_max + 1e-12
    np.testing.assert_allclose(SC.origin, 0.5 * (verts.min(axis=0) + verts.max(axis=0)))
    for b in ("left", "right"):
        np.testing.assert_array_equal(SC.waypoints[b], WORLD.centerlines[b].points)


def test_world_is_cached_and_shared() -> None:
    assert load_world("default") is WORLD


@pytest.mark.slow  # builds a second mesh and its Voronoi centerlines (~10 s without disk cache)
def test_second_anatomy_builds_scenarios() -> None:
    from cgail_planner.sim.anatomy import ANATOMY_NAMES

    other = next(n for n in ANATOMY_NAMES if n != "default")
    anatomy = build_anatomy(other)
    world = load_world(other)
    assert world.anatomy is anatomy
    assert len(world.scenarios.starts) == 3 and len(world.scenarios.targets) == 5
    assert set(compute_centerlines(anatomy)) >= {"left", "right"}

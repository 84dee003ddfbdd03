"""Start configurations, their introducers and targets (paper section IV-A)."""


import numpy as np
import pytest

from cgail_sim.anatomy import build_anatomy
from cgail_sim.centerline import compute_centerlines
from cgail_sim.scenarios import (
    build_starts,
    build_targets,
    INTRODUCER_RADIUS,
    introducer_tail,
    ScenarioError,
    tube_clearance,
)
from cgail_sim.testing import curved_world
from cgail_sim.worlds import load_world

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
    from cgail_sim.anatomy import ANATOMY_NAMES

    other = next(n for n in ANATOMY_NAMES if n != "default")
    anatomy = build_anatomy(other)
    world = load_world(other)
    assert world.anatomy is anatomy
    assert len(world.scenarios.starts) == 3 and len(world.scenarios.targets) == 5
    assert set(compute_centerlines(anatomy)) >= {"left", "right"}


# ---------------------------------------------------------------- introducers (issue 12)
@pytest.fixture(scope="module")
def curved():
    """The world of the aorta whose descending part curves near its open end."""
    return curved_world()


def _cap_radius(anatomy) -> float:
    cap = np.unique(anatomy.faces[~anatomy.wall_face_mask])
    rel = anatomy.vertices[cap] - anatomy.exit_point
    on_plane = np.abs(rel @ anatomy.exit_normal) < 1e-4
    return float(np.linalg.norm(rel[on_plane], axis=1).max())


@pytest.mark.parametrize("name", ["default", "elongated"])
def test_built_in_starts_keep_their_straight_introducers_inside_the_lumen(name: str) -> None:
    world = load_world(name)
    for s in world.scenarios.starts:
        assert not s.bent and s.introducer.shape == (1, 3)
        assert np.array_equal(s.introducer[0], s.introducer_tail)
        assert np.array_equal(s.introducer_tail,
                              introducer_tail(world.anatomy, s.position, s.rotation))
        clearance, _ = tube_clearance(world.anatomy, np.vstack([s.introducer, s.position]))
        assert clearance >= INTRODUCER_RADIUS


def test_curved_descending_aorta_straight_introducer_runs_outside_the_wall(curved) -> None:
    """Issue 12 reproduced: the straight introducer behind start 2 (53 mm up) leaves the lumen
    and crosses the exit plane outside the cap."""
    anatomy = curved.anatomy
    s = curved.scenarios.starts[2]
    tail = introducer_tail(anatomy, s.position, s.rotation)
    clearance, _ = tube_clearance(anatomy, np.stack([tail, s.position]))
    assert clearance < -0.003  # its axis runs > 3 mm beyond the wall
    h, n = s.rotation[:, 1], anatomy.exit_normal
    cross = s.position - float((s.position - anatomy.exit_point) @ n) / float(h @ n) * h
    assert np.linalg.norm(cross - anatomy.exit_point) > _cap_radius(anatomy) + 0.003


def test_curved_descending_aorta_starts_get_introducers_along_the_centerline(curved) -> None:
    anatomy = curved.anatomy
    starts = curved.scenarios.starts
    assert [s.bent for s in starts] == [False, True, True]
    for s in starts:
        nodes = np.vstack([s.introducer, s.position])
        clearance, _ = tube_clearance(anatomy, nodes)
        assert clearance >= INTRODUCER_RADIUS - 2.5e-4
        # the proximal end lies beyond the exit plane, on the cap's axis side
        tail = s.introducer[0]
        assert float((tail - anatomy.exit_point) @ anatomy.exit_normal) == pytest.approx(
            0.005, abs=1e-9)
        assert np.linalg.norm(tail - 0.005 * anatomy.exit_normal - anatomy.exit_point) < \
            _cap_radius(anatomy) - INTRODUCER_RADIUS
        # the nodes advance towards the start without turning back
        seg = np.diff(nodes, axis=0)
        assert np.all(np.linalg.norm(seg, axis=1) > 0)
        heads = seg / np.linalg.norm(seg, axis=1)[:, None]
        assert np.all(np.einsum("ij,ij->i", heads[1:], heads[:-1]) > 0.9)
    # a start's bent introducer follows the centerline: every node but the proximal end lies
    # within a millimetre of it
    cl = curved.centerlines["left"].points
    inner = starts[2].introducer[1:]
    assert np.min(np.linalg.norm(cl[None] - inner[:, None], axis=2), axis=1).max() < 1e-3


def test_a_start_with_no_introducer_inside_the_lumen_is_refused(curved) -> None:
    with pytest.raises(ScenarioError, match=(
            r"anatomy 'curved', start 0 \(0 mm above start 0\): expected an introducer inside "
            r"the lumen \(a 30.0 mm tube .*\), found the straight one: its axis comes within "
            r".* mm of the wall .*; the one along the centerline: its axis comes within")):
        build_starts(curved.anatomy, curved.centerlines["left"], introducer_radius=0.015)


def test_world_introducer_behind_any_pose(curved) -> None:
    """A pose near start 2 gets an introducer along the centerline too; a pose outside the
    lumen gets none."""
    s = curved.scenarios.starts[2]
    p = s.position + np.array([0.0005, 0.0, 0.0])
    intro = curved.introducer(p, s.rotation)
    assert len(intro) > 1
    assert tube_clearance(curved.anatomy, np.vstack([intro, p]))[0] >= INTRODUCER_RADIUS - 2.5e-4
    with pytest.raises(ScenarioError, match="expected an introducer inside the lumen"):
        curved.introducer(s.position + np.array([0.0, 0.0, 0.0]) + 0.02 * s.rotation[:, 0],
                          s.rotation)

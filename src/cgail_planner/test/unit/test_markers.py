"""Marker geometry (core/markers.py): lumen triangles and decimation, the deformed wall, the
catheter body, the planner's markers and the suggested-bend arc, exact where it can be."""

import math

import numpy as np
import pytest

from cgail_planner.core import markers as mk
from cgail_planner.core.guidance import suggested_bend
from cgail_sim.anatomy_spec import resolve_anatomy
from cgail_sim.ftl_model import CatheterBatch, CatheterConfig

EYE = np.eye(3)


@pytest.fixture(scope='module')
def anatomy():
    return resolve_anatomy('default')


def test_lumen_is_every_wall_triangle_of_the_rest_wall(anatomy) -> None:
    lumen = mk.LumenMesh(anatomy)
    wall_faces = anatomy.faces[anatomy.wall_face_mask]
    assert not lumen.decimated
    # (the remeshed built-in's size differs in the last bits between numpy's SIMD paths:
    # 4783 wall faces on AVX-512, 4793 on AVX2; never a constant here)
    assert lumen.faces.shape == wall_faces.shape and 4000 < len(wall_faces) < 6000
    m = lumen.marker(anatomy.vertices)
    assert (m.ns, m.id, m.kind, m.scale) == ('lumen', 0, 'triangle_list', (1.0, 1.0, 1.0))
    assert m.points.shape == (3 * len(wall_faces), 3)
    assert np.array_equal(m.points, anatomy.vertices[wall_faces.reshape(-1)])


def test_lumen_is_decimated_onto_its_own_vertices(anatomy) -> None:
    lumen = mk.LumenMesh(anatomy, max_triangles=2000)
    assert lumen.decimated
    assert 1900 <= len(lumen.faces) <= 2000
    f = lumen.faces
    assert not ((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])).any()
    # a subset of the original vertices: a deformed wall is drawn by indexing its vertices
    assert set(np.unique(f)) <= set(np.unique(anatomy.faces[anatomy.wall_face_mask]))
    # the collapses keep a consistent winding: no directed edge is used twice
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len(np.unique(edges, axis=0)) == len(edges)
    # the same mesh decimates the same way; a budget above the face count changes nothing
    assert np.array_equal(mk.LumenMesh(anatomy, max_triangles=2000).faces, f)
    assert np.array_equal(mk.decimate_faces(anatomy.vertices, f, 2000), f)


def test_the_deformed_wall_moves_the_lumen_between_two_phases(anatomy) -> None:
    from cgail_sim.wall import DeformableWall

    wall = DeformableWall(anatomy)
    lumen = mk.LumenMesh(anatomy)
    rest = lumen.marker(wall.vertices).points
    frames = []
    t, dt = 0.0, 0.02
    for phase in (0.2, 0.45):  # s into the 0.857 s heartbeat
        while t < phase - 1e-9:
            t += dt
            wall.step(t, dt, np.zeros((0, 3)), 0.0)
        frames.append(lumen.marker(wall.vertices).points)
    moved = np.linalg.norm(frames[1] - frames[0], axis=1)
    assert moved.max() > 1e-3                          # the root moves by millimetres
    assert np.median(moved) < 1e-3                     # the descending aorta barely
    assert np.linalg.norm(frames[0] - rest, axis=1).max() > 1e-3
    assert frames[0].shape == rest.shape               # one topology, vertices move


def test_index_triangles_inverts_the_triangle_list(anatomy) -> None:
    points = mk.LumenMesh(anatomy).marker(anatomy.vertices).points
    vertices, faces, first = mk.index_triangles(points)
    assert faces.shape == (len(points) // 3, 3)
    assert np.array_equal(vertices[faces].reshape(-1, 3), points)
    assert np.array_equal(points[first], vertices)
    assert np.all(np.diff(first) > 0)                  # numbered by first appearance
    assert len(vertices) == len(np.unique(anatomy.faces[anatomy.wall_face_mask]))
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
    v, f, first = mk.index_triangles(tri)
    assert f.tolist() == [[0, 1, 2], [1, 3, 2]] and first.tolist() == [0, 1, 2, 4]
    assert v.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
    with pytest.raises(ValueError, match='3 per triangle, found 4'):
        mk.index_triangles(tri[:4])


def test_body_is_the_catheter_models_chain() -> None:
    cat = CatheterBatch(1, CatheterConfig(), capacity=64)
    cat.reset_env(0, np.array([0.0, 0.01, 0.0]), EYE, np.array([0.0, -0.01, 0.0]))
    m = mk.body_marker(cat, 0, spacing=0.001)
    assert (m.ns, m.id, m.kind, m.scale) == ('catheter_body', 0, 'line_strip', (0.007, 0.0, 0.0))
    assert np.array_equal(m.points, cat.body_points(0, 0.001))
    assert m.points[0] == pytest.approx([0.0, -0.01, 0.0])
    assert m.points[-1] == pytest.approx([0.0, 0.01, 0.0])    # tip last


@pytest.mark.parametrize('theta', [0.05, 0.3, 0.6])
def test_the_bend_arc_reaches_the_waypoint(theta) -> None:
    """Holding the suggested (uncapped) bend over the arc length s = d theta / sin(theta)
    brings the tip onto the waypoint (guidance's constant-curvature arc)."""
    d = 0.05
    wp = np.array([-d * math.sin(theta), d * math.cos(theta), 0.0])
    cat = CatheterConfig()
    alpha, gamma, _ = suggested_bend(np.zeros(3), EYE, wp, cat.segment_length, cat.theta_max)
    assert math.hypot(alpha, gamma) < cat.theta_max
    s = d * theta / math.sin(theta)
    arc, r_end = mk.bend_arc(np.zeros(3), EYE, (alpha, gamma), s, cat, 400)
    assert arc.shape == (401, 3)
    assert arc[0] == pytest.approx([0.0, 0.0, 0.0])
    assert np.linalg.norm(arc[-1] - wp) < 1e-4        # (400 steps of the discrete model)
    turned = math.acos(float(np.clip(r_end[:, 1] @ EYE[:, 1], -1.0, 1.0)))
    assert turned == pytest.approx(2.0 * theta, abs=1e-3)


def test_planner_markers_namespaces_ids_and_kinds() -> None:
    cfg = mk.MarkerConfig()
    cat = CatheterConfig()
    path = np.column_stack([np.zeros(5), np.linspace(0.0, 0.04, 5), np.zeros(5)])
    guide = mk.TipGuidance(np.zeros(3), EYE, np.array([0.0, 0.025, 0.0]), (0.0, 0.0), 0.025)
    ms = mk.planner_markers(cfg, cat, goal=np.array([0.0, 0.04, 0.0]), goal_radius=0.01,
                            path=path, guidance=guide)
    assert mk.namespaces(ms) == [('target', 0, 'sphere'), ('path', 0, 'line_strip'),
                                 ('next_waypoint', 0, 'sphere'),
                                 ('suggested_bend', 0, 'line_strip'),
                                 ('suggested_bend', 1, 'arrow')]
    assert ms[0].scale == (0.02, 0.02, 0.02) and ms[0].points.tolist() == [[0.0, 0.04, 0.0]]
    assert np.array_equal(ms[1].points, path)
    # no bend: a straight arc of 25 mm and an arrow of 5 mm along the heading
    assert ms[3].points[-1] == pytest.approx([0.0, 0.025, 0.0])
    assert ms[4].points == pytest.approx(np.array([[0.0, 0.025, 0.0], [0.0, 0.030, 0.0]]))
    assert mk.planner_markers(cfg, cat, goal=None, goal_radius=0.01, path=None,
                              guidance=None) == []


def test_phantom_markers(anatomy) -> None:
    cat = CatheterBatch(1, CatheterConfig(), capacity=64)
    cat.reset_env(0, np.array([0.0, 0.01, 0.0]), EYE, np.array([0.0, -0.01, 0.0]))
    ms = mk.phantom_markers(mk.LumenMesh(anatomy), anatomy.vertices, cat, mk.MarkerConfig())
    assert mk.namespaces(ms) == [('lumen', 0, 'triangle_list'), ('catheter_body', 0, 'line_strip')]
    assert mk.namespaces(mk.phantom_markers(mk.LumenMesh(anatomy), anatomy.vertices, None,
                                            mk.MarkerConfig())) == [('lumen', 0, 'triangle_list')]
    n = len(anatomy.vertices)
    with pytest.raises(ValueError, match=rf'vertices must have shape \({n}, 3\), found \(3, 3\)'):
        mk.LumenMesh(anatomy).marker(np.zeros((3, 3)))


@pytest.mark.parametrize(('kwargs', 'match'), [
    (dict(kind='cube', points=np.zeros((1, 3))), "kind must be one of"),
    (dict(kind='sphere', points=np.zeros((2, 3))), 'a sphere marker needs 1 points, found 2'),
    (dict(kind='line_strip', points=np.zeros((1, 3))),
     'a line_strip marker needs 2 or more points, found 1'),
    (dict(kind='triangle_list', points=np.zeros((4, 3))),
     r'a triangle_list marker needs 3 or more points \(3 per triangle\), found 4'),
    (dict(kind='arrow', points=np.full((2, 3), np.nan)), 'points must be finite'),
])
def test_bad_geometry_is_refused(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        mk.MarkerGeometry(ns='x', id=0, scale=(1.0, 1.0, 1.0), color=(1.0, 1.0, 1.0, 1.0),
                          **kwargs)


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('max_triangles', 50, r'max_triangles must be an int in \[100, 100000\], found 50'),
    ('body_spacing', 0.0, r'body_spacing must be in \[0.0001, 0.01\], found 0.0'),
    ('line_width', -1.0, r'line_width must be in \(0.0, 0.01\], found -1.0'),
])
def test_bad_config_is_refused(field, value, match) -> None:
    with pytest.raises(ValueError, match=match):
        mk.MarkerConfig(**{field: value})


def test_refilled_guidance_messages_equal_new_ones() -> None:
    # the planner node refills its per-pose messages and guidance markers (conversions' out=)
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header

    from cgail_planner.nodes import conversions as conv

    cat = CatheterConfig()
    cfg = mk.MarkerConfig()
    outs: dict[tuple[str, int, str], object] = {}
    point_out = bend_out = None
    for k, bend in enumerate(((0.1, -0.2), (-0.3, 0.05))):
        header = Header(stamp=Time(sec=k, nanosec=7), frame_id='phantom')
        p = np.array([0.01 * k, 0.02, -0.01])
        geometries = [mk.waypoint_marker(p, cfg.waypoint_diameter),
                      *mk.bend_markers(p, np.eye(3), bend, 0.02 + 0.01 * k, cat, cfg)]
        for g in geometries:
            key = (g.ns, g.id, g.kind)
            outs[key] = conv.marker_msg(header, g, out=outs.get(key))
            assert outs[key] == conv.marker_msg(header, g)
        point_out = conv.point_msg(header.stamp, 'phantom', p, out=point_out)
        assert point_out == conv.point_msg(header.stamp, 'phantom', p)
        bend_out = conv.bend_msg(header.stamp, *bend, out=bend_out)
        assert bend_out == conv.bend_msg(header.stamp, *bend)

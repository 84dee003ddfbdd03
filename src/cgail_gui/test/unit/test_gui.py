"""cgail_gui pure parts: guidance maths, state coalescing, protocol, static table."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cgail_gui.config import GuiConfig
from cgail_gui.errors import ProtocolError
from cgail_gui.guidance import bend_on_screen, off_heading, ray_directions
from cgail_gui.model import GuiModel, TrialClock
from cgail_gui.protocol import parse_client_message
from cgail_gui.state import GuiState
from cgail_gui.static import build_table, lookup, VENDOR
from cgail_planner.core.rotations import quaternion_to_matrix


def test_quaternion_and_bend_geometry() -> None:
    s = math.sqrt(0.5)
    r = quaternion_to_matrix([0.0, 0.0, s, s])          # 90 deg about z: heading y -> -x
    np.testing.assert_allclose(r[:, 1], [-1.0, 0.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match=r'unit quaternion.*norm 2'):
        quaternion_to_matrix([0.0, 0.0, 0.0, 2.0])
    assert off_heading(np.array([1.0, 1.0, 0.0])) == pytest.approx((math.pi / 4, 1.0, 0.0))
    assert bend_on_screen(0.0, -0.3) == pytest.approx((0.3, 1.0, 0.0))     # right
    assert bend_on_screen(0.2, 0.0) == pytest.approx((0.2, 0.0, 1.0))      # up
    mag, x, y = bend_on_screen(0.3, 0.4)
    assert mag == pytest.approx(math.acos(math.cos(0.3) * math.cos(0.4)))
    lx, ly = -math.sin(0.4), math.cos(0.4) * math.sin(0.3)
    assert (x, y) == pytest.approx((lx / math.hypot(lx, ly), ly / math.hypot(lx, ly)))
    dirs = ray_directions(np.eye(3), 4, math.radians(30))
    np.testing.assert_allclose(dirs[0], [0, 1, 0])
    np.testing.assert_allclose(dirs[1], [0.5, math.cos(math.radians(30)), 0], atol=1e-12)


def test_state_coalesces_and_full_state_for_new_pages() -> None:
    state = GuiState()
    state.set('tip', {'seq': 1})
    state.set('path', {'points': []})
    items, sent = state.changes_since({})
    assert list(items) == ['path', 'tip']
    for k in range(2, 6):
        state.set('tip', {'seq': k})
    items, sent = state.changes_since(sent)
    assert items == {'tip': {'seq': 5}}                  # four updates -> one, the newest
    assert state.changes_since(sent)[0] == {}
    with pytest.raises(ValueError, match='item must be one of'):
        state.set('nope', 1)


def test_trial_clock_arms_runs_reaches_and_times_out() -> None:
    c = TrialClock(limit_s=180.0)
    c.update(0.0, np.zeros(3))
    c.update(1.0, np.array([0.001, 0, 0]))
    assert c.phase == 'armed'
    c.update(2.0, np.array([0.003, 0, 0]))
    assert c.phase == 'running'
    c.update(12.0, np.array([0.05, 0, 0]), dist_target=0.005, success_radius=0.01)
    assert (c.phase, c.elapsed_s) == ('reached', 10.0)
    c.start(0.0)
    c.update(500.0)
    assert (c.phase, c.elapsed_s) == ('timeout', 180.0)


def test_model_guide_from_tip_target_and_waypoint() -> None:
    state = GuiState()
    model = GuiModel(GuiConfig(), state)
    model.on_goal(np.array([0.0, 0.05, 0.0]), 'phantom')
    model.on_waypoint(np.array([0.0, 0.01, 0.01]))
    model.on_tip(np.zeros(3), np.array([0, 0, 0, 1.0]), 0.0, 0.0)
    guide = state.get('guide')
    assert guide['dist_target'] == pytest.approx(0.05)
    assert guide['waypoint']['angle'] == pytest.approx(math.pi / 4, abs=1e-6)
    assert guide['waypoint']['screen'] == pytest.approx([0.0, 1.0])
    with pytest.raises(ValueError, match='tip position'):
        model.on_tip(np.array([np.nan, 0, 0]), np.array([0, 0, 0, 1.0]), 0.0, 0.0)


def _box(half: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed cube around the origin (inward-facing does not matter to the rays)."""
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return v, f


def test_model_draws_and_raycasts_the_wall_from_a_triangle_list() -> None:
    import base64

    state = GuiState()
    model = GuiModel(GuiConfig(anatomy=''), state)
    v, f = _box(0.02)
    model.set_anatomy('rest', v * 2.0, f, None)            # a rest mesh first
    model.on_tip(np.zeros(3), np.array([0, 0, 0, 1.0]), 0.0, 0.0)
    model.set_lumen(v[f].reshape(-1, 3), 1.0)              # the phantom's lumen arrives
    mesh = state.get('mesh')
    assert (mesh['name'], mesh['vertex_count'], mesh['face_count']) == ('lumen', 8, 12)
    model.on_tip(np.zeros(3), np.array([0, 0, 0, 1.0]), 0.0, 0.0)
    assert state.get('guide')['wall_ahead'] == pytest.approx(0.02)   # rays hit the lumen
    # the same topology, moved: a deform frame (no new mesh), the rays follow it
    version = state.changes_since({})[1]['mesh']
    model.set_lumen((v * 1.5)[f].reshape(-1, 3), 1.2)
    assert state.changes_since({})[1]['mesh'] == version
    deform = state.get('deform')
    assert deform['t'] == 1.2
    got = np.frombuffer(base64.b64decode(deform['vertices']), '<f4').reshape(-1, 3)
    order = np.frombuffer(base64.b64decode(mesh['vertices']), '<f4').reshape(-1, 3)
    assert got == pytest.approx(order * 1.5)
    model.on_tip(np.zeros(3), np.array([0, 0, 0, 1.0]), 0.0, 0.0)
    assert state.get('guide')['wall_ahead'] == pytest.approx(0.03)
    model.set_anatomy('rest', v * 2.0, f, None)            # the rest mesh no longer wins
    assert state.get('mesh')['vertex_count'] == 8 and state.get('mesh')['name'] == 'lumen'
    # another topology is indexed again
    model.set_lumen(v[f[:6]].reshape(-1, 3), 1.4)
    assert state.get('mesh')['face_count'] == 6
    with pytest.raises(ValueError, match='3 per triangle, found 4'):
        model.set_lumen(np.zeros((4, 3)), 1.5)


@pytest.mark.parametrize('text, match', [
    ('nope', 'expected JSON'), ('[]', 'JSON object'), ('{"type": 1}', 'expected type'),
    ('{"type": "trial"}', 'trial action'), ('{"type": "replay", "action": "go"}', 'replay action'),
    ('{"type": "replay", "action": "start", "bag": "a", "rate": 0}', 'rate'),
    ('{"type": "replay", "action": "start", "bag": "a", "loop": 1}', 'loop'),
])
def test_protocol_rejects_bad_messages(text: str, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        parse_client_message(text)


def test_protocol_accepts_commands() -> None:
    c = parse_client_message('{"type": "replay", "action": "start", "bag": "a/b", "rate": 2}')
    assert (c.kind, c.action, c.bag, c.rate, c.loop) == ('replay', 'start', 'a/b', 2.0, False)
    assert parse_client_message('{"type": "ack"}').kind == 'ack'


def test_static_table_is_exact(tmp_path: Path) -> None:
    (tmp_path / 'index.html').write_text('<p>')
    (tmp_path / 'app.js').write_text('1')
    (tmp_path / 'secret.txt').write_text('no')
    (tmp_path / 'sub').mkdir()
    (tmp_path / 'sub' / 'x.js').write_text('no')
    (tmp_path / '.hidden.js').write_text('no')
    (tmp_path / 'linked.css').symlink_to(tmp_path / 'sub' / 'x.js')   # symlink install
    table = build_table(tmp_path)
    assert sorted(table) == ['/', '/app.js', '/index.html', '/linked.css']
    assert lookup(table, '/app.js?x=1') is not None
    for bad in ('/../app.js', '/sub/x.js', '/secret.txt', '/.hidden.js', 'app.js',
                '/sub/../app.js'):
        assert lookup(table, bad) is None
    assert not set(VENDOR) & set(table)


def test_config_validation() -> None:
    with pytest.raises(ValueError, match='host must be'):
        GuiConfig(host='localhost')
    with pytest.raises(ValueError, match='port must be'):
        GuiConfig(port=-1)
    with pytest.raises(ValueError, match='max_bend_rad'):
        GuiConfig(max_bend_rad=2.0)
    assert GuiConfig(host='::1', port=9).url == 'http://[::1]:9/'

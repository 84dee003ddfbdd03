"""The RViz2 config and the Foxglove layout parse, show frame phantom, and name only topics that
a node publishes (docs/interfaces.md contract) with the publisher's type and QoS; setup.py
installs both."""

import json
from pathlib import Path
import re

import pytest
import yaml

PKG = Path(__file__).resolve().parents[2]
REPO = PKG.parents[1]
RVIZ = PKG / 'config' / 'rviz' / 'cgail.rviz'
FOXGLOVE = PKG / 'config' / 'foxglove' / 'cgail_layout.json'
SHOWN = {'/phantom/lumen', '/phantom/markers', '/planner/markers', '/em_tracker/tip_pose'}
RVIZ_TYPES = {'rviz_default_plugins/MarkerArray': 'visualization_msgs/msg/MarkerArray',
              'rviz_default_plugins/Pose': 'geometry_msgs/msg/PoseStamped'}


def published() -> dict[str, tuple[str, str]]:
    """Absolute rig topic -> (type, QoS name) over every node's contract (a node's own
    ``~/name`` under the rig name its ``remaps`` give it)."""
    text = (REPO / 'docs' / 'interfaces.md').read_text()
    out = {}
    for block in re.findall(r'```contract\n(.*?)```', text, re.S):
        contract = yaml.safe_load(block)
        remaps = contract.get('remaps') or {}
        for topic, spec in (contract['publishes'] or {}).items():
            msg_type, qos = re.match(r'([\w/]+)\s*\[(\w+)\]', spec).groups()
            out['/' + remaps.get(topic, topic).lstrip('/')] = (msg_type, qos)
    return out


def test_rviz_config_shows_the_markers_and_the_tip_in_phantom() -> None:
    config = yaml.safe_load(RVIZ.read_text())
    manager = config['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == 'phantom'
    topics = published()
    shown = {}
    for display in manager['Displays']:
        if 'Topic' not in display:
            continue
        name, qos = display['Topic']['Value'], display['Topic']
        shown[name] = display['Class']
        msg_type, contract_qos = topics[name]          # a topic some node publishes
        assert RVIZ_TYPES[display['Class']] == msg_type, name
        if contract_qos == 'latched':
            assert qos['Durability Policy'] == 'Transient Local', name
        if contract_qos == 'sensor':
            assert qos['Reliability Policy'] == 'Best Effort', name
    assert set(shown) == SHOWN


def test_rviz_marker_displays_list_the_namespaces_the_nodes_use() -> None:
    from cgail_planner.core import markers as mk

    displays = {d['Topic']['Value']: d for d in
                yaml.safe_load(RVIZ.read_text())['Visualization Manager']['Displays']
                if d['Class'] == 'rviz_default_plugins/MarkerArray'}
    assert set(displays['/phantom/lumen']['Namespaces']) == {mk.LUMEN_NS}
    assert set(displays['/phantom/markers']['Namespaces']) == {mk.BODY_NS}
    assert set(displays['/planner/markers']['Namespaces']) == {
        mk.TARGET_NS, mk.PATH_NS, mk.WAYPOINT_NS, mk.BEND_NS}


def _panels(tree: object) -> list[str]:
    """The panel ids of a Foxglove layout tree (a panel id, or a split of two trees)."""
    if isinstance(tree, str):
        return [tree]
    assert isinstance(tree, dict) and tree['direction'] in ('row', 'column'), tree
    return _panels(tree['first']) + _panels(tree['second'])


def test_foxglove_layout_is_the_3d_panel_the_pressures_and_the_diagnostics() -> None:
    """The 3D panel on the markers and the tip, a plot of the four PAM pressures and the
    diagnostics summary, each on a topic some node publishes with the type the panel reads,
    and each served live by foxglove_bridge (recorded bags hold the 3D panel's topics)."""
    from cgail_gui.core.foxglove_view import STREAMS

    layout = json.loads(FOXGLOVE.read_text())
    panels = _panels(layout['layout'])
    assert sorted(panels) == sorted(layout['configById'])
    assert [p.split('!')[0] for p in panels] == ['3D', 'Plot', 'DiagnosticSummary']
    panel = layout['configById'][panels[0]]
    assert panel['followTf'] == 'phantom'
    assert set(panel['topics']) == SHOWN
    assert set(panel['topics']) <= set(published())
    assert all(t['visible'] for t in panel['topics'].values())
    plot = layout['configById'][panels[1]]
    assert [p['value'] for p in plot['paths']] == [f'/pam/pressures.data[{i}]' for i in range(4)]
    assert [p['label'] for p in plot['paths']] == ['alpha_pos', 'alpha_neg', 'gamma_pos',
                                                   'gamma_neg']  # docs/interfaces.md's order
    assert published()['/pam/pressures'][0] == 'std_msgs/msg/Float64MultiArray'
    diagnostics = layout['configById'][panels[2]]['topicToRender']
    assert published()[diagnostics][0] == 'diagnostic_msgs/msg/DiagnosticArray'
    served = {'/' + (s.rig or s.own.lstrip('/')) for s in STREAMS}
    assert SHOWN | {'/pam/pressures', diagnostics} <= served


@pytest.mark.parametrize('path', [RVIZ, FOXGLOVE])
def test_setup_installs_the_view(path: Path) -> None:
    setup = (PKG / 'setup.py').read_text()
    rel = path.relative_to(PKG)
    pattern = f"glob('{rel.parent}/*{path.suffix}')"
    assert f"('share/' + PACKAGE + '/{rel.parent}', {pattern})" in setup

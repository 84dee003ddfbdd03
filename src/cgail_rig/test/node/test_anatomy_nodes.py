"""planner_node, phantom_node and gui_node take an anatomy as a name or a path (issue 12).

A prepared anatomy directory works like a built-in name; a bad one (no such path, a directory
that is not a prepared anatomy, a mesh that fails to load) fails construction with the
resolver's one line, and the console script prints it and exits with status 2. A policy
trained on a path anatomy is accepted where the anatomy has its content hash, whatever the
directory is called, and refused elsewhere with both identities.
"""

from __future__ import annotations

from pathlib import Path
import shutil
import time

import pytest
from rclpy.parameter import Parameter

from cgail_gui.nodes import gui_node
from cgail_gui.nodes.gui_node import GuiNode
from cgail_learning.export import default_contract, write_contract
from cgail_planner.core.errors import ContractError
from cgail_planner.nodes import planner_node
from cgail_planner.nodes.planner_node import PlannerNode
from cgail_rig.nodes import phantom_node
from cgail_rig.nodes.phantom_node import PhantomNode
from cgail_sim.anatomy import AnatomyError
from cgail_sim.anatomy_spec import resolve_anatomy

TEST = Path(__file__).resolve().parents[1]
POLICY = (TEST.parents[1] / 'cgail_planner' / 'cgail_planner' / 'models'
          / 'cgail_default_static.onnx')

NODES = {
    'planner_node': (PlannerNode, planner_node.main, dict(planner_type='centerline')),
    'phantom_node': (PhantomNode, phantom_node.main, {}),
    'gui_node': (GuiNode, gui_node.main, dict(port=0)),
}


def _overrides(params: dict) -> list[Parameter]:
    return [Parameter(k, value=v) for k, v in params.items()]


@pytest.mark.parametrize('name', sorted(NODES))
def test_a_bad_anatomy_fails_construction_in_one_line(ros, tmp_path, bad_anatomy,
                                                      name) -> None:
    cls, _, params = NODES[name]
    spec, text = bad_anatomy
    extra = dict(aurora_link=str(tmp_path / 'aurora')) if name == 'phantom_node' else {}
    with pytest.raises(AnatomyError) as info:
        cls(parameter_overrides=_overrides(params | extra | dict(anatomy=str(spec))))
    assert text in str(info.value) and '\n' not in str(info.value)


@pytest.mark.parametrize('name', sorted(NODES))
def test_the_console_script_prints_one_line_and_exits_2(capsys, bad_anatomy, name) -> None:
    _, main, params = NODES[name]
    spec, text = bad_anatomy
    args = ['--ros-args', '-p', f'anatomy:={spec}']
    for key, value in params.items():
        args += ['-p', f'{key}:={value}']
    with pytest.raises(SystemExit) as info:
        main(args)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f'{name}: error: ') and err.count('\n') == 1 and text in err, err


def test_phantom_and_planner_run_in_a_prepared_anatomy(ros, prepared, tmp_path) -> None:
    anatomy = resolve_anatomy(prepared)
    phantom = PhantomNode(parameter_overrides=_overrides(dict(
        anatomy=str(prepared), aurora_link=str(tmp_path / 'aurora'), simulate_regulators=False,
        simulate_driver=False, start_id=2, target_id=1)))
    planner = PlannerNode(parameter_overrides=_overrides(dict(
        anatomy=str(prepared), planner_type='centerline')))
    try:
        assert phantom.world.anatomy.content_hash == anatomy.content_hash
        assert phantom.anatomy_label == 'p07'
        start = phantom.world.scenarios.starts[2]
        assert phantom.physics.tip_position.tolist() == start.position.tolist()
        assert planner.planner is not None
        result = planner.planner.plan(start.position, start.rotation,
                                      phantom.target_position())
        assert len(result.path) > 100
    finally:
        phantom.destroy_node()
        planner.destroy_node()


def test_the_gui_draws_a_prepared_anatomy(ros, prepared) -> None:
    node = GuiNode(parameter_overrides=_overrides(dict(anatomy=str(prepared), port=0)))
    try:
        deadline = time.monotonic() + 30.0
        while getattr(node, '_anatomy', None) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert node._anatomy[0] == 'p07'
        assert len(node._anatomy[1]) == len(resolve_anatomy(prepared).vertices)
    finally:
        node.destroy_node()


@pytest.fixture(scope='module')
def p07_policy(prepared, tmp_path_factory) -> Path:
    """The committed default policy re-contracted as trained on the prepared ``p07``."""
    out = tmp_path_factory.mktemp('policies') / 'cgail_p07_static.onnx'
    return write_contract(POLICY, default_contract(prepared, 'static'), out)


def test_a_path_trained_policy_runs_where_its_anatomy_content_is(ros, prepared, p07_policy,
                                                                 tmp_path) -> None:
    copy = tmp_path / 'renamed'
    shutil.copytree(prepared, copy)
    for anatomy in (prepared, copy):
        node = PlannerNode(parameter_overrides=_overrides(dict(
            anatomy=str(anatomy), policy_path=str(p07_policy))))
        try:
            assert node.planner is not None and node.contract_notes == []
        finally:
            node.destroy_node()


def test_a_policy_and_an_anatomy_that_differ_are_refused_with_both_identities(
        ros, prepared, p07_policy) -> None:
    h = resolve_anatomy(prepared).content_hash
    with pytest.raises(ContractError, match=(
            rf"^anatomy: expected the policy's 'p07' \(content hash {h}\), found parameter "
            r"built-in 'default' \(set override_policy_contract to run anyway\)$")):
        PlannerNode(parameter_overrides=_overrides(dict(anatomy='default',
                                                        policy_path=str(p07_policy))))
    with pytest.raises(ContractError, match=(
            rf"^anatomy: expected the policy's built-in 'default', found parameter 'p07' "
            rf"\(content hash {h}\) ")):
        PlannerNode(parameter_overrides=_overrides(dict(anatomy=str(prepared),
                                                        policy_path=str(POLICY))))

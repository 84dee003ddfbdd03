"""planner_node builds itself from the policy's contract and refuses parameters that disagree.

The committed C-GAIL policy carries its contract (theta_max 90 deg, L 50 mm, the default
anatomy's observation frame). A parameter that repeats a contract entry with another value
makes construction fail in one line naming the parameter, the policy's value and the
parameter's, unless ``override_policy_contract`` is set: then the parameter wins and the node
notes (logs) a warning. A policy without a contract is refused unless overridden.
"""

from __future__ import annotations

import math
from pathlib import Path

import onnx
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter

from cgail_planner.core.errors import ContractError
from cgail_planner.nodes.planner_node import PlannerNode
from cgail_sim.ftl_model import CatheterConfig, CONTRACT_KEY

TEST = Path(__file__).resolve().parents[1]
PLANNER = TEST.parents[1] / 'cgail_planner'
POLICY = str(PLANNER / 'cgail_planner' / 'models' / 'cgail_default_static.onnx')


@pytest.fixture
def ros():
    """An rclpy context of this test's own; every node of the test is built in it."""
    context = Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


def planner_node(context: Context, **params) -> PlannerNode:
    return PlannerNode(context=context,
                       parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


def test_the_planner_takes_its_model_from_the_policy(ros) -> None:
    node = planner_node(ros, policy_path=POLICY)
    try:
        assert node.planner is not None and node.contract_notes == []
        contract = node.planner.policy.contract
        assert node.config.catheter == contract.catheter == CatheterConfig()
        assert node.planner.spec.same_as(contract.observation)
        assert node.guidance_config.segment_length == contract.catheter.segment_length
    finally:
        node.destroy_node()


def test_parameters_that_agree_with_the_contract_are_accepted(ros) -> None:
    node = planner_node(ros, policy_path=POLICY, theta_max=math.pi / 2, segment_length=0.05)
    try:
        assert node.planner is not None and node.contract_notes == []
    finally:
        node.destroy_node()


@pytest.mark.parametrize(('params', 'match'), [
    (dict(theta_max=math.radians(60)),
     r"^theta_max: expected the policy's 1\.5708, found parameter 1\.0472 "
     r"\(set override_policy_contract to run anyway\)$"),
    (dict(segment_length=0.04),
     r"^segment_length: expected the policy's 0\.05, found parameter 0\.04 "),
    (dict(anatomy='elongated'),
     r"^anatomy: expected the policy's 'default', found parameter 'elongated' "),
])
def test_a_parameter_that_disagrees_with_the_contract_is_refused(ros, params, match) -> None:
    with pytest.raises(ContractError, match=match) as info:
        planner_node(ros, policy_path=POLICY, **params)
    assert '\n' not in str(info.value)


def test_an_explicit_override_runs_with_the_parameter_and_warns(ros) -> None:
    node = planner_node(ros, policy_path=POLICY, theta_max=math.radians(60),
                        override_policy_contract=True)
    try:
        assert node.planner is not None
        assert node.config.catheter.theta_max == pytest.approx(math.radians(60), abs=0)
        assert node.planner.config.catheter.segment_length == 0.05  # the policy's
        assert node.contract_notes == [
            "override_policy_contract: theta_max 1.0472 instead of the policy's 1.5708"]
    finally:
        node.destroy_node()


def test_a_static_policy_may_plan_in_the_beating_world(ros) -> None:
    node = planner_node(ros, policy_path=POLICY, mode='dynamic')
    try:
        assert node.planner is not None
        assert node.contract_notes == ['policy trained in the static world runs in the '
                                       'dynamic world']
    finally:
        node.destroy_node()


@pytest.fixture
def no_contract(tmp_path: Path) -> str:
    """The straight fixture policy with its contract removed."""
    model = onnx.load(str(PLANNER / 'test' / 'fixtures' / 'straight_policy.onnx'))
    kept = [(p.key, p.value) for p in model.metadata_props if p.key != CONTRACT_KEY]
    del model.metadata_props[:]
    for key, value in kept:
        prop = model.metadata_props.add()
        prop.key, prop.value = key, value
    path = tmp_path / 'no_contract.onnx'
    onnx.save(model, str(path))
    return str(path)


def test_a_policy_without_a_contract_is_refused_unless_overridden(ros, no_contract) -> None:
    node = planner_node(ros, policy_path=no_contract)
    try:
        assert node.planner is None
        assert 'carries no catheter contract' in node.policy_error
        assert node.diagnostics().status[0].message == node.policy_error
    finally:
        node.destroy_node()
    node = planner_node(ros, policy_path=no_contract, override_policy_contract=True,
                        theta_max=1.2)
    try:
        assert node.planner is not None and node.config.catheter.theta_max == 1.2
        assert node.contract_notes[0].startswith('override_policy_contract: ')
    finally:
        node.destroy_node()


def test_a_population_policy_plans_in_any_anatomy_in_its_frame(ros, tmp_path: Path) -> None:
    """A generalist's contract (anatomies: population; here the committed policy's contract so
    marked, selected in a population sample): the node takes it in `elongated` without an
    override, observes in elongated's frame with the sphere targets' d_max, and says so."""
    import dataclasses

    from cgail_learning.export import write_contract
    from cgail_planner.core.onnx_policy import OnnxPolicy
    from cgail_sim.worlds import load_world

    contract = dataclasses.replace(OnnxPolicy(POLICY).contract, anatomy='population-128',
                                   anatomy_hash='0123456789abcdef', anatomies='population',
                                   env_options='sphere_targets')
    path = write_contract(Path(POLICY), contract, tmp_path / 'generalist.onnx')
    node = planner_node(ros, policy_path=str(path), anatomy='elongated')
    try:
        assert node.planner is not None
        sc = load_world('elongated').scenarios
        assert node.planner.spec.d_max == sc.d_max_for('sphere')
        assert node.planner.spec.origin.tolist() == sc.origin.tolist()
        assert len(node.contract_notes) == 1 and node.contract_notes[0].startswith(
            "population policy (trained across the anatomy population) runs in built-in "
            "'elongated', observed in its frame")
    finally:
        node.destroy_node()

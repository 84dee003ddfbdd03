"""The YAML parameter files of the planner's nodes hold exactly the declared defaults
(``config/planner.yaml``, ``config/operator.yaml``,
``config/autonomy.yaml``; the phantom's file is cgail_rig's test)."""

import importlib
from pathlib import Path

import pytest
import yaml

CONFIG = Path(__file__).resolve().parents[2] / 'config'


@pytest.mark.parametrize(('cls_path', 'yaml_name'), [
    ('cgail_planner.nodes.planner_node:PlannerNode', 'planner.yaml'),
    ('cgail_planner.nodes.operator_node:OperatorNode', 'operator.yaml'),
    ('cgail_planner.nodes.autonomy_node:AutonomyNode', 'autonomy.yaml'),
])
def test_yaml_defaults_equal_the_declared_defaults(ros, cls_path, yaml_name) -> None:
    module, name = cls_path.split(':')
    params = next(iter(yaml.safe_load((CONFIG / yaml_name).read_text()).values()))
    params = params['ros__parameters']
    node = getattr(importlib.import_module(module), name)()
    try:
        declared = {n: node.get_parameter(n).value for n in node._parameters
                    if n not in ('use_sim_time', 'start_type_description_service')}
        assert set(declared) == set(params)
        for key, value in params.items():
            assert declared[key] == pytest.approx(value), key
    finally:
        node.destroy_node()

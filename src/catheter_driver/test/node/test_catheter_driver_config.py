"""config/*.yaml hold exactly the nodes' declared parameters with their default values."""

from pathlib import Path

import pytest
import yaml

from catheter_driver.hw.gamepad import FakeGamepadFactory
from catheter_driver.nodes.driver_node import DriverNode
from catheter_driver.nodes.joy_node import JoyNode
from catheter_driver.nodes.teleop_node import TeleopNode

CONFIG = Path(__file__).resolve().parents[2] / 'config'


@pytest.mark.parametrize(('file', 'factory'), [
    ('driver.yaml', lambda: DriverNode(parameter_overrides=[])),
    ('joy.yaml', lambda: JoyNode(gamepad_factory=FakeGamepadFactory(None))),
    ('teleop.yaml', TeleopNode),
])
def test_yaml_equals_declared_defaults(harness, file, factory):
    node = harness.add(factory())
    data = yaml.safe_load((CONFIG / file).read_text())
    params = data[node.get_name()]['ros__parameters']
    automatic = {'use_sim_time', 'start_type_description_service'}
    declared = {name: node.get_parameter(name).value for name in node._parameters
                if name not in automatic}
    assert sorted(params) == sorted(declared)
    for name, value in declared.items():
        assert params[name] == (pytest.approx(value) if isinstance(value, float) else value), name

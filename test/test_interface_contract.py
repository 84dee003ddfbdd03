"""Hold every node to the contract tables in docs/interfaces.md.

Each ```contract block names a node, its package/executable, and the exact set of topics it
publishes and subscribes (with message types) and the services it offers. The test builds the
node in-process (its class is the rclpy Node subclass defined in ``<pkg>.nodes.<executable>``),
configures and activates it when it is a lifecycle node, and compares the ROS graph's view of
the node with the table. Parameter/housekeeping endpoints that every rclpy node has
(``/parameter_events``, ``/rosout``, ``~/get_parameters``... and lifecycle services) are ignored.
"""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path
import re

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
CONTRACT_RE = re.compile(r'```contract\n(.*?)```', re.S)
TYPE_RE = re.compile(r'^\s*([\w/]+)\s*(?:\[(\w+)\])?\s*$')
QOS_NAMES = {'sensor', 'command', 'latched', 'diagnostics', 'tf'}
IGNORED_TOPICS = {'/parameter_events', '/rosout'}
IGNORED_TOPIC_SUFFIXES = ('/transition_event',)  # lifecycle nodes publish it
IGNORED_SERVICE_SUFFIXES = (
    'describe_parameters', 'get_parameter_types', 'get_parameters', 'list_parameters',
    'set_parameters', 'set_parameters_atomically', 'get_type_description',
    'change_state', 'get_state', 'get_available_states', 'get_available_transitions',
    'get_transition_graph',
)


def load_contracts() -> list[dict]:
    text = (ROOT / 'docs' / 'interfaces.md').read_text()
    blocks = [yaml.safe_load(b) for b in CONTRACT_RE.findall(text)]
    assert blocks, 'docs/interfaces.md has no contract blocks'
    return blocks


def parse_endpoints(section: dict | None) -> dict[str, tuple[str, str | None]]:
    out = {}
    for name, spec in (section or {}).items():
        m = TYPE_RE.match(str(spec))
        assert m, f'bad contract entry {name}: {spec!r}'
        msg_type, qos = m.group(1), m.group(2)
        assert qos is None or qos in QOS_NAMES, f'{name}: unknown QoS {qos!r}'
        out[name] = (msg_type, qos)
    return out


def test_contract_blocks_are_well_formed():
    names = set()
    for block in load_contracts():
        for key in ('node', 'package', 'executable', 'publishes', 'subscribes', 'services'):
            assert key in block, f'contract of {block.get("node")} lacks {key!r}'
        assert block['node'] not in names
        names.add(block['node'])
        parse_endpoints(block['publishes'])
        parse_endpoints(block['subscribes'])
        setup_py = (ROOT / 'src' / block['package'] / 'setup.py').read_text()
        assert f"'{block['executable']} = " in setup_py, \
            f'{block["executable"]} is not a console script of {block["package"]}'


def _node_class(package: str, executable: str):
    from rclpy.node import Node

    module = importlib.import_module(f'{package}.nodes.{executable}')
    classes = [c for _, c in inspect.getmembers(module, inspect.isclass)
               if issubclass(c, Node) and c.__module__ == module.__name__]
    assert len(classes) == 1, f'{module.__name__} should define exactly one Node class'
    return classes[0]


def _resolve(node, name: str) -> str:
    return name if name.startswith('/') else f'/{name}'


@pytest.mark.parametrize('contract', load_contracts(), ids=lambda c: c['node'])
@pytest.mark.usefixtures('rclpy_context')
def test_node_matches_contract(contract):
    from rclpy.parameter import Parameter

    try:
        cls = _node_class(contract['package'], contract['executable'])
    except ModuleNotFoundError as exc:
        pytest.fail(f'node {contract["node"]} is in the contract but not implemented: {exc}')
    overrides = contract.get('test_parameters') or {}  # e.g. a free port instead of a fixed one
    node = cls(parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()]) \
        if overrides else cls()
    try:
        if hasattr(node, 'trigger_configure'):
            node.trigger_configure()
            node.trigger_activate()
        assert node.get_name() == contract['node']
        name, ns = node.get_name(), node.get_namespace()
        pubs = {t: types for t, types in
                node.get_publisher_names_and_types_by_node(name, ns)
                if t not in IGNORED_TOPICS and not t.endswith(IGNORED_TOPIC_SUFFIXES)}
        subs = {t: types for t, types in
                node.get_subscriber_names_and_types_by_node(name, ns)
                if t not in IGNORED_TOPICS}
        srvs = {s: types for s, types in node.get_service_names_and_types_by_node(name, ns)
                if not s.endswith(IGNORED_SERVICE_SUFFIXES)}
        want_pubs = {_resolve(node, t): [ty] for t, (ty, _) in
                     parse_endpoints(contract['publishes']).items()}
        want_subs = {_resolve(node, t): [ty] for t, (ty, _) in
                     parse_endpoints(contract['subscribes']).items()}
        want_srvs = {_resolve(node, s): [str(ty)] for s, ty in
                     (contract['services'] or {}).items()}
        assert pubs == want_pubs, f'{name} publishers differ from docs/interfaces.md'
        assert subs == want_subs, f'{name} subscriptions differ from docs/interfaces.md'
        assert srvs == want_srvs, f'{name} services differ from docs/interfaces.md'
        # QoS: latched topics must be transient-local, sensor topics best effort.
        from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
        for topic, (_, qos) in parse_endpoints(contract['publishes']).items():
            infos = node.get_publishers_info_by_topic(_resolve(node, topic))
            mine = [i for i in infos if i.node_name == name]
            assert mine, topic
            profile = mine[0].qos_profile
            if qos == 'latched':
                assert profile.durability == DurabilityPolicy.TRANSIENT_LOCAL, topic
                assert profile.reliability == ReliabilityPolicy.RELIABLE, topic
            elif qos == 'sensor':
                assert profile.reliability == ReliabilityPolicy.BEST_EFFORT, topic
            elif qos in ('command', 'diagnostics'):
                assert profile.reliability == ReliabilityPolicy.RELIABLE, topic
            elif qos == 'tf':  # tf2's /tf: reliable, volatile
                assert profile.reliability == ReliabilityPolicy.RELIABLE, topic
                assert profile.durability == DurabilityPolicy.VOLATILE, topic
    finally:
        node.destroy_node()

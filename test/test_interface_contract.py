"""Hold every node to the contract tables in docs/interfaces.md, and the rig to its remaps.

Each ```contract block names a node, its package/executable, and the exact set of topics it
publishes and subscribes (with message types) and the services it offers, under the node's own
names: ``~/name`` (private: under the node's name) or an absolute ``/name`` (``/diagnostics``,
``/tf``). ``remaps`` gives each private topic its name in the rig (relative, so a namespace
moves the whole rig), as the launch files remap it; ``when`` lists endpoints that exist only
with some ``parameters``. The test builds the node in-process (its class is the rclpy Node
subclass defined in ``<pkg>.nodes.<executable>``), configures and activates it when it is a
lifecycle node, and compares the ROS graph's view of the node with the table. Parameter and
housekeeping endpoints that every rclpy node has (``/parameter_events``, ``/rosout``,
``~/get_parameters``... and lifecycle services) are ignored. Then the launch files must remap
exactly as the contract says, and the remapped rig must be wired: every subscription has a
publisher of its type, and the session records what the rig publishes.
"""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path
import re

import pytest
import yaml

from cgail_rig.launch_spec import load_launch_file

ROOT = Path(__file__).resolve().parents[1]
LAUNCH_DIR = ROOT / 'src' / 'cgail_rig' / 'launch'
CONTRACT_RE = re.compile(r'```contract\n(.*?)```', re.S)
TYPE_RE = re.compile(r'^\s*([\w/]+)\s*(?:\[(\w+)\])?\s*$')
RIG_NAME_RE = re.compile(r'[A-Za-z_]\w*(/[A-Za-z_]\w*)*', re.ASCII)
QOS_NAMES = {'sensor', 'command', 'latched', 'diagnostics', 'tf'}
IGNORED_TOPICS = {'/parameter_events', '/rosout'}
IGNORED_TOPIC_SUFFIXES = ('/transition_event',)  # lifecycle nodes publish it
IGNORED_SERVICE_SUFFIXES = (
    'describe_parameters', 'get_parameter_types', 'get_parameters', 'list_parameters',
    'set_parameters', 'set_parameters_atomically', 'get_type_description',
    'change_state', 'get_state', 'get_available_states', 'get_available_transitions',
    'get_transition_graph',
)
#: Rig inputs that come from outside the launch (rig name -> who publishes it): the goal from
#: the session or the person at the rig; on the real rig no phantom publishes the wall.
EXTERNAL_INPUTS = {
    'sim_rig': {'/planner/goal'},
    'rig': {'/planner/goal', '/phantom/markers', '/phantom/lumen'},
}


def load_contracts() -> list[dict]:
    text = (ROOT / 'docs' / 'interfaces.md').read_text()
    blocks = [yaml.safe_load(b) for b in CONTRACT_RE.findall(text)]
    assert blocks, 'docs/interfaces.md has no contract blocks'
    return blocks


CONTRACTS = {c['node']: c for c in load_contracts()}


def parse_endpoints(section: dict | None) -> dict[str, tuple[str, str | None]]:
    out = {}
    for name, spec in (section or {}).items():
        m = TYPE_RE.match(str(spec))
        assert m, f'bad contract entry {name}: {spec!r}'
        msg_type, qos = m.group(1), m.group(2)
        assert qos is None or qos in QOS_NAMES, f'{name}: unknown QoS {qos!r}'
        out[name] = (msg_type, qos)
    return out


def topics(contract: dict, kind: str, *, conditional: bool = True) -> dict[str, tuple]:
    """The node's own ``publishes`` or ``subscribes``, with its ``when`` ones."""
    out = parse_endpoints(contract[kind])
    if conditional:
        out |= parse_endpoints((contract.get('when') or {}).get(kind))
    return out


def own_name(node: str, name: str) -> str:
    """A contract name as the graph shows it for a node in the root namespace."""
    return f'/{node}/{name[2:]}' if name.startswith('~/') else name


def rig_name(contract: dict, name: str) -> str:
    """A contract name as the rig's launch files make it (root namespace)."""
    remaps = contract.get('remaps') or {}
    return '/' + remaps[name] if name in remaps else own_name(contract['node'], name)


def test_contract_blocks_are_well_formed():
    for block in CONTRACTS.values():
        node = block['node']
        for key in ('node', 'package', 'executable', 'publishes', 'subscribes', 'services'):
            assert key in block, f'contract of {node} lacks {key!r}'
        unknown = set(block) - {'node', 'package', 'executable', 'publishes', 'subscribes',
                                'services', 'remaps', 'when', 'test_parameters'}
        assert not unknown, f'contract of {node}: unknown keys {unknown}'
        own = topics(block, 'publishes') | topics(block, 'subscribes')
        for name in [*own, *(block['services'] or {})]:
            assert name.startswith(('~/', '/')), \
                f'{node}: {name!r} must be the node\'s own (~/...) or absolute (/...)'
        private = {t for t in own if t.startswith('~/')}
        remaps = block.get('remaps') or {}
        assert set(remaps) == private, \
            f'{node}: remaps must give every private topic its rig name: {set(remaps)} != ' \
            f'{private}'
        for target in remaps.values():
            assert RIG_NAME_RE.fullmatch(target), \
                f'{node}: rig name {target!r} must be relative (a namespace moves the rig)'
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


def _graph(node) -> tuple[dict, dict, dict]:
    name, ns = node.get_name(), node.get_namespace()
    pubs = {t: types for t, types in node.get_publisher_names_and_types_by_node(name, ns)
            if t not in IGNORED_TOPICS and not t.endswith(IGNORED_TOPIC_SUFFIXES)}
    subs = {t: types for t, types in node.get_subscriber_names_and_types_by_node(name, ns)
            if t not in IGNORED_TOPICS}
    srvs = {s: types for s, types in node.get_service_names_and_types_by_node(name, ns)
            if not s.endswith(IGNORED_SERVICE_SUFFIXES)}
    return pubs, subs, srvs


def _check_node(contract: dict, parameters: dict, conditional: bool) -> None:
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    try:
        cls = _node_class(contract['package'], contract['executable'])
    except ModuleNotFoundError as exc:
        pytest.fail(f'node {contract["node"]} is in the contract but not implemented: {exc}')
    node = cls(parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()]) \
        if parameters else cls()
    try:
        if hasattr(node, 'trigger_configure'):
            node.trigger_configure()
            node.trigger_activate()
        name = node.get_name()
        assert name == contract['node']
        pubs, subs, srvs = _graph(node)
        want_pubs = {own_name(name, t): [ty] for t, (ty, _) in
                     topics(contract, 'publishes', conditional=conditional).items()}
        want_subs = {own_name(name, t): [ty] for t, (ty, _) in
                     topics(contract, 'subscribes', conditional=conditional).items()}
        want_srvs = {own_name(name, s): [str(ty)] for s, ty in
                     (contract['services'] or {}).items()}
        assert pubs == want_pubs, f'{name} publishers differ from docs/interfaces.md'
        assert subs == want_subs, f'{name} subscriptions differ from docs/interfaces.md'
        assert srvs == want_srvs, f'{name} services differ from docs/interfaces.md'
        # QoS: latched topics must be transient-local, sensor topics best effort.
        for topic, (_, qos) in topics(contract, 'publishes', conditional=conditional).items():
            infos = node.get_publishers_info_by_topic(own_name(name, topic))
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


@pytest.mark.parametrize('contract', CONTRACTS.values(), ids=list(CONTRACTS))
@pytest.mark.usefixtures('rclpy_context')
def test_node_matches_contract(contract):
    """Built without remaps, the node shows its own names: ``~/x`` is ``/<node>/x``."""
    _check_node(contract, contract.get('test_parameters') or {}, conditional=False)


@pytest.mark.parametrize('contract', [c for c in CONTRACTS.values() if c.get('when')],
                         ids=[n for n, c in CONTRACTS.items() if c.get('when')])
@pytest.mark.usefixtures('rclpy_context')
def test_node_matches_contract_with_its_conditional_endpoints(contract):
    parameters = {**(contract.get('test_parameters') or {}), **contract['when']['parameters']}
    _check_node(contract, parameters, conditional=True)


@pytest.mark.usefixtures('rclpy_context')
def test_the_remaps_give_the_rig_names():
    """rcl reads each remap as the contract means it: the private name becomes the rig's,
    under a namespace pushed onto the rig too."""
    from rclpy.node import Node

    for contract in CONTRACTS.values():
        remaps = contract.get('remaps') or {}
        args = ['--ros-args', *(w for rule in remaps.items() for w in ('-r', ':='.join(rule)))]
        for namespace in ('/', '/rig2'):
            node = Node(contract['node'], namespace=namespace, cli_args=args,
                        start_parameter_services=False, enable_rosout=False)
            try:
                prefix = '' if namespace == '/' else namespace
                for source, target in remaps.items():
                    assert node.resolve_topic_name(source) == f'{prefix}/{target}', \
                        (contract['node'], source)
            finally:
                node.destroy_node()


def _launch(name: str):
    # rig.launch.yaml reads the em_tracker parameters it names; any calibration file does
    calibration = ROOT / 'src' / 'em_tracker' / 'config' / 'aurora.yaml'
    arguments = {'calibration': str(calibration)} if name == 'rig' else None
    return load_launch_file(LAUNCH_DIR / f'{name}.launch.yaml', arguments)


@pytest.mark.parametrize('launch', sorted(EXTERNAL_INPUTS))
def test_launch_files_remap_each_node_as_its_contract_says(launch):
    spec = _launch(launch)
    for node in spec.nodes:
        assert node.name in CONTRACTS, f'{launch}: node {node.name!r} has no contract'
        contract = CONTRACTS[node.name]
        assert (node.package, node.executable) == (contract['package'],
                                                   contract['executable']), node.name
        assert node.remappings == (contract.get('remaps') or {}), \
            f'{launch}.launch.yaml remaps {node.name} otherwise than docs/interfaces.md'


@pytest.mark.parametrize('launch', sorted(EXTERNAL_INPUTS))
def test_the_remapped_rig_is_wired(launch):
    """Every topic a node of the launch reads is published in it with that type (or comes
    from outside: EXTERNAL_INPUTS), and the rig names do not collide across types."""
    spec = _launch(launch)
    published: dict[str, set[str]] = {}
    for node in spec.nodes:
        contract = CONTRACTS[node.name]
        for topic, (msg_type, _) in topics(contract, 'publishes').items():
            published.setdefault(rig_name(contract, topic), set()).add(msg_type)
    assert all(len(types) == 1 for types in published.values()), published
    for node in spec.nodes:
        contract = CONTRACTS[node.name]
        default = topics(contract, 'subscribes', conditional=False)
        for topic, (msg_type, _) in topics(contract, 'subscribes').items():
            name = rig_name(contract, topic)
            if name in published:
                assert published[name] == {msg_type}, (launch, node.name, topic)
            elif topic in default:
                assert name in EXTERNAL_INPUTS[launch], \
                    f'{launch}: {node.name} reads {name} ({topic}), which nothing publishes'


def test_the_session_records_what_the_sim_rig_publishes():
    """The bags keep their topic names: each recorded topic is a sim rig node's (remapped)
    publication, the goal the session's own."""
    from cgail_rig.session import TOPICS

    published = {rig_name(CONTRACTS[n.name], t) for n in _launch('sim_rig').nodes
                 for t in topics(CONTRACTS[n.name], 'publishes')}
    recorded = {'/' + t.lstrip('/') for t in TOPICS}
    assert recorded - published == {'/planner/goal'}, \
        f'the session records {sorted(recorded - published)}, which the sim rig does not publish'


def test_record_demos_wires_teleop_and_joy_as_the_rig_does():
    from cgail_rig.record_demos import REMAPS

    for name in ('teleop', 'joy'):
        assert REMAPS[name] == CONTRACTS[name]['remaps'], name

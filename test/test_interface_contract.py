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

Each node's parameter table (in its section, or after a ``**`node`**`` label: the
catheter_driver tables) is held to the parameters the node, built the same way, declares: the
same names (less those rclpy declares for every node), the type column, each default, and the
default inside the range column where that is a numeric interval or an enumeration.
"""

from __future__ import annotations

import ast
import functools
import importlib
import inspect
import math
import operator
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


def _build_node(contract: dict, parameters: dict):
    """The contract's node class built in-process, with ``parameters`` as overrides."""
    from rclpy.parameter import Parameter

    try:
        cls = _node_class(contract['package'], contract['executable'])
    except ModuleNotFoundError as exc:
        pytest.fail(f'node {contract["node"]} is in the contract but not implemented: {exc}')
    return cls(parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()]) \
        if parameters else cls()


def _check_node(contract: dict, parameters: dict, conditional: bool) -> None:
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    node = _build_node(contract, parameters)
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


# -- parameter tables ------------------------------------------------------------------------
#
# Each node's parameter table in docs/interfaces.md (the section of its contract block, or the
# table after a ``**`node`**`` label: the catheter_driver tables) is held to what the node
# declares when built in-process: the same names, the type column, each default and, where the
# table has a range column, the default inside the range.

#: Parameters that rclpy declares for every node (a bare ``rclpy.node.Node`` has exactly these;
#: ``test_rclpy_declares_only_the_excluded_parameters`` keeps the list true), so no table lists
#: them.
RCLPY_PARAMETERS = {
    'use_sim_time': 'rclpy: the node clock follows /clock (set by launch files and sessions)',
    'start_type_description_service': "rclpy (Jazzy): whether the node offers "
                                       "~/get_type_description",
}
#: The headers of a parameter table (the operator's has no range column; the catheter_driver
#: tables say ``parameter``/``meaning`` and write numbers without backticks).
PARAM_HEADERS = {
    ('name', 'type', 'default', 'range', 'description'),
    ('name', 'type', 'default', 'description'),
    ('parameter', 'type', 'default', 'meaning'),
}
#: The type column's spellings.
PARAM_TYPES = {
    'bool': 'BOOL', 'int': 'INTEGER', 'double': 'DOUBLE', 'string': 'STRING',
    'bool[]': 'BOOL_ARRAY', 'int[]': 'INTEGER_ARRAY', 'double[]': 'DOUBLE_ARRAY',
    'string[]': 'STRING_ARRAY',
}
#: What a range cell may write for "no range" (outside backticks). A default must be written
#: out, so these are refused in the default column unless in backticks (`` `none` `` is the
#: string ``none``, the phantom's ``fixture``); the empty string is written ``` `''` ``` (or
#: ``` `""` ``` in the catheter_driver tables).
PLACEHOLDERS = {'', '-', '—', '–', '(none)', 'none'}
LABEL_RE = re.compile(r'^\*\*`(\w+)`\*\*')
INTERVAL_RE = re.compile(r'^([\[(])\s*([^,]+?)\s*,\s*([^,]+?)\s*([\])])$')
DOTS_RE = re.compile(r'^([^.]\S*?)\s*\.\.\s*(\S+)$')
BOUND_RE = re.compile(r'^(>=|<=|>|<)\s*(\S+)$')
COUNTS_RE = re.compile(r'^(\d+) or (\d+) values$')
BINARY_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
              ast.Div: operator.truediv, ast.Pow: operator.pow}
WORD_RE = re.compile(r'[A-Za-z_]\w*')
REL_TOL = 1e-9


def _cells(line: str) -> list[str]:
    """The cells of a table row (``\\|`` is a pipe inside a cell)."""
    inner = line.strip()[1:-1] if line.strip().endswith('|') else line.strip()[1:]
    return [c.strip().replace('\\|', '|') for c in re.split(r'(?<!\\)\|', inner)]


def _tokens(cell: str) -> list[tuple[str, bool]]:
    """``cell`` split at its top-level commas (not inside backticks or brackets): each token's
    text and whether it was one backtick span (then the text is the span's inside)."""
    tokens, current, depth, in_tick = [], '', 0, False
    for ch in cell:
        if ch == '`':
            in_tick = not in_tick
        elif not in_tick and ch in '[(':
            depth += 1
        elif not in_tick and ch in '])':
            depth -= 1
        if ch == ',' and depth == 0 and not in_tick:
            tokens.append(current)
            current = ''
        else:
            current += ch
    tokens.append(current)
    out = []
    for t in (t.strip() for t in tokens):
        m = re.fullmatch(r'`([^`]*)`', t)
        out.append((m.group(1), True) if m else (t, False))
    return out


def _number(text: str, table: dict[str, dict] | None = None) -> float | int:
    """A number the doc writes: ``0.005``, ``1e-4``, ``pi/2``, ``2^31-1``, or (in a range) the
    name of a parameter of the same table, meaning its default. Raises ValueError."""
    text = text.strip().strip('`')
    if table is not None and text in table:
        value = table[text]['default']
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f'{text} is not a number')
        return value
    try:
        value = yaml.safe_load(text) if text else None
    except yaml.YAMLError:
        value = None
    if isinstance(value, int | float) and not isinstance(value, bool):
        return value
    try:
        return _arithmetic(ast.parse(text.replace('^', '**'), mode='eval').body)
    except (SyntaxError, ValueError, ZeroDivisionError, OverflowError) as exc:
        raise ValueError(f'not a number: {text!r}') from exc


def _arithmetic(expr: ast.expr) -> float | int:
    """Numbers, ``pi``, + - * / ** and parentheses; anything else raises ValueError."""
    if isinstance(expr, ast.Constant) and type(expr.value) in (int, float):
        return expr.value
    if isinstance(expr, ast.Name) and expr.id == 'pi':
        return math.pi
    if isinstance(expr, ast.UnaryOp) and isinstance(expr.op, ast.USub | ast.UAdd):
        value = _arithmetic(expr.operand)
        return -value if isinstance(expr.op, ast.USub) else value
    if isinstance(expr, ast.BinOp) and type(expr.op) in BINARY_OPS:
        return BINARY_OPS[type(expr.op)](_arithmetic(expr.left), _arithmetic(expr.right))
    raise ValueError(ast.dump(expr))


def _doc_default(node: str, name: str, text: str, ticked: bool, type_: str):
    """The default as the table writes it, read for the parameter's type: a string is the text
    as written (``true``, ``none`` and ``127.0.0.1`` stay strings; ``''`` and ``""`` are the
    empty string); other types are YAML scalars or lists, numbers also ``pi/2``-style."""
    where = f'{node}: parameter {name}: default {text!r} in docs/interfaces.md'
    if not ticked and text.strip() in PLACEHOLDERS:
        pytest.fail(f'{where}: write the default (an empty string as `\'\'`)')
    if type_ == 'string':
        if len(text) >= 2 and text[0] == text[-1] and text[0] in '\'"':
            return yaml.safe_load(text)
        return text
    if type_ == 'bool':
        value = yaml.safe_load(text)
        assert isinstance(value, bool), f'{where}: not a bool'
        return value
    if type_.endswith('[]'):
        value = yaml.safe_load(text)
        assert isinstance(value, list), f'{where}: not a list'
        if type_ in ('int[]', 'double[]'):
            try:
                value = [_number(str(v)) for v in value]
            except ValueError as exc:
                pytest.fail(f'{where}: {exc}')
        return value
    try:
        value = _number(text)
    except ValueError as exc:
        pytest.fail(f'{where}: {exc}')
    if type_ == 'int':
        assert isinstance(value, int), f'{where}: not an int'
    return value


def _split(node: str, cell: str, count: int, what: str, name: str) -> list[tuple[str, bool]]:
    tokens = _tokens(cell)
    if len(tokens) == 1:
        return tokens * count
    assert len(tokens) == count, \
        f'{node}: row {name}: {count} names but {len(tokens)} {what}s ({cell!r})'
    return tokens


def parse_parameter_tables(text: str | None = None) -> dict[str, dict[str, dict]]:
    """``{node: {parameter: {'type', 'default', 'ranges'}}}`` from the parameter tables of
    docs/interfaces.md. A row may name several parameters (``a``, ``b``) with one type and
    default for all or one each, and one range for all or one each (``ranges`` is then a list
    of that parameter's range tokens)."""
    text = (ROOT / 'docs' / 'interfaces.md').read_text() if text is None else text
    lines = text.splitlines()
    tables: dict[str, dict[str, dict]] = {}
    node, i = None, 0
    while i < len(lines):
        line = lines[i]
        if line.startswith('```contract'):
            j = lines.index('```', i + 1)
            node = yaml.safe_load('\n'.join(lines[i + 1:j]))['node']
            i = j + 1
            continue
        if line.startswith(('## ', '### ')):
            node = None
        if m := LABEL_RE.match(line):
            assert m.group(1) in CONTRACTS, f'label {m.group(1)!r} names no contract node'
            node = m.group(1)
        if line.startswith('|') and i + 1 < len(lines) and lines[i + 1].startswith('|---'):
            header = tuple(_cells(line))
            if 'type' in header and 'default' in header:
                assert header in PARAM_HEADERS, \
                    f'docs/interfaces.md line {i + 1}: unknown parameter table header {header}'
                assert node is not None, \
                    f'docs/interfaces.md line {i + 1}: a parameter table outside a node section'
                assert node not in tables, f'{node}: a second parameter table (line {i + 1})'
                tables[node] = _parse_table(node, header, lines, i + 2)
            while i < len(lines) and lines[i].startswith('|'):
                i += 1
            continue
        i += 1
    return tables


def _parse_table(node: str, header: tuple, lines: list[str], start: int) -> dict[str, dict]:
    rows: dict[str, dict] = {}
    col = {h: k for k, h in enumerate(header)}
    for line in lines[start:]:
        if not line.startswith('|'):
            break
        cells = _cells(line)
        assert len(cells) == len(header), f'{node}: bad parameter row {line!r}'
        names_cell = cells[col.get('name', col.get('parameter'))]
        names = [t for t, ticked in _tokens(names_cell) if ticked]
        assert names and len(names) == len(_tokens(names_cell)), \
            f'{node}: parameter names must be in backticks: {names_cell!r}'
        types = [t for t, _ in _split(node, cells[col['type']], len(names), 'type', names[0])]
        defaults = _split(node, cells[col['default']], len(names), 'default', names[0])
        if 'range' in col:
            range_tokens = _tokens(cells[col['range']])
            per_name = len(range_tokens) == len(names) and len(names) > 1
            ranges = [[r] for r in range_tokens] if per_name else [range_tokens] * len(names)
        else:
            ranges = [[]] * len(names)
        for name, type_, (text, ticked), rng in zip(names, types, defaults, ranges, strict=True):
            assert type_ in PARAM_TYPES, f'{node}: parameter {name}: unknown type {type_!r}'
            assert name not in rows, f'{node}: parameter {name} listed twice'
            rows[name] = {'type': type_, 'default': _doc_default(node, name, text, ticked, type_),
                          'doc_default': text, 'ranges': rng}
    return rows


@functools.cache
def parameter_tables() -> dict[str, dict[str, dict]]:
    return parse_parameter_tables()


def _in_interval(value: float, lo: float, hi: float, lo_open: bool, hi_open: bool) -> bool:
    return (lo < value if lo_open else lo <= value) and (value < hi if hi_open else value <= hi)


def _bound(text: str, table: dict[str, dict]) -> float | None:
    """A range bound as a number; ``None`` for a word that is no parameter of the table
    (``>= initial``: prose, not checked)."""
    text = text.strip().strip('`')
    if WORD_RE.fullmatch(text) and text != 'pi' and text not in table:
        return None
    return _number(text, table)


def range_problems(node: str, name: str, table: dict[str, dict], value) -> list[str]:
    """Where ``value`` (the code's default) falls outside the range column of ``name``.

    Checked: numeric intervals ``[a, b]``, ``(a, b]``, ``[a, b)``, ``(a, b)`` and ``a..b``
    (inclusive), one-sided ``>= a``, ``> a``, ``<= a``, ``< a`` (bounds are numbers, ``pi``
    expressions like ``pi/2`` or ``2^31-1``, or a parameter of the same table:
    ``[stop_distance, 0.1]``), enumerations (two or more values, each in backticks or a plain
    number: ``` `D`, `S`, `B` ```, ``9600, 19200, ...``), ``non-empty`` and ``N or M values``.
    Not checked (prose): ``-`` (none), ``read-only`` (checked against the descriptor by the
    caller), a single backticked format example (``` `hh:/path.rom,...` ```), and words such as
    ``name or path (Conventions)``, ``IP literal``, ``scenario ids``, ``distinct``,
    ``axes distinct``, ``>= initial``.
    """
    row = table[name]
    tokens = row['ranges']
    shown = ', '.join(f'`{t}`' if ticked else t for t, ticked in tokens)
    where = (f'{node}: parameter {name}: the code\'s default {value!r} is outside the doc\'s '
             f'range {shown!r} (doc default {row["doc_default"]!r})')
    scalar = row['type'].rstrip('[]')
    literal = [ticked or _is_number(t) for t, ticked in tokens]
    if len(tokens) >= 2 and all(literal):
        allowed = [_doc_default(node, name, t, ticked, scalar) for t, ticked in tokens]
        ok = any(_same(scalar, a, value) for a in allowed)
        return [] if ok else [where]
    problems = []
    for text, ticked in tokens:
        t = text.strip()
        if ticked or t in PLACEHOLDERS or t == 'read-only':
            continue
        if t == 'non-empty':
            if value == '':
                problems.append(where)
            continue
        if m := COUNTS_RE.fullmatch(t):
            if len(value) not in (int(m.group(1)), int(m.group(2))):
                problems.append(where)
            continue
        try:
            if m := INTERVAL_RE.fullmatch(t):
                lo, hi = _bound(m.group(2), table), _bound(m.group(3), table)
                lo_open, hi_open = m.group(1) == '(', m.group(4) == ')'
            elif m := DOTS_RE.fullmatch(t):
                lo, hi = _bound(m.group(1), table), _bound(m.group(2), table)
                lo_open = hi_open = False
            elif m := BOUND_RE.fullmatch(t):
                b = _bound(m.group(2), table)
                lo, hi = (b, math.inf) if m.group(1)[0] == '>' else (-math.inf, b)
                lo_open = hi_open = len(m.group(1)) == 1
            else:
                continue  # prose
        except ValueError as exc:
            pytest.fail(f'{node}: parameter {name}: range {t!r} in docs/interfaces.md: {exc}')
        lo = -math.inf if lo is None else lo
        hi = math.inf if hi is None else hi
        if not _in_interval(value, lo, hi, lo_open, hi_open):
            problems.append(where)
    return problems


def _is_number(text: str) -> bool:
    try:
        _number(text)
    except ValueError:
        return False
    return True


def _same(type_: str, doc, code) -> bool:
    """The doc's default equals the code's: doubles within REL_TOL, the rest exactly."""
    if type_ == 'double':
        return (isinstance(doc, int | float) and isinstance(code, int | float)
                and math.isclose(doc, code, rel_tol=REL_TOL, abs_tol=0.0))
    if type_.endswith('[]'):
        return (isinstance(code, list | tuple) and len(doc) == len(code)
                and all(_same(type_[:-2], d, c) for d, c in zip(doc, code, strict=True)))
    return type(doc) is type(code) and doc == code


def test_parameter_tables_are_well_formed():
    """Every table parses (names in backticks, a known type, a default written out), and every
    node of a contract has its table."""
    tables = parameter_tables()
    assert set(tables) == set(CONTRACTS), \
        f'nodes without a parameter table in docs/interfaces.md: ' \
        f'{sorted(set(CONTRACTS) - set(tables))}'


@pytest.mark.usefixtures('rclpy_context')
def test_rclpy_declares_only_the_excluded_parameters():
    """What a bare rclpy node declares is what RCLPY_PARAMETERS excludes from the tables."""
    from rclpy.node import Node

    node = Node('parameter_probe', start_parameter_services=False, enable_rosout=False)
    try:
        assert set(node.get_parameters_by_prefix('')) == set(RCLPY_PARAMETERS)
    finally:
        node.destroy_node()


@pytest.mark.parametrize('contract', CONTRACTS.values(), ids=list(CONTRACTS))
@pytest.mark.usefixtures('rclpy_context')
def test_node_declares_the_parameters_of_its_table(contract):
    """Built as ``test_node_matches_contract`` builds it (with ``test_parameters``; every node
    declares its parameters in its constructor, so a lifecycle node is not configured), the
    node declares exactly the table's parameters (less RCLPY_PARAMETERS), of the table's type,
    with its default (doubles within REL_TOL, the rest exactly) inside its range. A parameter
    that ``test_parameters`` overrides is checked for its presence and type only."""
    name = contract['node']
    table = parameter_tables().get(name)
    if table is None:
        pytest.fail(f'{name}: no parameter table in docs/interfaces.md')
    overridden = set(contract.get('test_parameters') or {})
    node = _build_node(contract, contract.get('test_parameters') or {})
    try:
        declared = {k: p for k, p in node.get_parameters_by_prefix('').items()
                    if k not in RCLPY_PARAMETERS}
        problems = []
        for missing in sorted(set(table) - set(declared)):
            problems.append(f'{name}: parameter {missing}: in docs/interfaces.md (default '
                            f'{table[missing]["doc_default"]!r}) but not declared by the code')
        for extra in sorted(set(declared) - set(table)):
            problems.append(f'{name}: parameter {extra}: declared by the code (default '
                            f'{declared[extra].value!r}) but not in docs/interfaces.md')
        for pname in sorted(set(table) & set(declared)):
            row, param = table[pname], declared[pname]
            doc_type = PARAM_TYPES[row['type']]
            if param.type_.name != doc_type:
                problems.append(f'{name}: parameter {pname}: type {row["type"]!r} in '
                                f'docs/interfaces.md, {param.type_.name} in the code')
                continue
            if 'read-only' in [t for t, _ in row['ranges']] and \
                    not node.describe_parameter(pname).read_only:
                problems.append(f'{name}: parameter {pname}: read-only in docs/interfaces.md, '
                                f'not in the code')
            if pname in overridden:
                continue
            value = param.value
            if row['type'].endswith('[]'):
                value = list(value)  # rclpy may hold an array.array
            if not _same(row['type'], row['default'], value):
                problems.append(f'{name}: parameter {pname}: default {row["doc_default"]!r} '
                                f'in docs/interfaces.md, {value!r} in the code')
            problems += range_problems(name, pname, table, value)
        assert not problems, '\n'.join(problems)
    finally:
        node.destroy_node()

"""Launch files in ROS 2's YAML launch format, read by our launcher (ROS ``launch`` has no wheel).

A launch file is what ``ros2 launch`` reads (the ``launch_yaml`` frontend of ``launch`` and
``launch_ros``), so on a full ROS 2 install ``ros2 launch cgail_rig sim_rig.launch.yaml``
reads the same file. A package keeps its launch files in ``launch/*.launch.yaml`` (installed to
``share/<pkg>/launch/``). This module reads the part of that format the workspace uses:

.. code-block:: yaml

    launch:
    - arg: {name: anatomy, default: default, description: the aorta}   # cgail launch F anatomy:=X
    - let: {name: config, value: $(dirname)/..}                        # a launch configuration
    - node:
        pkg: em_tracker                   # install/<pkg>/lib/<pkg>/<exec>
        exec: aurora_node
        name: aurora                      # node name (__node); required here (log prefix, --only)
        namespace: rig                    # optional (__ns)
        on_exit: shutdown                 # ROS 1's required="true": its exit ends the launch
        respawn: true                     # restart it when it exits
        respawn_delay: 2.0                # s before a restart (default: 0.5 s doubling to 10 s)
        args: --verbose                   # command line arguments of the executable
        ros_args: --log-level debug       # after --ros-args
        output: screen                    # accepted; every line is printed as [name] line
        param:                            # ROS params files, then name/value pairs over them
        - from: $(dirname)/../aurora.yaml
        - {name: rate_hz, value: 40.0}
        - {name: port, value: $(var port)}
        remap:                            # the node's own name -> the rig's (-r from:=to)
        - {from: ~/tip_pose, to: em_tracker/tip_pose}
        env:
        - {name: RCUTILS_COLORIZED_OUTPUT, value: '0'}
    - executable:                         # a plain (non-ROS) process
        cmd: python3 -m em_tracker.hw.sim_aurora --link /tmp/aurora
        name: sim_aurora

Substitutions, inside any string: ``$(var NAME)`` (an ``arg`` or ``let`` above),
``$(dirname)`` (the launch file's directory), ``$(find-pkg-share PKG)`` and
``$(env NAME [DEFAULT])``. As in ``launch_ros``, a parameter value written as a string is typed
by YAML after substitution (``'8780'`` is an integer, ``''`` stays a string), ``arg`` defaults
and ``let`` values are strings, and a relative ``from`` path is relative to the working
directory (hence ``$(dirname)``). ``cgail launch FILE NAME:=VALUE`` sets an argument; an argument
without a default must be given.

A remapping's ``from`` and ``to`` are topic or service names: relative (``joy``), absolute
(``/joy``) or private (``~/joy``: under the node's name, how the workspace's nodes name their
topics), tokens of letters, digits and underscores that do not start with a digit, separated by
``/``. Each ``from`` appears once per node.

``--in-process`` builds each node from its class: ``<pkg>.nodes.<exec>:<Exec>``, the
executable's module and its name in CamelCase (CONTRIBUTING.md, "Code style":
``planner_node.py`` holds ``PlannerNode``), so launch files carry nothing ``ros2 launch``
would refuse.

This module is pure python (no rclpy) so specs can be validated without ROS.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import logging
import os
from pathlib import Path
import re
import shlex
from typing import Any

import yaml


class LaunchSpecError(ValueError):
    """A launch file is malformed; the message names the entry and the field."""


#: A topic or service name as a remapping may name it: relative, absolute or private (``~/``).
_REMAP_NAME = re.compile(r'(~/|/)?[A-Za-z_]\w*(/[A-Za-z_]\w*)*', re.ASCII)


def check_remapping(source: str, target: str, where: str) -> None:
    """Raise :class:`LaunchSpecError` unless ``source:=target`` is a topic remapping rcl reads.

    Args:
        source: the name the node uses (``from``), e.g. ``~/tip_pose``.
        target: the name it gets (``to``), e.g. ``em_tracker/tip_pose``.
        where: the entry, for the message (``launch 'rig': node 'aurora'.remap[0]``).
    """
    for side, value in (('from', source), ('to', target)):
        if value.startswith('__'):
            raise LaunchSpecError(f'{where}: remap {side} {value!r}: the node name and namespace '
                                  'are set with name and namespace, not remapped')
        if not _REMAP_NAME.fullmatch(value):
            raise LaunchSpecError(
                f'{where}: remap {side} {value!r} is not a topic name; expected a relative, '
                "absolute (/...) or private (~/...) name of letters, digits and underscores "
                "separated by '/', each part not starting with a digit")


@dataclass(frozen=True)
class NodeSpec:
    """One node (or plain process) of a launch.

    Attributes:
        name: Node name (``__node`` remap) and the log prefix. Unique within a launch.
        package: ROS package holding the executable (ROS nodes only).
        executable: Executable in ``install/<package>/lib/<package>/``.
        plugin: ``module:Class`` of the rclpy Node, for in-process mode.
        namespace: Node namespace (``__ns``), '' for the root.
        parameters: Parameters from ``name``/``value`` entries, applied after
            ``parameters_files``.
        parameters_files: ROS params YAML files (``<node>: {ros__parameters: {...}}`` or
            ``/**: {ros__parameters: ...}``), absolute paths, applied in order.
        required: If this process exits (any code), the whole launch shuts down.
        respawn: Restart the process when it exits (ignored when ``required``).
        respawn_delay: Seconds before a restart; None: 0.5 s, doubling up to 10 s.
        args: Extra command line arguments (process mode).
        ros_args: Extra ROS arguments, after ``--ros-args``.
        command: Full command line of a plain (non-ROS) process.
        ros: False for plain processes (no ``--ros-args`` are added).
        env: Extra environment variables for this process.
        remappings: Topic remappings ``{from: to}``.
    """

    name: str
    package: str = ''
    executable: str = ''
    plugin: str = ''
    namespace: str = ''
    parameters: dict[str, Any] = field(default_factory=dict)
    parameters_files: tuple[str, ...] = ()
    required: bool = False
    respawn: bool = False
    respawn_delay: float | None = None
    args: tuple[str, ...] = ()
    ros_args: tuple[str, ...] = ()
    command: tuple[str, ...] = ()
    ros: bool = True
    env: dict[str, str] = field(default_factory=dict)
    remappings: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace('_', 'a').isalnum():
            raise LaunchSpecError(
                f'node name must be a non-empty identifier ([A-Za-z0-9_]), found {self.name!r}')
        if self.ros:
            if not (self.package and self.executable):
                raise LaunchSpecError(
                    f'node {self.name!r}: expected pkg and exec, found '
                    f'pkg={self.package!r} exec={self.executable!r}')
        elif not self.command:
            raise LaunchSpecError(f'executable {self.name!r}: expected a non-empty cmd')
        if self.plugin and ':' not in self.plugin:
            raise LaunchSpecError(
                f'node {self.name!r}: plugin must read "module:Class", found {self.plugin!r}')
        if self.respawn_delay is not None and not self.respawn_delay >= 0.0:
            raise LaunchSpecError(f'node {self.name!r}: respawn_delay must be >= 0 s, found '
                                  f'{self.respawn_delay}')
        for source, target in self.remappings.items():
            check_remapping(source, target, f'node {self.name!r}')

    @property
    def fully_qualified_name(self) -> str:
        """``/namespace/name`` (``/name`` in the root namespace)."""
        ns = self.namespace.strip('/')
        return f'/{ns}/{self.name}' if ns else f'/{self.name}'


@dataclass(frozen=True)
class LaunchSpec:
    """A named set of nodes started together, with the launch arguments they were made with."""

    name: str
    nodes: tuple[NodeSpec, ...]
    arguments: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.nodes:
            raise LaunchSpecError(f'launch {self.name!r}: expected at least one node, found none')
        names = [n.name for n in self.nodes]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise LaunchSpecError(f'launch {self.name!r}: node names must be unique, found '
                                  f'duplicates {dupes}')

    def select(self, names: list[str] | None) -> LaunchSpec:
        """Return a spec with only the named nodes (all when ``names`` is empty/None)."""
        if not names:
            return self
        unknown = sorted(set(names) - {n.name for n in self.nodes})
        if unknown:
            raise LaunchSpecError(f'launch {self.name!r} has no node(s) {unknown}; expected '
                                  f'some of {[n.name for n in self.nodes]}')
        return LaunchSpec(self.name, tuple(n for n in self.nodes if n.name in names),
                          self.arguments)


def node_plugin(package: str, executable: str) -> str:
    """The in-process class of a node: ``<package>.nodes.<executable>:<CamelCase>``."""
    camel = ''.join(word.capitalize() for word in executable.split('_'))
    return f'{package}.nodes.{executable}:{camel}'


# Attributes of each action this reader understands (ros2 launch refuses unknown ones too).
_ATTRS = {
    'arg': {'name', 'default', 'description'},
    'let': {'name', 'value'},
    'node': {'pkg', 'exec', 'name', 'namespace', 'param', 'remap', 'env', 'args', 'ros_args',
             'output', 'respawn', 'respawn_delay', 'on_exit'},
    'executable': {'cmd', 'name', 'env', 'output', 'respawn', 'respawn_delay', 'on_exit'},
}
_SUBSTITUTION = re.compile(r'\$\(([a-z-]+)((?:\s+[^()\s]+)*)\s*\)')


@dataclass
class _Scope:
    """Where substitutions are resolved: the launch file's directory and its configurations."""

    base_dir: Path
    values: dict[str, str]

    def substitute(self, text: str, where: str) -> str:
        def one(match: re.Match[str]) -> str:
            kind, words = match.group(1), match.group(2).split()
            if kind == 'var' and len(words) == 1:
                if words[0] not in self.values:
                    raise LaunchSpecError(
                        f'{where}: $(var {words[0]}) names no launch argument; expected one of '
                        f'{sorted(self.values)}')
                return self.values[words[0]]
            if kind == 'dirname' and not words:
                return str(self.base_dir)
            if kind == 'find-pkg-share' and len(words) == 1:
                return _package_share(words[0], where)
            if kind == 'env' and len(words) in (1, 2):
                value = os.environ.get(words[0], words[1] if len(words) == 2 else None)
                if value is None:
                    raise LaunchSpecError(f'{where}: $(env {words[0]}): the environment '
                                          'variable is not set and no default is given')
                return value
            raise LaunchSpecError(
                f'{where}: unsupported substitution {match.group(0)!r}; expected $(var NAME), '
                '$(dirname), $(find-pkg-share PKG) or $(env NAME [DEFAULT])')

        out = _SUBSTITUTION.sub(one, text)
        if '$(' in out:
            raise LaunchSpecError(f'{where}: cannot read the substitution in {text!r} (nested '
                                  'or unclosed); expected $(var NAME), $(dirname), '
                                  '$(find-pkg-share PKG) or $(env NAME [DEFAULT])')
        return out


def _package_share(package: str, where: str) -> str:
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for prefix in prefixes:
        share = Path(prefix) / 'share' / package
        if share.is_dir():
            return str(share)
    raise LaunchSpecError(f'{where}: $(find-pkg-share {package}): no share/{package} under '
                          f'AMENT_PREFIX_PATH={prefixes}')


def _text(body: dict[str, Any], key: str, where: str, *, required: bool = False) -> str | None:
    """A string attribute (None when absent and not required)."""
    if key not in body:
        if required:
            raise LaunchSpecError(f'{where}: expected a {key!r} attribute, found none')
        return None
    value = body[key]
    if not isinstance(value, str):
        raise LaunchSpecError(f'{where}: {key!r} must be a string (quote it in the YAML), '
                              f'found {type(value).__name__} {value!r}')
    return value


def _entries(body: dict[str, Any], key: str, where: str) -> list[dict[str, Any]]:
    """A list-of-mappings attribute (``param``, ``remap``, ``env``)."""
    value = body.get(key, [])
    if not isinstance(value, list) or not all(isinstance(e, dict) for e in value):
        raise LaunchSpecError(f'{where}: {key!r} must be a list of mappings, found {value!r}')
    return value


def _typed(value: str, where: str) -> Any:
    """A string parameter value typed as ``launch_ros`` types it: by YAML, after substitution."""
    try:
        typed = yaml.safe_load(value)
    except yaml.YAMLError:
        return value
    if typed is None:
        return value
    if not isinstance(typed, bool | int | float | str | list):
        raise LaunchSpecError(f'{where}: a parameter value must read as a bool, number, string '
                              f'or list, found {type(typed).__name__} {value!r}')
    return typed


def _parameters(entries: list[dict[str, Any]], scope: _Scope, where: str, prefix: str = '',
                files: list[str] | None = None) -> dict[str, Any]:
    """``param`` entries: ``from`` files into ``files``; name/value pairs (nested with
    ``param``) as a flat ``{dotted.name: value}``."""
    out: dict[str, Any] = {}
    for j, entry in enumerate(entries):
        here = f'{where}.param[{j}]'
        unknown = sorted(set(entry) - {'name', 'value', 'from', 'param'})
        if unknown:
            raise LaunchSpecError(f'{here} has unknown key(s) {unknown}; expected name with '
                                  'value (or nested param), or from')
        if 'from' in entry:
            if files is None or set(entry) != {'from'}:
                raise LaunchSpecError(f'{here}: from stands alone, at the top level of param')
            path = Path(scope.substitute(str(_text(entry, 'from', here)), here)).expanduser()
            if not path.is_file():
                raise LaunchSpecError(f'{here}: parameters file {str(path)!r} not found (a '
                                      'relative path is relative to the working directory; '
                                      'write $(dirname)/... for one next to the launch file)')
            files.append(str(path.resolve()))
            continue
        name = scope.substitute(str(_text(entry, 'name', here, required=True)), here)
        if ('value' in entry) == ('param' in entry):
            raise LaunchSpecError(f'{here}: parameter {name!r} needs a value or nested param, '
                                  'not both')
        if 'param' in entry:
            out.update(_parameters(_entries(entry, 'param', here), scope, here,
                                   f'{prefix}{name}.'))
            continue
        value = entry['value']
        if isinstance(value, str):
            value = _typed(scope.substitute(value, here), here)
        elif isinstance(value, list):
            value = [scope.substitute(v, here) if isinstance(v, str) else v for v in value]
        elif isinstance(value, dict):
            raise LaunchSpecError(f'{here}: parameter {name!r} must be a scalar or a list, '
                                  f'found a mapping (nest it with param:)')
        out[prefix + name] = value
    return out


def _pairs(body: dict[str, Any], key: str, first: str, second: str, scope: _Scope,
           where: str) -> dict[str, str]:
    """``remap`` (from/to) or ``env`` (name/value) entries as a mapping."""
    out: dict[str, str] = {}
    for j, entry in enumerate(_entries(body, key, where)):
        here = f'{where}.{key}[{j}]'
        if set(entry) != {first, second}:
            raise LaunchSpecError(f'{here}: expected exactly {first} and {second}, found '
                                  f'{sorted(entry)}')
        source = scope.substitute(str(_text(entry, first, here)), here)
        target = scope.substitute(str(_text(entry, second, here)), here)
        if key == 'remap':
            check_remapping(source, target, here)
            if source in out:
                raise LaunchSpecError(f'{here}: {source!r} is remapped twice (to '
                                      f'{out[source]!r} and {target!r}); expected once')
        out[source] = target
    return out


def _process(kind: str, body: dict[str, Any], scope: _Scope, where: str) -> NodeSpec:
    """A ``node`` or ``executable`` action as a :class:`NodeSpec`."""
    def text(key: str, required: bool = False) -> str:
        value = _text(body, key, where, required=required)
        return '' if value is None else scope.substitute(value, where)

    def words(key: str) -> tuple[str, ...]:
        try:
            return tuple(shlex.split(text(key)))
        except ValueError as exc:
            raise LaunchSpecError(f'{where}: cannot split {key!r} into words: {exc}') from None

    on_exit = body.get('on_exit')
    if on_exit not in (None, 'shutdown'):
        raise LaunchSpecError(f'{where}: on_exit must be shutdown, found {on_exit!r}')
    respawn = body.get('respawn', False)
    if not isinstance(respawn, bool):
        raise LaunchSpecError(f'{where}: respawn must be true or false, found {respawn!r}')
    delay = body.get('respawn_delay')
    if delay is not None and (isinstance(delay, bool) or not isinstance(delay, int | float)):
        raise LaunchSpecError(f'{where}: respawn_delay must be a number of seconds, found '
                              f'{delay!r}')
    name = text('name')
    if not name:
        raise LaunchSpecError(f'{where}: expected a name (cgail launch prefixes the output with '
                              'it and selects nodes by it), found none')
    common: dict[str, Any] = {
        'name': name, 'required': on_exit == 'shutdown', 'respawn': respawn,
        'respawn_delay': None if delay is None else float(delay),
        'env': _pairs(body, 'env', 'name', 'value', scope, where),
    }
    if kind == 'executable':
        return NodeSpec(command=words('cmd'), ros=False, **common)
    files: list[str] = []
    parameters = _parameters(_entries(body, 'param', where), scope, where, files=files)
    package, executable = text('pkg', required=True), text('exec', required=True)
    return NodeSpec(
        package=package, executable=executable, plugin=node_plugin(package, executable),
        namespace=text('namespace'), parameters=parameters, parameters_files=tuple(files),
        args=words('args'), ros_args=words('ros_args'),
        remappings=_pairs(body, 'remap', 'from', 'to', scope, where), **common)


def parse_launch(data: Any, base_dir: Path | None = None,
                 arguments: dict[str, str] | None = None, *, name: str = 'launch') -> LaunchSpec:
    """Build a :class:`LaunchSpec` from a loaded ROS 2 YAML launch file.

    Args:
        data: the launch file's YAML (``{'launch': [actions...]}``).
        base_dir: the launch file's directory (``$(dirname)``; default: the working directory).
        arguments: launch argument values over the file's ``arg`` defaults.
        name: the launch's name (the file's name without ``.launch.yaml``/``.yaml``).

    Raises:
        LaunchSpecError: naming the entry and field that is wrong, an argument the file does
            not declare (or one without a default that is not given), or a substitution that
            cannot be resolved.
    """
    base = (base_dir or Path.cwd()).resolve()
    if not isinstance(data, dict) or list(data) != ['launch']:
        found = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise LaunchSpecError(
            f"launch {name!r}: expected ROS 2's YAML launch format, a mapping with the one key "
            f"'launch' holding a list of actions (arg, let, node, executable), found {found}")
    actions = data['launch']
    if not isinstance(actions, list):
        raise LaunchSpecError(f"launch {name!r}: 'launch' must be a list of actions, found "
                              f'{type(actions).__name__}')
    parsed: list[tuple[str, dict[str, Any], str]] = []
    for i, entry in enumerate(actions):
        where = f'launch {name!r}: launch[{i}]'
        if not isinstance(entry, dict) or len(entry) != 1:
            raise LaunchSpecError(f'{where} must be a mapping with one action key, found '
                                  f'{entry!r}')
        ((kind, body),) = entry.items()
        if kind not in _ATTRS:
            raise LaunchSpecError(f'{where}: unsupported action {kind!r}; expected one of '
                                  f'{sorted(_ATTRS)}')
        if not isinstance(body, dict):
            raise LaunchSpecError(f'{where}.{kind} must be a mapping of attributes, found '
                                  f'{body!r}')
        if isinstance(body.get('name'), str):
            where = f'launch {name!r}: {kind} {body["name"]!r}'
        unknown = sorted(set(body) - _ATTRS[kind])
        if unknown:
            raise LaunchSpecError(f'{where} has unknown key(s) {unknown}; expected some of '
                                  f'{sorted(_ATTRS[kind])}')
        parsed.append((kind, body, where))
    declared = [b.get('name') for k, b, _ in parsed if k == 'arg']
    unknown_given = sorted(set(arguments or {}) - set(declared))
    if unknown_given:
        raise LaunchSpecError(f'launch {name!r} has no argument(s) {unknown_given}; expected '
                              f'some of {sorted(str(d) for d in declared)}')
    scope = _Scope(base, {})
    values: dict[str, str] = {}  # the arguments' (lets are configurations, not arguments)
    nodes: list[NodeSpec] = []
    for kind, body, where in parsed:  # in order: $(var X) sees the arg/let entries above it
        if kind in ('node', 'executable'):
            nodes.append(_process(kind, body, scope, where))
            continue
        key = str(_text(body, 'name', where, required=True))
        if not key.isidentifier():
            raise LaunchSpecError(f'{where}: argument names must be identifiers, found {key!r}')
        if kind == 'let':
            scope.values[key] = scope.substitute(
                str(_text(body, 'value', where, required=True)), where)
            continue
        default = _text(body, 'default', where)
        _text(body, 'description', where)
        if arguments and key in arguments:
            values[key] = str(arguments[key])
        elif default is not None:
            values[key] = scope.substitute(default, where)
        else:
            raise LaunchSpecError(f'launch {name!r} needs the argument {key!r} (it has no '
                                  f'default): give it as {key}:=VALUE')
        scope.values[key] = values[key]
    return LaunchSpec(name, tuple(nodes), values)


def _moved_launch_file(path: Path) -> Path | None:
    """Where a launch file of the old layout (``<pkg>/config/launch/NAME.yaml``) is now:
    ``<pkg>/launch/NAME.launch.yaml``, if that exists. The old paths are read for one release."""
    if path.suffix != '.yaml' or path.parent.name != 'launch' or \
            path.parent.parent.name != 'config':
        return None
    moved = path.parents[2] / 'launch' / f'{path.stem}.launch.yaml'
    return moved if moved.is_file() else None


def load_launch_file(path: str | Path, arguments: dict[str, str] | None = None) -> LaunchSpec:
    """Load and validate a ROS 2 YAML launch file (``arguments``: values over its defaults).

    A path of the old layout (``<pkg>/config/launch/NAME.yaml``) that no longer exists is read
    from ``<pkg>/launch/NAME.launch.yaml`` with a deprecation warning, until the next release.
    """
    p = Path(path)
    moved = None if p.is_file() else _moved_launch_file(p)
    if moved is not None:
        logging.getLogger(__name__).warning(
            'launch file %s moved to %s; the old path is deprecated and will stop working in '
            'the next release', p, moved)
        p = moved
    if not p.is_file():
        raise LaunchSpecError(f'launch file {str(p)!r} does not exist')
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise LaunchSpecError(f'launch file {str(p)!r} is not valid YAML: {exc}') from exc
    name = p.name.removesuffix('.yaml').removesuffix('.launch')
    return parse_launch(data, p.parent, arguments, name=name)


def default_launch_file() -> Path:
    """``launch/sim_rig.launch.yaml`` of ``cgail_rig`` (source tree, else the install's
    ``share/cgail_rig/launch/``): the simulated rig that ``cgail session`` and
    ``cgail identify-pam --sim`` run."""
    here = Path(__file__).resolve().parents[1] / 'launch' / 'sim_rig.launch.yaml'
    if here.is_file():
        return here
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        cand = Path(prefix) / 'share' / 'cgail_rig' / 'launch' / 'sim_rig.launch.yaml'
        if prefix and cand.is_file():
            return cand
    return here


def ros_params_yaml(node: NodeSpec) -> dict[str, Any]:
    """The node's name/value parameters as a ROS params file for ``--params-file`` (the file is
    the node's own, so the ``/**`` wildcard, as ``launch_ros`` writes it)."""
    return {'/**': {'ros__parameters': dict(node.parameters)}}


def load_params_file(path: str, node_name: str, namespace: str = '') -> dict[str, Any]:
    """The parameters of a node in a ROS params file: the ``/**`` wildcard sections, then the
    node's own (``name`` or ``/name``; in a namespace only ``/namespace/name``, as rcl reads a
    key without a leading slash as one in the root namespace)."""
    data = yaml.safe_load(Path(path).read_text()) or {}
    if not isinstance(data, dict):
        raise LaunchSpecError(f'parameters file {path!r} must be a mapping')
    ns = namespace.strip('/')
    keys = ['/**', '**', f'/**/{node_name}']
    keys += [f'{ns}/{node_name}', f'/{ns}/{node_name}'] if ns else [node_name, '/' + node_name]
    out: dict[str, Any] = {}
    for key in keys:
        section = data.get(key)
        if isinstance(section, dict):
            out.update(section.get('ros__parameters', {}) or {})
    return out

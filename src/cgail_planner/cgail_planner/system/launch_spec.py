"""Launch descriptions for our small multi-node launcher (ROS ``launch`` has no wheel).

A launch file is YAML:

.. code-block:: yaml

    # sim_rig.yaml
    name: sim_rig
    nodes:
      - name: aurora                      # node name (remaps __node)
        package: em_tracker
        executable: aurora_node           # install/<package>/lib/<package>/<executable>
        plugin: em_tracker.nodes.aurora_node:AuroraNode   # class for --in-process mode
        parameters:                       # inline parameters ...
          rate_hz: 40.0
        parameters_file: config/aurora.yaml   # ... and/or a ROS params file (relative to the
                                              # package share dir or the launch file)
        required: true                    # if it exits, the whole launch shuts down
        respawn: false
      - name: sim_aurora                  # a plain (non-ROS) process, e.g. a simulated device
        command: [python, -m, em_tracker.hw.sim_aurora]
        ros: false

Launch arguments, as in ROS 2 launch files: ``arguments`` maps each name to its default, and
``$(var NAME)`` in a string of ``parameters``, ``args``, ``command`` or ``env`` is replaced by
the argument's value (``rig_launch FILE NAME:=VALUE`` sets one; values are strings):

.. code-block:: yaml

    arguments:
      anatomy: default
    nodes:
      - name: planner
        ...
        parameters: {anatomy: $(var anatomy)}

This module is pure python (no rclpy) so specs can be validated without ROS.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
import re
from typing import Any

import yaml


class LaunchSpecError(ValueError):
    """A launch file is malformed; the message names the entry and the field."""


_NODE_KEYS = {
    'name', 'package', 'executable', 'plugin', 'parameters', 'parameters_file', 'required',
    'respawn', 'args', 'command', 'ros', 'env', 'remappings',
}


@dataclass(frozen=True)
class NodeSpec:
    """One node (or plain process) of a launch.

    Attributes:
        name: Node name (``__node`` remap) and the log prefix. Unique within a launch.
        package: ROS package holding the executable (ROS nodes only).
        executable: Executable in ``install/<package>/lib/<package>/``.
        plugin: ``module:Class`` of the rclpy Node, for in-process mode.
        parameters: Inline parameter overrides, applied after ``parameters_file``.
        parameters_file: Optional ROS params YAML (``<node>: {ros__parameters: {...}}`` or
            ``/**: {ros__parameters: ...}``), already resolved to an absolute path.
        required: If this process exits (any code), the whole launch shuts down.
        respawn: Restart the process when it exits (ignored when ``required``).
        args: Extra command line arguments (process mode).
        command: Full command line of a plain (non-ROS) process.
        ros: False for plain processes (no ``--ros-args`` are added).
        env: Extra environment variables for this process.
        remappings: Topic remappings ``{from: to}``.
    """

    name: str
    package: str = ''
    executable: str = ''
    plugin: str = ''
    parameters: dict[str, Any] = field(default_factory=dict)
    parameters_file: str = ''
    required: bool = False
    respawn: bool = False
    args: tuple[str, ...] = ()
    command: tuple[str, ...] = ()
    ros: bool = True
    env: dict[str, str] = field(default_factory=dict)
    remappings: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace('_', 'a').isalnum():
            raise LaunchSpecError(
                f'node name must be a non-empty identifier ([A-Za-z0-9_]), found {self.name!r}')
        if self.ros:
            if self.command:
                if self.package or self.executable:
                    raise LaunchSpecError(
                        f'node {self.name!r}: give either command or package+executable, '
                        'not both')
            elif not (self.package and self.executable):
                raise LaunchSpecError(
                    f'node {self.name!r}: expected package and executable (or command), found '
                    f'package={self.package!r} executable={self.executable!r}')
        elif not self.command:
            raise LaunchSpecError(f'process {self.name!r}: ros: false needs a command list')
        if self.plugin and ':' not in self.plugin:
            raise LaunchSpecError(
                f'node {self.name!r}: plugin must read "module:Class", found {self.plugin!r}')


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


def _resolve_file(value: str, base_dir: Path, package: str) -> str:
    """Resolve a parameters file relative to the launch file, then the package share dir."""
    path = Path(os.path.expandvars(os.path.expanduser(value)))
    if path.is_absolute():
        candidates = [path]
    else:
        candidates = [base_dir / path]
        if package:
            for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
                if prefix:
                    candidates.append(Path(prefix) / 'share' / package / path)
    for cand in candidates:
        if cand.is_file():
            return str(cand.resolve())
    raise LaunchSpecError(
        f'parameters_file {value!r} not found; looked in {[str(c) for c in candidates]}')


_VAR = re.compile(r'\$\(var ([^)]*)\)')


def _launch_arguments(name: str, declared: Any, given: dict[str, str] | None) -> dict[str, str]:
    """The values of the launch's arguments: the declared defaults, then the given ones."""
    if declared is None:
        declared = {}
    if not isinstance(declared, dict):
        raise LaunchSpecError(f'launch {name!r}: "arguments" must be a mapping of names to '
                              f'defaults, found {type(declared).__name__}')
    values: dict[str, str] = {}
    for key, default in declared.items():
        if not str(key).isidentifier():
            raise LaunchSpecError(f'launch {name!r}: argument names must be identifiers, found '
                                  f'{key!r}')
        if not isinstance(default, (str, int, float)):
            raise LaunchSpecError(f'launch {name!r}: argument {key!r} must have a string '
                                  f'default, found {type(default).__name__}')
        values[str(key)] = str(default)
    unknown = sorted(set(given or {}) - set(values))
    if unknown:
        raise LaunchSpecError(f'launch {name!r} has no argument(s) {unknown}; expected some of '
                              f'{sorted(values)}')
    values.update({k: str(v) for k, v in (given or {}).items()})
    return values


def _substitute(value: Any, arguments: dict[str, str], where: str) -> Any:
    """``value`` with every ``$(var NAME)`` in its strings replaced (lists and mappings too)."""
    if isinstance(value, str):
        def one(match: re.Match[str]) -> str:
            if match.group(1) not in arguments:
                raise LaunchSpecError(f'{where}: $(var {match.group(1)}) names no launch '
                                      f'argument; expected one of {sorted(arguments)}')
            return arguments[match.group(1)]
        return _VAR.sub(one, value)
    if isinstance(value, list):
        return [_substitute(v, arguments, where) for v in value]
    if isinstance(value, dict):
        return {k: _substitute(v, arguments, f'{where}.{k}') for k, v in value.items()}
    return value


def parse_launch(data: dict[str, Any], base_dir: Path | None = None,
                 arguments: dict[str, str] | None = None) -> LaunchSpec:
    """Build a :class:`LaunchSpec` from already-loaded YAML data.

    Args:
        data: the launch file's YAML.
        base_dir: where relative ``parameters_file`` entries are looked for first.
        arguments: launch argument values over the file's ``arguments`` defaults.

    Raises:
        LaunchSpecError: naming the entry and field that is wrong, an argument the file does
            not declare, or a ``$(var NAME)`` that names no argument.
    """
    base = base_dir or Path.cwd()
    if not isinstance(data, dict):
        raise LaunchSpecError(f'launch file must be a mapping, found {type(data).__name__}')
    name = str(data.get('name', 'launch'))
    values = _launch_arguments(name, data.get('arguments'), arguments)
    raw_nodes = data.get('nodes')
    if not isinstance(raw_nodes, list):
        raise LaunchSpecError(f'launch {name!r}: "nodes" must be a list, found '
                              f'{type(raw_nodes).__name__}')
    nodes = []
    for i, raw in enumerate(raw_nodes):
        if not isinstance(raw, dict):
            raise LaunchSpecError(f'launch {name!r}: nodes[{i}] must be a mapping')
        unknown = sorted(set(raw) - _NODE_KEYS)
        if unknown:
            raise LaunchSpecError(f'launch {name!r}: nodes[{i}] has unknown key(s) {unknown}; '
                                  f'expected some of {sorted(_NODE_KEYS)}')
        raw = {key: _substitute(raw[key], values, f'launch {name!r}: nodes[{i}].{key}')
               if key in ('parameters', 'args', 'command', 'env') else raw[key] for key in raw}
        params = raw.get('parameters') or {}
        if not isinstance(params, dict):
            raise LaunchSpecError(f'launch {name!r}: nodes[{i}].parameters must be a mapping')
        package = str(raw.get('package', ''))
        pfile = raw.get('parameters_file', '')
        nodes.append(NodeSpec(
            name=str(raw.get('name', '')),
            package=package,
            executable=str(raw.get('executable', '')),
            plugin=str(raw.get('plugin', '')),
            parameters=dict(params),
            parameters_file=_resolve_file(str(pfile), base, package) if pfile else '',
            required=bool(raw.get('required', False)),
            respawn=bool(raw.get('respawn', False)),
            args=tuple(str(a) for a in raw.get('args', ()) or ()),
            command=tuple(str(a) for a in raw.get('command', ()) or ()),
            ros=bool(raw.get('ros', True)),
            env={str(k): str(v) for k, v in (raw.get('env') or {}).items()},
            remappings={str(k): str(v) for k, v in (raw.get('remappings') or {}).items()},
        ))
    return LaunchSpec(name, tuple(nodes), values)


def load_launch_file(path: str | Path, arguments: dict[str, str] | None = None) -> LaunchSpec:
    """Load and validate a launch YAML file (``arguments``: values over its defaults)."""
    p = Path(path)
    if not p.is_file():
        raise LaunchSpecError(f'launch file {str(p)!r} does not exist')
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise LaunchSpecError(f'launch file {str(p)!r} is not valid YAML: {exc}') from exc
    return parse_launch(data, p.parent, arguments)


def ros_params_yaml(node: NodeSpec) -> dict[str, Any]:
    """Inline parameters in the ROS params-file layout for ``--params-file``."""
    return {node.name: {'ros__parameters': dict(node.parameters)}}


def load_params_file(path: str, node_name: str) -> dict[str, Any]:
    """Read the parameters for ``node_name`` from a ROS params file (``/**`` wildcard too)."""
    data = yaml.safe_load(Path(path).read_text()) or {}
    if not isinstance(data, dict):
        raise LaunchSpecError(f'parameters file {path!r} must be a mapping')
    out: dict[str, Any] = {}
    for key in ('/**', '**', node_name, '/' + node_name):
        section = data.get(key)
        if isinstance(section, dict):
            out.update(section.get('ros__parameters', {}) or {})
    return out

"""``cgail launch``: start the nodes of a launch file, as ``ros2 launch`` does (ROS 2's
``launch`` is not installable from PyPI, so this is a small launcher of our own).

Reads a launch file in ROS 2's YAML launch format (:mod:`cgail_rig.launch_spec`;
the same file works with ``ros2 launch`` on a full install) and starts its nodes with their
parameters, either as child processes (default, one process per node, like ``ros2 launch``) or
all in this process on one multi-threaded executor (``--in-process``), forwards SIGINT/SIGTERM,
and shuts everything down cleanly: SIGINT to every child, then SIGTERM after
``--shutdown-timeout`` seconds, then SIGKILL.

Usage::

    cgail launch src/cgail_rig/launch/sim_rig.launch.yaml --in-process
    cgail launch my_rig.yaml --only aurora planner
    cgail launch src/cgail_rig/launch/sim_rig.launch.yaml --in-process \\
        anatomy:=runs/patients/p07    # a launch argument (NAME:=VALUE)

The launcher refuses to start when ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is unset (DDS would
multicast onto the network): run it through ``scripts/ws`` (``scripts/ws cgail launch ...``,
which sources ``scripts/env.sh``) or pass ``--allow-unset-discovery-range`` on purpose.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import contextlib
from dataclasses import dataclass
import importlib
import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any, IO

import yaml

from cgail_rig.launch_spec import (
    LaunchSpec,
    LaunchSpecError,
    load_launch_file,
    load_params_file,
    NodeSpec,
    ros_params_yaml,
)
from cgail_sim.cli_help import tool_parser


def find_executable(package: str, executable: str) -> str:
    """Locate ``lib/<package>/<executable>`` on AMENT_PREFIX_PATH (what ``ros2 run`` does)."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for prefix in prefixes:
        cand = Path(prefix) / 'lib' / package / executable
        if cand.is_file() and os.access(cand, os.X_OK):
            return str(cand)
    raise LaunchSpecError(
        f'executable {executable!r} of package {package!r} not found under lib/{package}/ of '
        f'AMENT_PREFIX_PATH={prefixes}; build the workspace (bash scripts/setup.sh) and run '
        'through scripts/ws')


def node_command(node: NodeSpec, params_dir: Path) -> list[str]:
    """The command line that starts ``node`` as a child process."""
    if node.command:
        cmd = list(node.command)
    else:
        cmd = [find_executable(node.package, node.executable)]
    cmd += list(node.args)
    if not node.ros:
        return cmd
    cmd += ['--ros-args', *_ros_arguments(node)]
    for path in node.parameters_files:
        cmd += ['--params-file', path]
    if node.parameters:
        pfile = params_dir / f'{node.name}.yaml'
        pfile.write_text(yaml.safe_dump(ros_params_yaml(node)))
        cmd += ['--params-file', str(pfile)]
    return cmd


def _ros_arguments(node: NodeSpec) -> list[str]:
    """Name, namespace, remappings and the file's ``ros_args`` (after ``--ros-args``)."""
    words = ['-r', f'__node:={node.name}']
    if node.namespace:
        words += ['-r', f'__ns:=/{node.namespace.strip("/")}']
    for src, dst in node.remappings.items():
        words += ['-r', f'{src}:={dst}']
    return words + list(node.ros_args)


@dataclass
class _Child:
    spec: NodeSpec
    cmd: list[str]
    proc: subprocess.Popen[bytes] | None = None
    restarts: int = 0
    pump: threading.Thread | None = None


class ProcessLauncher:
    """Runs every node of a spec as a child process and supervises them.

    Args:
        spec: What to start.
        out: Where the children's prefixed output goes (default stdout).
        shutdown_timeout: Seconds to wait after SIGINT before SIGTERM (and again before
            SIGKILL).
    """

    def __init__(self, spec: LaunchSpec, *, out: IO[str] | None = None,
                 shutdown_timeout: float = 5.0) -> None:
        if shutdown_timeout <= 0:
            raise ValueError(f'shutdown_timeout must be > 0 s, found {shutdown_timeout}')
        self.spec = spec
        self.out = out or sys.stdout
        self.shutdown_timeout = shutdown_timeout
        self._tmp = tempfile.TemporaryDirectory(prefix=f'launch_{spec.name}_')
        self._children = [_Child(n, node_command(n, Path(self._tmp.name))) for n in spec.nodes]
        self._stop = threading.Event()
        self._out_lock = threading.Lock()
        self.exit_code = 0

    # -- output ------------------------------------------------------------------------
    def _emit(self, name: str, line: str) -> None:
        with self._out_lock:
            self.out.write(f'[{name}] {line}')
            if not line.endswith('\n'):
                self.out.write('\n')
            self.out.flush()

    def _pump(self, child: _Child) -> None:
        proc = child.proc
        if proc is None or proc.stdout is None:
            return
        for raw in iter(proc.stdout.readline, b''):
            self._emit(child.spec.name, raw.decode(errors='replace'))
        proc.stdout.close()

    # -- lifecycle -----------------------------------------------------------------------
    def _spawn(self, child: _Child) -> None:
        env = dict(os.environ)
        env.update(child.spec.env)
        env.setdefault('PYTHONUNBUFFERED', '1')
        child.proc = subprocess.Popen(
            child.cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=env, start_new_session=True)  # own session: only we forward signals
        child.pump = threading.Thread(target=self._pump, args=(child,), daemon=True)
        child.pump.start()
        self._emit('launch', f'started {child.spec.name} (pid {child.proc.pid}): '
                   f'{" ".join(child.cmd)}')

    def start(self) -> None:
        """Start every child in spec order."""
        for child in self._children:
            self._spawn(child)

    def request_stop(self, *_: Any) -> None:
        """Ask the supervisor loop to shut everything down (signal-handler safe)."""
        self._stop.set()

    def pids(self) -> dict[str, int]:
        """PIDs of the running children by node name."""
        return {c.spec.name: c.proc.pid for c in self._children
                if c.proc is not None and c.proc.poll() is None}

    def supervise(self, poll_s: float = 0.1, max_duration: float | None = None) -> int:
        """Block until stopped, a required child exits, or every child exited.

        Returns:
            The launch's exit code: 0 after a clean requested shutdown, else the first
            non-zero exit code of a required child (or 1).
        """
        t0 = time.monotonic()
        while not self._stop.is_set():
            if max_duration is not None and time.monotonic() - t0 > max_duration:
                self._emit('launch', f'max duration {max_duration:.1f} s reached')
                break
            alive = 0
            for child in self._children:
                proc = child.proc
                if proc is None:
                    continue
                code = proc.poll()
                if code is None:
                    alive += 1
                    continue
                if child.spec.required:
                    self._emit('launch', f'required node {child.spec.name} exited with code '
                               f'{code}; shutting down')
                    self.exit_code = code or 1
                    self._stop.set()
                    break
                if child.spec.respawn:
                    child.restarts += 1
                    delay = child.spec.respawn_delay
                    if delay is None:
                        delay = min(0.5 * 2 ** (child.restarts - 1), 10.0)
                    self._emit('launch', f'{child.spec.name} exited with code {code}; '
                               f'respawn #{child.restarts} in {delay:.1f} s')
                    child.proc = None
                    time.sleep(delay)
                    if not self._stop.is_set():
                        self._spawn(child)
                        alive += 1
                    continue
                if code != 0:
                    self._emit('launch', f'{child.spec.name} exited with code {code}')
                child.proc = None
            if alive == 0 and not self._stop.is_set():
                self._emit('launch', 'all processes exited')
                break
            self._stop.wait(poll_s)
        self.shutdown()
        return self.exit_code

    def shutdown(self) -> None:
        """SIGINT every running child (reverse start order), then escalate."""
        running = [c for c in reversed(self._children)
                   if c.proc is not None and c.proc.poll() is None]
        for sig, label in ((signal.SIGINT, 'SIGINT'), (signal.SIGTERM, 'SIGTERM'),
                           (signal.SIGKILL, 'SIGKILL')):
            running = [c for c in running if c.proc is not None and c.proc.poll() is None]
            if not running:
                break
            for c in running:
                assert c.proc is not None
                self._emit('launch', f'sending {label} to {c.spec.name} (pid {c.proc.pid})')
                with contextlib.suppress(ProcessLookupError):
                    c.proc.send_signal(sig)
            deadline = time.monotonic() + self.shutdown_timeout
            for c in running:
                assert c.proc is not None
                with contextlib.suppress(subprocess.TimeoutExpired):
                    c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        for c in self._children:
            if c.pump is not None:
                c.pump.join(timeout=1.0)
            if c.proc is not None and c.proc.returncode not in (None, 0, -signal.SIGINT):
                self._emit('launch', f'{c.spec.name} finished with code {c.proc.returncode}')
        self._tmp.cleanup()

    def __enter__(self) -> ProcessLauncher:
        self.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.request_stop()
        self.shutdown()


def _import_plugin(plugin: str) -> Callable[..., Any]:
    module_name, _, attr = plugin.partition(':')
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise LaunchSpecError(f'plugin {plugin!r}: cannot import {module_name!r}: {exc}') from exc
    try:
        return getattr(module, attr)  # type: ignore[no-any-return]
    except AttributeError as exc:
        raise LaunchSpecError(f'plugin {plugin!r}: module {module_name!r} has no {attr!r}') \
            from exc


#: Parameters of every lean node (:func:`build_node`): rclpy's ``~/get_type_description``
#: service is not started. In Jazzy the service (rclpy's ``TypeDescriptionService`` over rcl)
#: leaves ~1 KB of glibc heap in use per node after the node is destroyed: building and
#: destroying 2,000 bare nodes in one context kept 0.98 KB per node with it, 0.01 KB without.
#: A process that builds a rig per trial (``bench/bench_autonomy_soak.py --detail``) grew by
#: that, trial after trial. Nothing in a closed simulated rig asks for type descriptions (the
#: bags carry their own). What a destroyed node still keeps is upstream and left: ~0.02 KB per
#: plain node, and ~0.3 KB per lifecycle node, in its state machine (rclpy's
#: ``LifecycleStateMachine``; the same with ``enable_communication_interface=False``, and a
#: bare state machine on a plain node keeps as much), so ~1 KB per trial's rig.
LEAN_PARAMETERS: dict[str, Any] = {'start_type_description_service': False}


def build_node(spec_node: NodeSpec, extra: dict[str, Any] | None = None,
               lean: bool = False, *, context: Any = None,
               prepare: Callable[[Any], None] | None = None) -> Any:
    """Build one ROS node of a spec in this process, configured and activated if lifecycle.

    Parameters: the ``parameters_files`` first, then the name/value ``parameters``, then
    ``extra``. The node class is built as ``Class(parameter_overrides=[...],
    cli_args=['--ros-args', '-r', '__node:=<name>', ...])`` (namespace, remappings and
    ``ros_args`` too), so it must forward ``**kwargs`` to ``rclpy.node.Node.__init__``.

    With ``lean`` the node offers no parameter services, no ``/rosout`` publisher, no type
    description service (:data:`LEAN_PARAMETERS`) and (lifecycle nodes) no lifecycle services:
    for a closed in-process rig that nothing outside calls (the simulated in-vitro session; its
    node logs go to the log file). Every service is an entity an executor has to watch; the
    rig's ~70 such services cost rclpy's executor ~10 % of its CPU. The type description
    service also keeps ~1 KB of heap per node after the node is destroyed (Jazzy's rclpy; a
    process that builds a rig per trial grew by that per node, trial after trial).

    Args:
        spec_node: the node's entry of the launch file.
        extra: parameters over the file's.
        lean: as above.
        context: the rclpy context of the node (default: the global one).
        prepare: called with the node after construction, before configure/activate (the
            lockstep executor attaches the node's clock there, so activation already reads
            simulated time).
    """
    from rclpy.parameter import Parameter

    params: dict[str, Any] = {}
    for path in spec_node.parameters_files:
        params.update(load_params_file(path, spec_node.name, spec_node.namespace))
    params.update(spec_node.parameters)
    params.update(extra or {})
    cls = _import_plugin(spec_node.plugin)
    options: dict[str, Any] = {}
    if context is not None:
        options['context'] = context
    if lean:
        from rclpy.lifecycle import LifecycleNode

        options['start_parameter_services'] = False
        options['enable_rosout'] = False
        if isinstance(cls, type) and issubclass(cls, LifecycleNode):
            options['enable_communication_interface'] = False
    if lean:
        params.update(LEAN_PARAMETERS)
    node = cls(parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
               cli_args=['--ros-args', *_ros_arguments(spec_node)], **options)
    if prepare is not None:
        prepare(node)
    # a lifecycle node starts itself unless its ``autostart`` is false (the device nodes'
    # parameter, as in their standalone main): then a lifecycle manager drives it
    if (hasattr(node, 'trigger_configure') and hasattr(node, 'trigger_activate')
            and getattr(node, 'autostart', True)):
        node.trigger_configure()
        node.trigger_activate()
    return node


def run_in_process(spec: LaunchSpec, *, max_duration: float | None = None,
                   out: IO[str] | None = None) -> int:
    """Run every ROS node of ``spec`` in this process on one MultiThreadedExecutor.

    Plain (``ros: false``) processes are still started as children. Node classes are built as
    ``Class(parameter_overrides=[...], cli_args=['--ros-args', '-r', '__node:=<name>'])``, so a
    node class must forward ``**kwargs`` to ``rclpy.node.Node.__init__``. Lifecycle nodes are
    configured and activated, unless their ``autostart`` parameter is false.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    from cgail_node_utils.entry_point import try_shutdown

    plain = LaunchSpec(spec.name, tuple(n for n in spec.nodes if not n.ros)) \
        if any(not n.ros for n in spec.nodes) else None
    ros_nodes = [n for n in spec.nodes if n.ros]
    missing = [n.name for n in ros_nodes if not n.plugin]
    if missing:
        raise LaunchSpecError(f'--in-process needs a plugin (module:Class) for node(s) {missing}')
    children = ProcessLauncher(plain, out=out) if plain else None
    if children:
        children.start()
    rclpy.init(args=[])  # not sys.argv: rcl would read NAME:=VALUE as a global remap
    executor = MultiThreadedExecutor()
    nodes = []
    code = 0
    try:
        for spec_node in ros_nodes:
            try:
                node = build_node(spec_node)
            except ValueError as exc:  # a parameter the node refuses (bad anatomy, range, ...)
                raise LaunchSpecError(f'node {spec_node.name!r}: {exc}') from exc
            nodes.append(node)
            executor.add_node(node)
        deadline = None if max_duration is None else time.monotonic() + max_duration
        while rclpy.ok() and (deadline is None or time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        try_shutdown()
        if children:
            children.request_stop()
            children.shutdown()
            code = children.exit_code
    return code


def build_parser() -> argparse.ArgumentParser:
    """Command line of ``cgail launch``."""
    parser = tool_parser('launch', __doc__, details=True)
    parser.add_argument('launch_file', help="launch file in ROS 2's YAML launch format (see "
                        'cgail_rig.launch_spec)')
    parser.add_argument('launch_arguments', nargs='*', metavar='NAME:=VALUE',
                        help="launch arguments over the file's defaults (e.g. anatomy:=DIR)")
    parser.add_argument('--only', nargs='+', metavar='NODE',
                        help='start only these nodes (by name; default: all)')
    parser.add_argument('--in-process', action='store_true',
                        help='run all ROS nodes in this process on one executor')
    parser.add_argument('--max-duration', type=float, default=None,
                        help='stop everything after this many seconds (default: run until '
                             'SIGINT/SIGTERM)')
    parser.add_argument('--shutdown-timeout', type=float, default=5.0,
                        help='seconds between SIGINT, SIGTERM and SIGKILL at shutdown')
    parser.add_argument('--allow-unset-discovery-range', action='store_true',
                        help='start even if ROS_AUTOMATIC_DISCOVERY_RANGE is unset')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail launch``; returns the exit status."""
    # intermixed: NAME:=VALUE may follow options (cgail launch FILE --in-process anatomy:=DIR)
    args = build_parser().parse_intermixed_args(argv)
    if not os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') and \
            not args.allow_unset_discovery_range:
        print('cgail launch: error: ROS_AUTOMATIC_DISCOVERY_RANGE is unset, so DDS would '
              'multicast onto the network; run through scripts/ws (sources scripts/env.sh) or '
              'pass --allow-unset-discovery-range', file=sys.stderr)
        return 2
    # (NAME:=VALUE after --only NODE... lands in --only; a node name never holds ':=')
    words = [*args.launch_arguments, *[w for w in args.only or () if ':=' in w]]
    only = [w for w in args.only or () if ':=' not in w]
    bad = [w for w in words if ':=' not in w or not w.partition(':=')[0]]
    if bad:
        print(f'cgail launch: error: launch arguments must read NAME:=VALUE, found {bad}',
              file=sys.stderr)
        return 2
    arguments = dict(w.split(':=', 1) for w in words)
    try:
        spec = load_launch_file(args.launch_file, arguments).select(only)
        if args.in_process:
            return run_in_process(spec, max_duration=args.max_duration)
        launcher = ProcessLauncher(spec, shutdown_timeout=args.shutdown_timeout)
    except LaunchSpecError as exc:
        print(f'cgail launch: error: {exc}', file=sys.stderr)
        return 2
    signal.signal(signal.SIGINT, launcher.request_stop)
    signal.signal(signal.SIGTERM, launcher.request_stop)
    launcher.start()
    return launcher.supervise(max_duration=args.max_duration)


if __name__ == '__main__':
    sys.exit(main())

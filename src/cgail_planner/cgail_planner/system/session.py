"""``invitro_session``: the simulated in-vitro session of the paper (section IV-B), end to end.

    scripts/ros2run cgail_planner invitro_session --out runs/invitro     # the paper's protocol
    scripts/ws python -m cgail_planner.system.session --trials 2 --policy model.onnx --mode dynamic

The whole simulated rig runs in THIS process (python-can virtual buses only connect objects of one
process), built from ``config/launch/sim_rig.yaml`` like the launcher's ``--in-process`` mode:
``phantom`` (simulated Aurora on a pty, regulator bank and sleeve driver on virtual CAN, the
catheter-in-aorta physics), the real ``aurora`` (ndicapi over the pty), ``pam_controller``,
``sleeve_driver``, ``teleop``, ``planner`` and the scripted ``operator``, on one executor
(``SingleThreadedExecutor`` by default, ``--threads``). Protocol: ``--trials`` trials following
the C-GAIL path, then as many following the centerline (``planner_type: centerline``), cycling
the 3 starts and 5 targets. Before each trial the catheter is reloaded (phantom reset to the
start pose, sleeve driver re-homed, a fresh planner); a trial ends when the operator stops
(target reached, or closest approach passed) or at the 3-minute limit, and is recorded to its
own bag (``cgail_planner.bags`` recorder). Then the offline metrics (``bag_metrics``) print the
markdown table with the paper's in-vitro numbers side by side and write the box plots.

**Time acceleration.** 20 trials of up to 3 minutes cannot run in real time, so the rig runs on
simulated time: the phantom steps the physics and the simulated devices by fixed simulated
increments, ``--time-scale`` (default 6) times faster than the wall clock, and publishes
``/clock``; every node runs with ``use_sim_time``, so their timers, stamps, the operator's
reaction delay and the 3-minute limit are in simulated seconds. The real nodes and the real
protocols stay in the loop (ndicapi over the pty, CAN frames, Joy -> teleop -> commands). What
does not scale by itself is set accordingly: the tracker polls the simulated Aurora on the wall
clock, so its ``rate_hz`` is ``--tracker-rate`` (40) times the time scale; the rig nodes' own
watchdogs use wall-clock time (they are only stricter in simulated time). When the CPU cannot
keep up, simulated time slows down rather than taking bigger steps.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import os
from pathlib import Path
import sys
import tempfile
import threading
import time
from typing import Any

TOPICS = ('em_tracker/tip_pose', 'planner/path', 'planner/goal', 'planner/next_waypoint',
          'planner/suggested_bend', 'phantom/tip_pose')
CONDITIONS = ('cgail', 'centerline')


def default_launch_file() -> Path:
    """``config/launch/sim_rig.yaml`` of this package (source tree or install share)."""
    here = Path(__file__).resolve().parents[2] / 'config' / 'launch' / 'sim_rig.yaml'
    if here.is_file():
        return here
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        cand = Path(prefix) / 'share' / 'cgail_planner' / 'config' / 'launch' / 'sim_rig.yaml'
        if prefix and cand.is_file():
            return cand
    return here


def default_policy(anatomy: str = 'default', mode: str = 'static') -> Path:
    """The committed C-GAIL policy for ``anatomy`` in ``mode`` (installed with the package):
    ``learning/models/cgail_<anatomy>_<mode>.onnx``, or the anatomy's static policy when there is
    no policy re-trained for that mode. The path may not exist (no policy for that anatomy)."""
    import cgail_planner.learning

    models = Path(cgail_planner.learning.__file__).resolve().parent / 'models'
    path = models / f'cgail_{anatomy}_{mode}.onnx'
    return path if path.is_file() else models / f'cgail_{anatomy}_static.onnx'


class SimRig:
    """The simulated rig's nodes in this process, spinning on a background executor.

    Args:
        launch_file: the rig's launch YAML (``sim_rig.yaml``).
        overrides: per node name, parameters applied over the launch file's.
        threads: executor threads (1: SingleThreadedExecutor).
        skip: nodes of the launch file not to start (e.g. ``gui`` unless asked for).
    """

    def __init__(self, launch_file: Path, overrides: dict[str, dict[str, Any]],
                 threads: int = 1, skip: frozenset[str] = frozenset()) -> None:
        import rclpy
        from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

        from cgail_planner.system.launch_spec import load_launch_file

        spec = load_launch_file(launch_file)
        self.spec = spec.select([n.name for n in spec.nodes if n.name not in skip])
        self.overrides = overrides
        rclpy.init()
        self.executor = SingleThreadedExecutor() if threads == 1 \
            else MultiThreadedExecutor(num_threads=threads)
        self.nodes: dict[str, Any] = {}
        self.errors: list[str] = []
        self._spin_lock = threading.Lock()
        self._stopping = threading.Event()
        self._retired: dict[str, list[Any]] = {}
        self._thread = threading.Thread(target=self._spin, name='rig_executor', daemon=True)
        try:
            first, *others = self.spec.nodes
            phantom = self.add(first.name)
            # the phantom's /clock runs before the other nodes exist, so none of them stamps
            # anything with a simulated time of 0
            self._thread.start()
            if hasattr(phantom, 'sim_time'):
                wait_until(lambda: phantom.sim_time > 0.2, 30.0)
            for spec_node in others:
                self.add(spec_node.name)
        except BaseException:
            self.close()
            raise
        self.session = rclpy.create_node('session', parameter_overrides=[
            rclpy.parameter.Parameter('use_sim_time', value=True)])
        self.executor.add_node(self.session)
        from geometry_msgs.msg import PoseStamped

        from cgail_planner.nodes import conversions as conv

        self._goal_pub = self.session.create_publisher(PoseStamped, 'planner/goal',
                                                       conv.COMMAND_QOS)

    def publish_goal(self, position: Any) -> None:
        """Publish the target (m, phantom frame) on ``planner/goal``, stamped now."""
        import numpy as np

        from cgail_planner.nodes import conversions as conv

        self._goal_pub.publish(conv.pose_msg(self.session.get_clock().now().to_msg(), 'phantom',
                                             np.asarray(position, dtype=float), np.eye(3)))

    def _spin(self) -> None:
        import traceback

        import rclpy
        from rclpy.executors import ExternalShutdownException

        while rclpy.ok() and not self._stopping.is_set():
            try:
                with self._spin_lock:  # nodes are replaced only between callbacks
                    self.executor.spin_once(timeout_sec=0.05)
            except (ExternalShutdownException, rclpy.executors.ShutdownException):
                return
            except Exception:
                self.errors.append(traceback.format_exc())
                print(f'invitro_session: a callback raised:\n{self.errors[-1]}', file=sys.stderr)

    def add(self, name: str, **extra: Any) -> Any:
        """Build node ``name`` of the launch file (plus ``extra`` parameters) and spin it."""
        from cgail_planner.system.launcher import build_node

        spec_node = next(n for n in self.spec.nodes if n.name == name)
        node = build_node(spec_node, {**self.overrides.get(name, {}), **extra}, lean=True)
        self.nodes[name] = node
        self.executor.add_node(node)
        return node

    def locked(self) -> threading.Lock:
        """Hold it to create or destroy entities from another thread: no callback runs and the
        executor is not between collecting its wait set and using it."""
        return self._spin_lock

    def replace(self, name: str, **extra: Any) -> Any:
        """Destroy node ``name`` and build it again with ``extra`` parameters."""
        with self._spin_lock:
            old = self.nodes.pop(name)
            self.executor.remove_node(old)
            # rclpy's executor may still hold the removed node's entities in its current wait
            # iteration: destroy it one replacement later, when that iteration is long gone
            for retired in self._retired.pop(name, []):
                retired.destroy_node()
            self._retired[name] = [old]
            return self.add(name, **extra)

    def close(self) -> None:
        """Stop spinning, destroy every node, shut rclpy down."""
        import rclpy

        self._stopping.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)
        self.executor.shutdown()
        retired = [n for nodes in self._retired.values() for n in nodes]
        for node in [*self.nodes.values(), *retired, getattr(self, 'session', None)]:
            if node is not None:
                node.destroy_node()
        self.nodes.clear()
        rclpy.try_shutdown()


def wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.05) -> bool:
    """Poll ``predicate`` on the wall clock until it holds or ``timeout_s`` passes."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return predicate()


def run_trial(rig: SimRig, condition: str, index: int, bag: Path, *, time_limit: float,
              mode: str, log: Callable[[str], None]) -> str:
    """One trial: reset, record, send the goal, wait for the operator; returns the outcome."""
    import rclpy

    from cgail_planner.bags.record import BagRecorder, RecorderConfig

    phantom, operator = rig.nodes['phantom'], rig.nodes['operator']
    # a fresh planner per trial: no latched path of the previous trial in this trial's bag
    planner = rig.replace('planner', planner_type=condition)
    # the catheter is reloaded between trials: the sleeve driver is re-homed (its catheter
    # position restarts at 0; it would otherwise reach position_max = 1 m after ~4 trials),
    # then the phantom puts the tip back at the start (the next reading is its reference)
    rig.replace('sleeve_driver')
    t_home = phantom.sim_time
    wait_until(lambda: phantom.sim_time - t_home > 0.5, 30.0)
    sc = phantom.world.scenarios
    start_id, target_id = index % len(sc.starts), index % len(sc.targets)
    phantom.reset_trial(start_id, target_id)
    operator.reset()
    t_reset = phantom.sim_time
    wait_until(lambda: phantom.sim_time - t_reset > 1.0, 30.0)  # poses from the new start
    with rig.locked():
        recorder = BagRecorder(rig.session, RecorderConfig(output=bag, topics=TOPICS,
                                                           condition=condition,
                                                           discovery_period=0.2))
    wait_until(lambda: len(recorder.topics) >= len(TOPICS), 5.0)
    time.sleep(0.3)  # let the new subscriptions match
    failed_before = planner.counts['failed_plans']
    goal = phantom.target_position()
    rig.publish_goal(goal)
    t0 = phantom.sim_time
    last_goal, last_print = t0, time.monotonic()
    outcome = ''
    while not outcome:
        time.sleep(0.05)
        if not rclpy.ok():  # SIGINT: rclpy's handler shut the context down
            with rig.locked():
                recorder.stop()
            raise KeyboardInterrupt
        now = phantom.sim_time
        if operator.done:
            outcome = operator.operator.reason
        elif planner.counts['failed_plans'] > failed_before and planner.follower is None \
                and operator.operator.state == 'idle':
            outcome = f'no path: {planner.last_error}'
        elif now - t0 > time_limit + 5.0:
            outcome = 'time limit (operator still running)'
        if mode == 'dynamic' and now - last_goal >= 1.0:
            last_goal = now
            rig.publish_goal(phantom.target_position())
        if time.monotonic() - last_print >= 2.0:
            last_print = time.monotonic()
            dist = float(((phantom.target_position() - phantom.physics.tip_position) ** 2)
                         .sum() ** 0.5)
            log(f'  [{condition} {index + 1}] t = {now - t0:6.1f} s (sim), tip-target '
                f'{dist * 1e3:6.1f} mm, inserted {phantom.physics.inserted * 1e3:6.1f} mm')
    time.sleep(0.2)
    with rig.locked():
        recorder.stop()
    return outcome


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``invitro_session``."""
    p = argparse.ArgumentParser(prog='invitro_session', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--trials', type=int, default=10, help='trials per condition (paper: 10)')
    p.add_argument('--anatomy', default='default', help='built-in anatomy name')
    p.add_argument('--mode', choices=('static', 'dynamic'), default='static',
                   help='rigid phantom or deformable beating wall')
    p.add_argument('--out', type=Path, default=Path('runs/invitro_session'),
                   help='output directory (bags/, metrics.md, metrics.csv, box plots)')
    p.add_argument('--policy', type=Path, default=None,
                   help='ONNX C-GAIL policy (export_onnx); default: the committed '
                        'learning/models/cgail_<anatomy>_<mode>.onnx (static if there is no '
                        'policy for the mode)')
    p.add_argument('--conditions', nargs='+', choices=CONDITIONS, default=list(CONDITIONS),
                   help='conditions to run, in order')
    p.add_argument('--time-scale', type=float, default=6.0,
                   help='simulated seconds per wall second (default 6)')
    p.add_argument('--time-limit', type=float, default=180.0,
                   help='trial time limit, simulated s (paper: 180)')
    p.add_argument('--physics-rate', type=float, default=50.0,
                   help='phantom physics, device and /clock rate, Hz of simulated time (the '
                        'pam and sleeve-driver control loops run at half of it)')
    p.add_argument('--tracker-rate', type=float, default=40.0,
                   help='EM tracker rate in simulated time, Hz (the Aurora: 40); the tracker '
                        'polls tracker_rate * time_scale times per wall second')
    p.add_argument('--threads', type=int, default=1,
                   help='executor threads (1: SingleThreadedExecutor, the fastest in rclpy)')
    p.add_argument('--launch-file', type=Path, default=None, help='rig launch YAML')
    p.add_argument('--seed', type=int, default=0, help='seed of the EM and stick noise')
    p.add_argument('--gui', action='store_true',
                   help='also start the guidance GUI (gui_node) and print its URL')
    p.add_argument('--gui-port', type=int, default=8780, help='port of the guidance GUI')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``invitro_session``; returns the exit status."""
    args = build_parser().parse_args(argv)
    if args.trials < 1:
        print(f'invitro_session: --trials must be >= 1, found {args.trials}', file=sys.stderr)
        return 2
    if not os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE'):
        print('invitro_session: ROS_AUTOMATIC_DISCOVERY_RANGE is unset (DDS would multicast); '
              'run through scripts/ws', file=sys.stderr)
        return 2
    if args.policy is None:
        args.policy = default_policy(args.anatomy, args.mode)
    if 'cgail' in args.conditions and not args.policy.is_file():
        print(f'invitro_session: the cgail condition needs --policy <model.onnx> (export_onnx), '
              f'found no file at {args.policy}', file=sys.stderr)
        return 2
    bags_dir = args.out / 'bags'
    if bags_dir.exists() and any(bags_dir.iterdir()):
        print(f'invitro_session: {bags_dir} already holds bags; choose another --out',
              file=sys.stderr)
        return 2

    def log(text: str) -> None:
        print(text, flush=True)

    tmp = tempfile.TemporaryDirectory(prefix='invitro_')
    link = str(Path(tmp.name) / 'aurora')
    common = {'use_sim_time': True}
    overrides = {
        'phantom': {**common, 'anatomy': args.anatomy, 'mode': args.mode, 'aurora_link': link,
                    'publish_clock': True, 'time_scale': args.time_scale, 'seed': args.seed,
                    'physics_rate_hz': args.physics_rate},
        'aurora': {**common, 'port': link,
                   'rate_hz': min(1000.0, args.tracker_rate * args.time_scale)},
        # The host control loops run at half the /clock rate: a sim-time timer fires on /clock
        # ticks, so its real period is a whole number of ticks (1-1.5 x the nominal period here).
        # The relay's return stroke commands error/period: an actual period >= 2x the nominal
        # one would make the sleeve oscillate around the stroke end instead of converging.
        'pam_controller': {**common, 'control_rate_hz': args.physics_rate / 2.0},
        'sleeve_driver': {**common, 'control_rate_hz': args.physics_rate / 2.0},
        'teleop': dict(common),
        'planner': {**common, 'anatomy': args.anatomy, 'mode': args.mode,
                    'policy_path': str(args.policy or ''), 'planner_type': args.conditions[0]},
        'operator': {**common, 'time_limit_s': args.time_limit, 'seed': args.seed},
        'gui': {**common, 'anatomy': args.anatomy, 'dynamic': args.mode == 'dynamic',
                'port': args.gui_port},
    }
    t_start = time.monotonic()
    log(f'invitro_session: building the simulated rig ({args.anatomy}, {args.mode}, '
        f'x{args.time_scale:g} simulated time); policy {args.policy}...')
    rig = SimRig(args.launch_file or default_launch_file(), overrides, threads=args.threads,
                 skip=frozenset() if args.gui else frozenset({'gui'}))
    if 'gui' in rig.nodes:
        log(f'invitro_session: guidance GUI on {rig.nodes["gui"].url} (open it in a browser)')
    outcomes: list[tuple[str, int, str]] = []
    try:
        if not wait_until(lambda: rig.nodes['planner'].last_pose is not None, 60.0):
            log('invitro_session: error: no tip pose from the tracker within 60 s')
            return 1
        for condition in args.conditions:
            for k in range(args.trials):
                bag = bags_dir / condition / f'{condition}_{k + 1:02d}'
                log(f'[{condition} trial {k + 1}/{args.trials}] recording to {bag}')
                outcome = run_trial(rig, condition, k, bag, time_limit=args.time_limit,
                                    mode=args.mode, log=log)
                outcomes.append((condition, k + 1, outcome))
                log(f'[{condition} trial {k + 1}/{args.trials}] {outcome} '
                    f'({time.monotonic() - t_start:.0f} s wall so far)')
    except KeyboardInterrupt:
        log('invitro_session: interrupted; evaluating the trials recorded so far')
    finally:
        rig.close()
        tmp.cleanup()
    if rig.errors:
        log(f'invitro_session: {len(rig.errors)} node callback(s) raised (tracebacks above)')
    return report(args.out, bags_dir, outcomes, log, wall_s=time.monotonic() - t_start,
                  callback_errors=len(rig.errors))


def report(out: Path, bags_dir: Path, outcomes: list[tuple[str, int, str]],
           log: Callable[[str], None], wall_s: float, callback_errors: int = 0) -> int:
    """Metrics of every evaluable trial bag: markdown table, CSV, box plots."""
    from cgail_planner.bags.errors import BagError
    from cgail_planner.bags.metrics_cli import evaluate_bags
    from cgail_planner.bags.report import box_plots, markdown_report, write_csv
    from cgail_planner.core.metrics import kruskal_by_condition, MetricsError

    trials = []
    skipped = []
    for bag in sorted(p for p in bags_dir.glob('*/*') if p.is_dir()):
        try:
            trials += evaluate_bags([bag], condition=bag.parent.name)
        except (BagError, MetricsError) as exc:
            skipped.append(f'{bag.name}: {exc}')
    if not trials:
        log('invitro_session: no trial could be evaluated')
        for s in skipped:
            log(f'  {s}')
        return 1
    tests = kruskal_by_condition(trials)
    text = markdown_report(trials, tests)
    lines = ['# Simulated in-vitro session', '',
             f'{len(outcomes)} trials, {wall_s:.0f} s wall time, callback errors: '
             f'{callback_errors}.', '', '## Outcomes', '',
             '| trial | condition | operator outcome |', '|---|---|---|']
    lines += [f'| {k} | {c} | {o} |' for c, k, o in outcomes]
    if skipped:
        lines += ['', '## Trials without metrics', ''] + [f'- {s}' for s in skipped]
    out.mkdir(parents=True, exist_ok=True)
    (out / 'metrics.md').write_text('\n'.join(lines) + '\n\n' + text)
    write_csv(trials, out / 'metrics.csv')
    png = box_plots(trials, tests, out / 'metrics_boxplot.png')
    log(text)
    log(f'invitro_session: wrote {out / "metrics.md"}, {out / "metrics.csv"} and {png} '
        f'({wall_s:.0f} s wall)')
    return 0


if __name__ == '__main__':
    sys.exit(main())

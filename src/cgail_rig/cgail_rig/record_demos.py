"""``cgail record-demos``: record your own demonstrations in the simulator, with a gamepad or
keyboard.

    cgail record-demos --anatomy default --out bags/demos/mine              # gamepad
    cgail record-demos --anatomy default --out bags/demos/mine --driver keyboard
    cgail record-demos --anatomy default --out runs/demos_scripted --driver scripted \\
        --episodes 10 --time-scale 8                                     # no person
    cgail train --preset cgail --demos bags/demos/mine --out runs/my_demos

Options: ``--anatomy NAME|PATH`` (a built-in name, a prepared anatomy directory or a mesh file
with its landmarks), ``--out DIR`` (the demo bag to create), ``--mode static|dynamic``,
``--episodes N`` (saved episodes; default 10), ``--order sequential|random``, ``--seed S``,
``--who NAME`` (recorded with each episode), ``--driver gamepad|keyboard|scripted``,
``--port P`` (the page; 0: any free port), ``--time-limit S`` (180 s), ``--pause S`` (2 s
between episodes), ``--time-scale X`` (simulated seconds per wall second; 1 = real time).

**The rig.** One process runs the simulated catheter as a live rig, driven through the same
topics as the in-vitro rig: a gamepad (``joy_node``, SDL) or the page's keyboard publishes
``sensor_msgs/Joy`` on ``joy``; ``teleop_node`` turns it into ``catheter/bend_command`` and
``catheter/insertion_command`` (deadman, rate-mode bend: :mod:`catheter_driver.core.teleop`);
the recorder node (:mod:`cgail_rig.nodes.record_demos_node`) maps those commands onto the
simulator's action once per control step (0.1 s) with the catheter model's own conversion and
steps :class:`~cgail_sim.env.CatheterNavEnv` (:mod:`cgail_learning.recorder`).
The nodes run on one simulated clock (:class:`~cgail_rig.lockstep.
LockstepExecutor`), paced at ``--time-scale`` times real time. ``--driver scripted`` puts the
scripted expert (:mod:`cgail_learning.expert`) at the gamepad instead: it publishes its
actions as stick deflections on ``joy`` and teleop runs in ``position`` bend mode.

**The page** (``http://127.0.0.1:8780/``; the URL is printed) is the guidance page of
``gui_node`` with the external and the internal view and the target, without a planned path:
the demonstrator navigates by themselves. It shows the episode, its start and target, the time
left, the commanded bend and the outcome. With no gamepad, its keyboard is the gamepad:

=======================  ==============================================================
key                      gamepad equivalent
=======================  ==============================================================
Space (hold)             deadman (left shoulder button): nothing moves while released
E / Q                    insert / retract (left stick up / down), 5 mm/s
W A S D or arrow keys    bend up / left / down / right (right stick), 0.5 rad/s
Esc or Backspace         discard the episode (gamepad: button 1, B)
=======================  ==============================================================

**Episodes** (:mod:`cgail_learning.recorder`): each starts at one of the scenario's
starts and targets (in order, or at random with ``--order random``), waits for the first
insertion and ends on success (the tip within 10 mm of the target), a non-minor collision,
leaving the anatomy, the time limit, or a discard (the same start and target come again).

**The bag** (``--out``) is a demonstration bag (:mod:`cgail_learning.demo_bags`:
``demo/episode``, ``demo/tip_pose``, ``demo/action``, ``demo/target``), rewritten after every
saved episode, so an interrupted recording keeps what it saved. Its ``metadata.yaml`` custom
data ``cgail_planner.record_demos`` holds who recorded each episode, the device
(``gamepad``, ``keyboard``, ``scripted``), the outcome and the duration. ``cgail train --demos
DIR`` takes it as it takes ``cgail make-demos``' bags (the successful episodes).

Exit status: 0 when done or interrupted (Ctrl-C; the bag holds the saved episodes), 2 on bad
input (one line on stderr), 1 when the rig fails.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import getpass
import json
import math
from pathlib import Path
import sys
import time
from typing import Any

from cgail_sim.cli_help import tool_parser

#: ros-args of the process: teleop's warnings (a rejected or stale Joy) are reported once by the
#: recorder node instead; joy_node's (no gamepad) stay on the console.
ROS_ARGS = ['--ros-args', '--disable-rosout-logs', '--log-level', 'teleop:=error']
DRIVERS = ('gamepad', 'keyboard', 'scripted')
#: Each node's own topic names -> the rig's (``-r`` rules), per node name: teleop and joy as
#: the rig's launch files remap them (docs/interfaces.md), the recorder in the place of the
#: tracker and the devices, the keyboard and the scripted expert as gamepads.
REMAPS: dict[str, dict[str, str]] = {
    'record_demos': {'~/tip_pose': 'em_tracker/tip_pose', '~/keyboard_joy': 'joy',
                     '~/joy': 'joy', '~/bend_command': 'catheter/bend_command',
                     '~/insertion_command': 'catheter/insertion_command'},
    'teleop': {'~/joy': 'joy', '~/insertion_command': 'catheter/insertion_command',
               '~/bend_command': 'catheter/bend_command'},
    'expert_joy': {'~/joy': 'joy'},
    'joy': {'~/joy': 'joy'},
}
MAX_TIME_SCALE = 1000.0


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``cgail record-demos``."""
    p = tool_parser('record-demos', __doc__)
    p.add_argument('--anatomy', default='default',
                   help='built-in anatomy name (default, elongated), prepared anatomy directory '
                        'or mesh file with its <stem>.yaml landmarks')
    p.add_argument('--out', type=Path, required=True, help='demo bag directory to create')
    p.add_argument('--mode', choices=('static', 'dynamic'), default='static',
                   help='rigid aorta (static) or deformable beating wall with a moving target '
                        '(dynamic)')
    p.add_argument('--episodes', type=int, default=10, help='episodes to save (default 10)')
    p.add_argument('--order', choices=('sequential', 'random'), default='sequential',
                   help='starts x targets in order (as cgail make-demos) or drawn with --seed')
    p.add_argument('--seed', type=int, default=0,
                   help="seed of the random order (and of the scripted driver's episodes)")
    p.add_argument('--who', default=None,
                   help='who records (default: the login name; "scripted expert" for '
                        '--driver scripted)')
    p.add_argument('--driver', choices=DRIVERS, default='gamepad',
                   help='gamepad (joy_node; the page keyboard works too), keyboard (the page '
                        'only) or scripted (the scripted expert at the gamepad)')
    p.add_argument('--port', type=int, default=8780, help='port of the page (0: any free one)')
    p.add_argument('--time-limit', type=float, default=180.0,
                   help='simulated seconds an episode may last (default 180)')
    p.add_argument('--pause', type=float, default=2.0,
                   help='simulated seconds between episodes (default 2)')
    p.add_argument('--time-scale', type=float, default=1.0,
                   help=f'simulated seconds per wall second (1: real time; up to '
                        f'{MAX_TIME_SCALE:g})')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail record-demos``."""
    args = build_parser().parse_args(argv)

    def fail(text: str, code: int = 2) -> int:
        print(f'cgail record-demos: error: {text}', file=sys.stderr, flush=True)
        return code

    if not (math.isfinite(args.time_scale) and 0.0 < args.time_scale <= MAX_TIME_SCALE):
        return fail(f'--time-scale: expected a number in (0, {MAX_TIME_SCALE:g}], found '
                    f'{args.time_scale}')
    if not 0 <= args.port <= 65535:
        return fail(f'--port: expected 0..65535, found {args.port}')
    who = args.who if args.who is not None else (
        'scripted expert' if args.driver == 'scripted' else getpass.getuser())
    from cgail_learning.errors import LearningError
    from cgail_learning.recorder import RecorderConfig
    from cgail_sim.anatomy_spec import resolve_anatomy

    try:
        config = RecorderConfig(episodes=args.episodes, order=args.order, seed=args.seed,
                                time_limit_s=args.time_limit, pause_s=args.pause, who=who)
        anatomy = resolve_anatomy(args.anatomy)
        if args.out.exists():
            raise ValueError(f'--out {args.out}: expected a new bag directory, found it '
                             'exists (choose another name or remove it)')
    except (ValueError, LearningError) as exc:
        option = {'episodes': '--episodes', 'order': '--order', 'seed': '--seed',
                  'time_limit_s': '--time-limit', 'pause_s': '--pause', 'who': '--who'}
        text = str(exc)
        first = text.split(' ', 1)[0]
        return fail(f'{option[first]}: {text}' if first in option else text)
    try:
        return _record(args, config, anatomy)
    except (ValueError, LearningError, OSError) as exc:
        return fail(str(exc), 1)


def _refuse_device_nodes() -> None:
    """A rig's device nodes on this ROS domain would receive teleop's commands: refuse.

    Raises:
        ValueError: naming them.
    """
    from cgail_rig.domain import foreign_device_nodes, requested_domain

    domain = requested_domain() or 0
    found = foreign_device_nodes(domain, 0.5)
    if found:
        raise ValueError(f'ROS domain {domain} has device node(s) {", ".join(found)} (a real '
                         f'rig?) that would receive teleop\'s catheter commands: expected a '
                         f'domain without them (set ROS_DOMAIN_ID)')


def _record(args: argparse.Namespace, config: Any, anatomy: Any) -> int:
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from catheter_driver.nodes.teleop_node import TeleopNode
    from cgail_gui.config import GuiConfig
    from cgail_gui.recording import RecordingPage
    from cgail_learning.recorder import DemoRecorder, EpisodeEnd
    from cgail_rig.lockstep import LockstepExecutor
    from cgail_rig.nodes.record_demos_node import ExpertJoyNode, JoyLayout, RecorderNode
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    def log(text: str) -> None:
        print(f'cgail record-demos: {text}', flush=True)

    t_build = time.monotonic()
    base = EnvConfig(mode=args.mode, anatomy=anatomy)
    env = CatheterNavEnv(EnvConfig(mode=args.mode, anatomy=anatomy,
                                   max_steps=math.ceil(config.time_limit_s / base.dt) + 10))
    replay_env = None if args.mode == 'static' else CatheterNavEnv(
        EnvConfig(mode='static', anatomy=anatomy))
    recorder = DemoRecorder(env, config, args.out, anatomy=args.anatomy, driver=args.driver,
                            replay_env=replay_env,
                            extra={'time_scale': args.time_scale, 'anatomy': args.anatomy})
    _refuse_device_nodes()
    layout = JoyLayout()
    page = RecordingPage(
        GuiConfig(port=args.port, anatomy='', dynamic=args.mode == 'dynamic',
                  trial_limit_s=config.time_limit_s,
                  success_radius_m=env.config.reward.epsilon, bags_dir=''),
        env.anatomy, env.unwrapped.engine.walls[0],  # type: ignore[attr-defined]
        lambda level, text: None if level == 'info' else log(text))
    if page.missing:
        log(f'three.js is not installed ({page.missing} missing): run npm ci in '
            'src/cgail_gui/web; the 3D views will not load')
    started = time.monotonic()

    def on_end(end: EpisodeEnd) -> None:
        what = 'saved' if end.saved else 'not saved'
        note = f' (saved as unsuccessful: {end.note})' if end.note else ''
        log(f'episode {recorder.saved}/{config.episodes}: {end.outcome} after {end.steps} '
            f'steps, {what}{note}; {recorder.successes} successful, {recorder.discarded} '
            f'discarded, {time.monotonic() - started:.1f} s')

    def remapped(name: str) -> list[str]:
        return ['--ros-args', *(w for rule in REMAPS[name].items()
                                for w in ('-r', ':='.join(rule)))]

    rclpy.init(args=ROS_ARGS, signal_handler_options=SignalHandlerOptions.NO)
    nodes: list[Any] = []
    errors: list[str] = []
    executor = LockstepExecutor(period_s=env.config.dt, on_error=errors.append)
    lean: dict[str, Any] = {'start_parameter_services': False, 'enable_rosout': False}
    try:
        from rclpy.parameter import Parameter

        teleop_overrides = [Parameter('enable_button', value=layout.enable_button)]
        if args.driver == 'scripted':  # the expert's actions are bends: position mode
            teleop_overrides += [Parameter('bend_mode', value='position'),
                                 Parameter('scale_bend', value=float(env.config.theta_max))]
        node = RecorderNode(recorder, page, layout, on_end=on_end, report=log,
                            cli_args=remapped('record_demos'), **lean)
        nodes.append(node)
        nodes.append(TeleopNode(parameter_overrides=teleop_overrides,
                                cli_args=remapped('teleop'), **lean))
        if args.driver == 'scripted':
            nodes.append(ExpertJoyNode(recorder, layout, seed=config.seed,
                                       period_s=env.config.dt, cli_args=remapped('expert_joy'),
                                       **lean))
        elif args.driver == 'gamepad':
            from catheter_driver.nodes.joy_node import JoyNode

            rate = min(1000.0, 20.0 * max(1.0, args.time_scale))
            nodes.append(JoyNode(parameter_overrides=[
                Parameter('autorepeat_rate', value=rate),
                Parameter('poll_rate_hz', value=1.0 / env.config.dt)],
                cli_args=remapped('joy'), **lean))
        for n in nodes:
            executor.add_node(n)
        executor.add_hook(node.world_step)
        executor.seal()
        port = page.start()
        log(f'{config.episodes} episodes in {args.anatomy} ({args.mode}), driver '
            f'{args.driver}, by {config.who!r}, into {args.out}; page on '
            f'http://127.0.0.1:{port}/ (time scale {args.time_scale:g}; built in '
            f'{time.monotonic() - t_build:.1f} s)')
        if args.driver == 'keyboard':
            log('keyboard: hold Space (deadman), E/Q insert/retract, WASD or arrows bend, '
                'Esc or Backspace discards the episode')
        interrupted = False
        lag = _run(executor, recorder, env.config.dt / args.time_scale)
        if errors:
            log(f'a node failed; {recorder.saved} episodes saved in {args.out}:\n{errors[0]}')
            return 1
    except KeyboardInterrupt:
        interrupted = True
        lag = 0.0
    finally:
        page.stop()
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()
    summary = {'out': str(args.out), 'saved': recorder.saved, 'successes': recorder.successes,
               'discarded': recorder.discarded, 'interrupted': interrupted,
               'wall_s': round(time.monotonic() - started, 1), 'max_lag_s': round(lag, 3),
               'rejected_inputs': node.rejected if nodes else {}}
    if interrupted:
        log(f'interrupted: {recorder.saved} episodes saved in {args.out}' if recorder.saved
            else 'interrupted before any episode was saved: no bag written')
    print(json.dumps(summary), flush=True)
    return 0


def _run(executor: Any, recorder: Any, period_wall: float) -> float:
    """Tick until every episode is saved, one tick per ``period_wall`` wall seconds (behind
    by more than a second: carry on from now). Returns the largest lag, s."""
    t0 = time.monotonic()
    k = 0
    lag = 0.0
    while not recorder.done and not executor.errors:
        executor.tick()
        k += 1
        due = t0 + k * period_wall
        now = time.monotonic()
        if now < due:
            time.sleep(due - now)
        else:
            lag = max(lag, now - due)
            if now - due > 1.0:
                t0, k = now, 0
    return lag


if __name__ == '__main__':
    sys.exit(main())

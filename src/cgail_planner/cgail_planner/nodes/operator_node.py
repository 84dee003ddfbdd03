"""Operator node (``operator``): a scripted person at the gamepad, following the guidance.

Run: ``ros2 run cgail_planner operator_node`` (pip-only: ``scripts/ros2run cgail_planner
operator_node``). Behaviour: :mod:`cgail_planner.core.operator`. Its topics are its own,
under its name (``~/path``, ``~/suggested_bend``, ``~/next_waypoint``, ``~/goal``,
``~/tip_pose``, ``~/joy``, ``~/done``); below they are named as in the rig, whose launch files
remap them (docs/interfaces.md).

* Starts a trial when a ``planner/path`` arrives while idle (the clinician begins once the path
  is shown); ``operator/reset`` (std_srvs/Trigger) makes it idle again for the next trial.
* Sees ``planner/suggested_bend``, ``planner/next_waypoint`` (the heading error towards it), the
  path (``planner/path``: aims ``look_ahead`` m beyond the waypoint), the target
  (``planner/goal``) and the tip (``em_tracker/tip_pose``); acts after its reaction delay.
* ``skill`` (the session sets it per trial from the practice trials before it) blends the
  ``novice_`` parameters into the practised ones.
* Publishes ``joy`` (sensor_msgs/Joy, ``teleop_node``'s layout: deadman button
  ``enable_button`` held while running, insertion on ``axis_insertion``, bend on
  ``axis_bend_alpha``/``axis_bend_gamma`` for teleop's ``position`` bend mode) at ``rate_hz``,
  and ``operator/done`` (std_msgs/Bool, latched) when it stops (target reached, closest approach
  passed, or the 3-minute limit).
"""

from __future__ import annotations

import math

from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState, Joy
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from cgail_node_utils.entry_point import run_node
from cgail_planner.core.errors import InvalidInputError
from cgail_planner.core.guidance import PathFollower
from cgail_planner.core.operator import (
    aimed_bend,
    OperatorConfig,
    Percept,
    ScriptedOperator,
    SupervisingOperator,
)
from cgail_planner.nodes import conversions as conv

#: ``role``: the person drives, or supervises the autonomy (shared autonomy).
ROLES = ('drive', 'supervise')


class OperatorNode(Node):
    """Thin wrapper around :class:`ScriptedOperator`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('operator', **kwargs)
        d = OperatorConfig()
        self.config = OperatorConfig(
            reaction_delay_s=conv.declare(self, 'reaction_delay_s', d.reaction_delay_s,
                                          'practised delay between display and action, s',
                                          lo=0.0, hi=2.0),
            novice_reaction_delay_s=conv.declare(
                self, 'novice_reaction_delay_s', d.novice_reaction_delay_s,
                'first-trial reaction delay, s', lo=0.0, hi=2.0),
            max_stick_rate=conv.declare(self, 'max_stick_rate', d.max_stick_rate,
                                        'largest stick speed, deflections/s', lo=0.01, hi=100.0),
            stick_noise=conv.declare(self, 'stick_noise', d.stick_noise,
                                     'practised stick noise standard deviation', lo=0.0, hi=0.5),
            novice_stick_noise=conv.declare(self, 'novice_stick_noise', d.novice_stick_noise,
                                            'first-trial stick noise', lo=0.0, hi=0.5),
            look_ahead=conv.declare(self, 'look_ahead', d.look_ahead,
                                    'aim this arc length beyond the next waypoint, m',
                                    lo=0.0, hi=0.1),
            correction_gain=conv.declare(self, 'correction_gain', d.correction_gain,
                                         'practised fraction of the aimed bend', lo=0.0, hi=2.0),
            novice_correction_gain=conv.declare(
                self, 'novice_correction_gain', d.novice_correction_gain,
                'first-trial correction gain', lo=0.0, hi=2.0),
            stick_frequency=conv.declare(self, 'stick_frequency', d.stick_frequency,
                                         'natural frequency of the bend stick response, rad/s '
                                         '(0: none)', lo=0.0, hi=100.0),
            stick_damping=conv.declare(self, 'stick_damping', d.stick_damping,
                                       'practised damping ratio of the bend stick response',
                                       lo=0.01, hi=0.99),
            novice_stick_damping=conv.declare(self, 'novice_stick_damping',
                                              d.novice_stick_damping,
                                              'first-trial damping ratio', lo=0.01, hi=0.99),
            skill=conv.declare(self, 'skill', d.skill,
                               'skill level: 0 novice, 1 practised', lo=0.0, hi=1.0),
            max_insertion_fraction=conv.declare(
                self, 'max_insertion_fraction', d.max_insertion_fraction,
                'largest insertion stick deflection', lo=0.01, hi=1.0),
            min_insertion_fraction=conv.declare(
                self, 'min_insertion_fraction', d.min_insertion_fraction,
                'insertion deflection close to the target', lo=0.01, hi=1.0),
            slow_down_distance=conv.declare(self, 'slow_down_distance', d.slow_down_distance,
                                            'slow down within this distance of the target, m',
                                            lo=0.001, hi=0.2),
            bend_scale=conv.declare(self, 'bend_scale', d.bend_scale,
                                    "bend at full deflection, rad (= teleop's scale_bend)",
                                    lo=0.01, hi=math.pi / 2),
            stop_distance=conv.declare(self, 'stop_distance', d.stop_distance,
                                       'stop within this distance of the target, m',
                                       lo=1e-4, hi=0.05),
            epsilon=conv.declare(self, 'epsilon', d.epsilon, 'success radius, m',
                                 lo=1e-4, hi=0.1),
            overshoot=conv.declare(self, 'overshoot', d.overshoot, 'within epsilon, stop when '
                                   'the distance grew this much, m', lo=1e-4, hi=0.05),
            time_limit_s=conv.declare(self, 'time_limit_s', d.time_limit_s,
                                      'trial time limit, s', lo=1.0, hi=3600.0))
        self.enable_button = conv.declare(self, 'enable_button', 4, 'deadman button index',
                                          lo=0, hi=31)
        self.axes = (conv.declare(self, 'axis_insertion', 1, 'Joy axis of insertion', lo=0,
                                  hi=31),
                     conv.declare(self, 'axis_bend_alpha', 4, 'Joy axis of bend_alpha', lo=0,
                                  hi=31),
                     conv.declare(self, 'axis_bend_gamma', 3, 'Joy axis of bend_gamma', lo=0,
                                  hi=31))
        if len(set(self.axes)) != 3:
            raise ValueError(f'axis_insertion, axis_bend_alpha and axis_bend_gamma must differ, '
                             f'found {self.axes}')
        rate = conv.declare(self, 'rate_hz', 20.0, 'Joy publishing rate, Hz', lo=1.0, hi=200.0)
        seed = conv.declare(self, 'seed', 0, 'seed of the stick noise', lo=0, hi=2**31 - 1)
        self.role = conv.declare(self, 'role', 'drive', "'drive' (the person drives through "
                                 "teleop) or 'supervise' (shared autonomy: deadman held, "
                                 'corrects only beyond supervise_threshold)')
        if self.role not in ROLES:
            raise ValueError(f'role: expected one of {ROLES}, found {self.role!r}')
        threshold = conv.declare(self, 'supervise_threshold', 0.005, "'supervise': deviation "
                                 'from the path beyond which the person corrects, m',
                                 lo=1e-4, hi=0.05)
        correction_scale = conv.declare(self, 'supervise_bend_scale', 0.5, "'supervise': bend "
                                        'the autonomy adds at full deflection, rad (its '
                                        'shared_scale_bend)', lo=0.01, hi=math.pi / 2)
        self.operator = ScriptedOperator(self.config, seed) if self.role == 'drive' else \
            SupervisingOperator(self.config, threshold, correction_scale, seed)
        self.goal: np.ndarray | None = None
        self.tip: np.ndarray | None = None
        self.heading: np.ndarray | None = None
        self.rotation: np.ndarray | None = None
        self.waypoint: np.ndarray | None = None
        self.path: PathFollower | None = None
        self._n_axes = max(self.axes) + 1
        self._n_buttons = self.enable_button + 1
        self._was_running = False

        self._joy_pub = self.create_publisher(Joy, '~/joy', conv.SENSOR_QOS)
        self._joy_msg = Joy()
        self._done_pub = self.create_publisher(Bool, '~/done', conv.LATCHED_QOS)
        self.create_subscription(Path, '~/path', self._on_path, conv.LATCHED_QOS)
        self.create_subscription(JointState, '~/suggested_bend', self._on_bend, conv.SENSOR_QOS)
        self.create_subscription(PointStamped, '~/next_waypoint', self._on_waypoint,
                                 conv.SENSOR_QOS)
        self.create_subscription(PoseStamped, '~/goal', self._on_goal, conv.COMMAND_QOS)
        self.create_subscription(PoseStamped, '~/tip_pose', self._on_tip, conv.SENSOR_QOS)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_timer(1.0 / rate, self._on_tick)
        self._done_pub.publish(Bool(data=False))

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # ------------------------------------------------------------------ trial control
    def reset(self) -> None:
        """Idle again (the next planner/path starts a new trial)."""
        self.operator.reset()
        self.goal = None
        self.tip = None
        self.waypoint = None
        self.path = None
        self._was_running = False
        self._done_pub.publish(Bool(data=False))

    @property
    def done(self) -> bool:
        """Whether the current trial has ended."""
        return self.operator.state == 'done'

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response):
        self.reset()
        response.success = True
        response.message = 'operator idle'
        return response

    # ------------------------------------------------------------------ inputs
    def _on_path(self, msg: Path) -> None:
        try:
            self.path = PathFollower(conv.path_points(msg))
        except ValueError:  # empty or degenerate: aim at the suggested bend as shown
            self.path = None
        if self.operator.state == 'idle' and msg.poses:
            self.operator.start(self._now())
            self.get_logger().info('path shown: operator starts the trial')

    def _on_goal(self, msg: PoseStamped) -> None:
        goal = conv.point_from_pose_msg(msg)
        if np.isfinite(goal).all():
            self.goal = goal

    def _on_tip(self, msg: PoseStamped) -> None:
        try:
            self.tip, rotation = conv.pose_from_msg(msg)
        except InvalidInputError:
            return
        self.rotation = rotation
        self.heading = rotation[:, 1]

    def _on_bend(self, msg: JointState) -> None:
        if self.goal is None or self.tip is None:
            return
        try:
            alpha, gamma = conv.joint_positions(msg, conv.BEND_JOINTS)
        except InvalidInputError as exc:
            self.get_logger().warning(f'suggested bend ignored: {exc}',
                                      throttle_duration_sec=2.0)
            return
        heading_error = 0.0
        bend = (alpha, gamma)
        if self.waypoint is not None and self.path is not None and self.rotation is not None:
            bend = aimed_bend(self.path, self.tip, self.rotation, self.waypoint, bend,
                              self.config.look_ahead)
        if self.waypoint is not None and self.heading is not None:
            to_wp = self.waypoint - self.tip
            n = math.sqrt(float(to_wp @ to_wp))  # = np.linalg.norm(to_wp)
            if n > 1e-9:
                heading_error = math.acos(max(-1.0, min(1.0, float(self.heading @ to_wp) / n)))
        deviation = 0.0
        if self.role == 'supervise' and self.path is not None:
            _, _, closest = self.path.project(self.tip)
            deviation = float(np.linalg.norm(closest - self.tip))
        to_goal = self.goal - self.tip
        self.operator.perceive(Percept(t=self._now(), bend=bend,
                                       heading_error=heading_error,
                                       distance=math.sqrt(float(to_goal @ to_goal)),
                                       deviation=deviation))

    def _on_waypoint(self, msg: PointStamped) -> None:
        self.waypoint = np.array([msg.point.x, msg.point.y, msg.point.z])

    # ------------------------------------------------------------------ output
    def _on_tick(self) -> None:
        sticks = self.operator.step(self._now())
        running = self.operator.state == 'running'
        if not running and not self._was_running:
            return
        axes = [0.0] * self._n_axes
        axes[self.axes[0]] = sticks.insertion
        axes[self.axes[1]] = sticks.alpha
        axes[self.axes[2]] = sticks.gamma
        buttons = [0] * self._n_buttons
        buttons[self.enable_button] = 1 if sticks.deadman else 0
        joy = self._joy_msg  # refilled: a publish serializes before it returns
        joy.header.stamp = self.get_clock().now().to_msg()
        joy.header.frame_id = 'joy'
        joy.axes, joy.buttons = axes, buttons
        self._joy_pub.publish(joy)
        if self._was_running and not running:
            self.get_logger().info(f'operator stopped: {self.operator.reason}')
            self._done_pub.publish(Bool(data=True))
        self._was_running = running


def main(args: list[str] | None = None) -> None:
    """Console script ``operator_node``."""
    run_node(OperatorNode, 'operator_node', args)


if __name__ == '__main__':
    main()

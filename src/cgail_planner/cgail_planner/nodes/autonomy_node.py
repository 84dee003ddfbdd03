"""Autonomy node (``autonomy``): the planner closes the loop, under the safety supervisor.

Run: ``ros2 run cgail_planner autonomy_node`` (pip-only: ``scripts/ros2run cgail_planner
autonomy_node``); docs/guides/autonomy.md says what to check before a first insertion. Its
topics are its own, under its name; below they are named as in the rig (docs/interfaces.md).

**One node hosts the controller and the supervisor** (:mod:`cgail_planner.core.autonomy`,
:mod:`cgail_planner.core.safety`): every command is computed and then passed through
:meth:`~cgail_planner.core.safety.Supervisor.tick` in the same timer callback, so no command
can reach ``catheter/insertion_command`` or ``catheter/bend_command`` without the supervisor,
no second publisher has to be arbitrated on them, and a stop costs no message hop. What a
separate supervisor process would add, surviving this process, the device nodes already give:
``sleeve_driver`` stops after 0.2 s and ``pam_controller`` vents after 0.5 s without commands.

* ``em_tracker/tip_pose`` (sensor): the tracked tip (frame ``frame_id``; NaN/inf or non-unit
  poses are rejected and count as no pose); ``planner/path`` (latched): the path to track and
  measure the deviation from; ``planner/goal`` (command): the target; ``planner/next_waypoint``
  (sensor): the planner's guidance, its liveness; ``joy`` (sensor): the deadman
  (``enable_button``) and, in ``shared`` mode, the person's corrections (teleop's layout);
  ``/diagnostics``: the device nodes' health (:data:`DEVICES`: a status at level ERROR stops
  with ``device_fault``, one at OK or WARN clears it).
* Every ``1 / rate_hz`` s: the controller's command from the latest pose (``controller``:
  ``path`` or ``policy``; ``shared``: corrected by the sticks,
  :func:`~cgail_planner.core.autonomy.shared_command`), through the supervisor, out on
  ``catheter/insertion_command`` (``insertion`` velocity, m/s) and ``catheter/bend_command``
  (``bend_alpha``, ``bend_gamma``, rad). Nothing is published while ``idle``.
* ``autonomy/state`` (std_msgs/String, latched): ``idle``, ``running``, ``done`` (at the goal:
  insertion 0) or ``stopped:<reason>`` (:data:`~cgail_planner.core.safety.STOP_REASONS`);
  ``/diagnostics`` carries the message (``autonomy: supervisor``), at once on every change.
* Services: ``autonomy/resume`` (std_srvs/Trigger): engage, or resume after a stop; refused,
  with the conditions that hold, while any does. ``autonomy/estop`` (std_srvs/SetBool): true
  stops at once (latched); false releases it (resume still needed). ``autonomy/reset``
  (Trigger): back to ``idle`` for a new trial (a session's, like ``operator/reset``).
* ``autostart``: engage by itself once, from ``idle``, as soon as nothing holds (a simulated
  session); never after a stop.
"""

from __future__ import annotations

from dataclasses import fields
import math
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState, Joy
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

from cgail_node_utils.entry_point import run_node
from cgail_node_utils.parameters import declare
from cgail_planner.core.autonomy import (
    AUTONOMY_MODES,
    AutonomyConfig,
    CONTROLLERS,
    PathTracker,
    policy_planner,
    PolicyController,
    shared_command,
    SharedConfig,
)
from cgail_planner.core.errors import ContractError, InvalidInputError, PolicyLoadError
from cgail_planner.core.safety import Command, SafetyConfig, Supervisor
from cgail_planner.nodes import conversions as conv
from cgail_sim.ftl_model import CatheterConfig
from cgail_sim.mesh_io import AnatomyError

#: Read-only limits of the supervisor: name -> (description with unit, lo, hi).
LIMITS: dict[str, tuple[str, float, float]] = {
    'tracking_timeout_s': ('stop without a valid EM pose for this long, s', 0.001, 10.0),
    'max_insertion_speed': ('cap of the insertion speed, m/s', 1e-4, 0.005),
    'max_bend': ('cap of the bend magnitude, rad', 1e-3, math.pi / 2),
    'max_bend_rate': ('cap of the bend rate, also the ramp to straight on a stop, rad/s',
                      1e-3, 10.0),
    'max_wall_speed': ('fastest the beating wall carries the tip (pose-jump bound), m/s',
                       0.0, 1.0),
    'pose_jump_slack': ('distance added to the pose-jump bound (EM noise), m', 1e-4, 0.05),
    'max_path_deviation': ('stop when the tip is further from the path, m', 1e-4, 0.05),
    'stall_window_s': ('window of the stall (contact/buckling) estimate, s', 0.1, 30.0),
    'stall_min_commanded': ('commanded insertion over the window before the stall test '
                            'applies, m', 1e-4, 0.1),
    'stall_min_ratio': ('stop when the tip advanced less than this share of the commanded '
                        'insertion', 0.01, 0.99),
    'lumen_margin': ('stop when the tip centre is further beyond the wall, m', 0.0, 0.02),
    'command_timeout_s': ('stop without a fresh controller command for this long, s',
                          0.001, 10.0),
    'planner_timeout_s': ('stop without planner output (path, guidance) for this long, s',
                          0.001, 60.0),
    'tick_timeout_s': ("stop when the supervisor's tick is this late, s", 0.001, 10.0),
    'joy_timeout_s': ('a deadman whose Joy is older than this is released, s', 0.001, 10.0),
}


#: Device nodes whose ``/diagnostics`` the supervisor watches: the status name's prefix
#: before ':' (``pam_controller: regulator bank``).
DEVICES = ('pam_controller', 'sleeve_driver', 'aurora')


class AutonomyNode(Node):
    """Thin wrapper around a controller and the :class:`Supervisor` (module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('autonomy', **kwargs)
        s, a, sh = SafetyConfig(), AutonomyConfig(), SharedConfig()
        self.controller_name = declare(self, 'controller', 'path', "'path' (pure pursuit on "
                                       "the planned path) or 'policy' (the ONNX policy)",
                                       read_only=True)
        self.autonomy_mode = declare(self, 'autonomy_mode', 'autonomous', "'autonomous' or "
                                     "'shared' (the person's sticks correct it)", read_only=True)
        policy_path = declare(self, 'policy_path', '', "ONNX policy (controller 'policy')",
                              read_only=True)
        anatomy = declare(self, 'anatomy', 'default', 'the registered anatomy: a built-in name, '
                          'a prepared anatomy directory or a mesh file', read_only=True)
        self.mode = declare(self, 'mode', 'static', "'static' or 'dynamic' (beating wall)",
                            read_only=True)
        for name, value, allowed in (('controller', self.controller_name, CONTROLLERS),
                                     ('autonomy_mode', self.autonomy_mode, AUTONOMY_MODES),
                                     ('mode', self.mode, ('static', 'dynamic'))):
            if value not in allowed:
                raise ValueError(f'{name}: expected one of {allowed}, found {value!r}')
        self.frame_id = declare(self, 'frame_id', 'phantom', 'frame of poses, paths and goals')
        rate = declare(self, 'rate_hz', 40.0, 'controller and supervisor tick rate, Hz',
                       lo=1.0, hi=500.0, read_only=True)
        self.autostart = declare(self, 'autostart', False, 'engage once, from idle, as soon as '
                                 'nothing holds (a simulated session)', read_only=True)
        deadman = declare(self, 'deadman_required', s.deadman_required, 'run only while the '
                          'Joy deadman is held', read_only=True)
        self.enable_button = declare(self, 'enable_button', 4, 'deadman button index', lo=0,
                                     hi=31, read_only=True)
        self.axes = tuple(declare(self, f'axis_{n}', d, f'Joy axis of {n}', lo=0, hi=31,
                                  read_only=True)
                          for n, d in (('insertion', 1), ('bend_alpha', 4), ('bend_gamma', 3)))
        if len(set(self.axes)) != 3:
            raise ValueError(f'axis_insertion, axis_bend_alpha, axis_bend_gamma: expected three '
                             f'different axes, found {self.axes}')
        limits = {n: declare(self, n, float(getattr(s, n)), d, lo=lo, hi=hi, read_only=True)
                  for n, (d, lo, hi) in LIMITS.items()}
        tuning = {f.name: declare(self, f.name, float(getattr(a, f.name)), f'controller: '
                                  f'{f.name} (AutonomyConfig)', lo=0.0, hi=1.0, read_only=True)
                  for f in fields(AutonomyConfig) if f.name != 'max_bend'}
        self.shared = SharedConfig(**{f.name: declare(
            self, f'shared_{f.name}', float(getattr(sh, f.name)), f'shared mode: {f.name} '
            '(SharedConfig)', lo=0.0, hi=2.0, read_only=True) for f in fields(SharedConfig)})
        diag_period = declare(self, 'diagnostics_period_s', 1.0, 'period of /diagnostics, s',
                              lo=0.05, hi=60.0)

        from cgail_sim.anatomy_spec import anatomy_identity
        from cgail_sim.wall import DeformableWall, StaticWall
        from cgail_sim.worlds import load_world

        world = load_world(anatomy)
        self.wall = StaticWall(world.anatomy) if self.mode == 'static' \
            else DeformableWall(world.anatomy)
        catheter = CatheterConfig()
        config = AutonomyConfig(**tuning, max_bend=limits['max_bend'])
        if self.controller_name == 'policy':
            from cgail_planner.core.onnx_policy import OnnxPolicy

            if not policy_path:
                raise PolicyLoadError("policy_path: expected an ONNX policy for controller "
                                      "'policy', found ''")
            label, anatomy_hash = anatomy_identity(anatomy)
            planner = policy_planner(OnnxPolicy(policy_path), world, self.wall, anatomy=label,
                                     anatomy_hash=anatomy_hash, mode=self.mode)
            self.controller: PathTracker | PolicyController = PolicyController(planner, config)
            catheter = planner.config.catheter
        else:
            self.controller = PathTracker(config, catheter)
        self.catheter = catheter
        self.supervisor = Supervisor(SafetyConfig(
            **limits, deadman_required=deadman, segment_length=catheter.segment_length,
            catheter_radius=catheter.radius), self.wall)
        self._pose: tuple[np.ndarray, np.ndarray] | None = None
        self._pose_t = -math.inf
        self._sticks = (0.0, 0.0, 0.0)
        self._engaged_once = False
        self.counts = dict(rejected_poses=0, rejected_inputs=0, controller_errors=0)
        self.last_error = ''
        self.last_output: Command | None = None
        self._state = ''

        self._ins_pub = self.create_publisher(JointState, '~/insertion_command',
                                              conv.COMMAND_QOS)
        self._bend_pub = self.create_publisher(JointState, '~/bend_command', conv.COMMAND_QOS)
        self._state_pub = self.create_publisher(String, '~/state', conv.LATCHED_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                               conv.DIAGNOSTICS_QOS)
        self.create_subscription(PoseStamped, '~/tip_pose', self._on_tip_pose, conv.SENSOR_QOS)
        self.create_subscription(Path, '~/path', self._on_path, conv.LATCHED_QOS)
        self.create_subscription(PoseStamped, '~/goal', self._on_goal, conv.COMMAND_QOS)
        self.create_subscription(PointStamped, '~/next_waypoint', self._on_waypoint,
                                 conv.SENSOR_QOS)
        self.create_subscription(Joy, '~/joy', self._on_joy, conv.SENSOR_QOS)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics,
                                 conv.DIAGNOSTICS_QOS)
        self.create_service(Trigger, '~/resume', self._on_resume)
        self.create_service(SetBool, '~/estop', self._on_estop)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self._period = 1.0 / rate
        self.create_timer(self._period, self._on_tick)
        self.create_timer(diag_period, self._publish_diagnostics)
        if self.mode == 'dynamic':
            self.create_timer(0.1, self._on_wall_timer)
        self._publish_state()

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    @property
    def state(self) -> str:
        """``idle``, ``running``, ``done`` or ``stopped:<reason>`` (``autonomy/state``)."""
        sup = self.supervisor
        if sup.state == 'stopped' and sup.stop is not None:
            return f'stopped:{sup.stop.reason}'
        return 'done' if sup.state == 'running' and self.controller.done else sup.state

    # ------------------------------------------------------------------ inputs
    def _on_tip_pose(self, msg: PoseStamped) -> None:
        now = self._now()
        try:
            if msg.header.frame_id not in ('', self.frame_id):
                raise InvalidInputError(f'tip pose frame: expected {self.frame_id!r}, found '
                                        f'{msg.header.frame_id!r}')
            self._pose = conv.pose_from_msg(msg)
        except InvalidInputError as exc:
            self._reject('rejected_poses', f'tip pose rejected: {exc}')
            return
        self._pose_t = now
        self.supervisor.on_pose(now, self._pose[0])

    def _on_path(self, msg: Path) -> None:
        points = conv.path_points(msg)
        try:
            self.supervisor.on_path(self._now(), points)
            if isinstance(self.controller, PathTracker):
                self.controller.set_path(points)
        except ValueError as exc:
            self._reject('rejected_inputs', f'path rejected: {exc}')

    def _on_goal(self, msg: PoseStamped) -> None:
        try:
            self.controller.set_goal(conv.point_from_pose_msg(msg))
        except InvalidInputError as exc:
            self._reject('rejected_inputs', f'goal rejected: {exc}')

    def _on_waypoint(self, msg: PointStamped) -> None:
        self.supervisor.on_planner_output(self._now())

    def _on_joy(self, msg: Joy) -> None:
        now = self._now()
        try:
            held, self._sticks = conv.joy_sticks(msg, self.enable_button, self.axes)
        except InvalidInputError as exc:  # fail safe: as a release
            held, self._sticks = False, (0.0, 0.0, 0.0)
            self._reject('rejected_inputs', f'Joy rejected: {exc}')
        self.supervisor.on_deadman(now, held)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        now = self._now()
        for status in msg.status:
            device = status.name.split(':', 1)[0].strip()
            if device not in DEVICES:
                continue
            error = status.level == DiagnosticStatus.ERROR
            self.supervisor.on_device(now, device, status.message if error else None)

    def _reject(self, counter: str, text: str) -> None:
        self.counts[counter] += 1
        self.last_error = text
        self.get_logger().warning(text, throttle_duration_sec=1.0)

    # ------------------------------------------------------------------ services
    def _on_resume(self, request: Trigger.Request, response: Trigger.Response
                   ) -> Trigger.Response:
        response.success, response.message = self.resume()
        return response

    def resume(self) -> tuple[bool, str]:
        """Engage or resume (``autonomy/resume``): ``(accepted, message)``."""
        ok, message = self.supervisor.resume(self._now())
        if ok:
            self._engaged_once = True
            self.controller.reset()
            self.get_logger().info(message)
        else:
            self.get_logger().warning(message)
        self._publish_state()
        return ok, message

    def _on_estop(self, request: SetBool.Request, response: SetBool.Response
                  ) -> SetBool.Response:
        self.supervisor.set_estop(self._now(), request.data)
        self._publish_state()
        response.success = True
        response.message = 'e-stop engaged' if request.data else \
            'e-stop released (autonomy/resume to run again)'
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        self.supervisor.reset()
        self.controller.reset()
        self._engaged_once = False
        self._publish_state()
        response.success, response.message = True, 'autonomy idle'
        return response

    # ------------------------------------------------------------------ tick
    def _on_tick(self) -> None:
        now = self._now()
        proposed = None
        if self._pose is not None and now - self._pose_t <= self.supervisor.config.\
                tracking_timeout_s:
            try:
                proposed = self.controller.command(*self._pose, now)
            except InvalidInputError as exc:
                self.counts['controller_errors'] += 1
                self.last_error = f'controller: {exc}'
                self.get_logger().warning(self.last_error, throttle_duration_sec=2.0)
            if proposed is not None and self.autonomy_mode == 'shared':
                proposed = shared_command(proposed, self._sticks, self.shared)
        sup = self.supervisor
        out = sup.tick(now, proposed)
        if self.autostart and not self._engaged_once and sup.state == 'idle' \
                and not sup.holding(now):
            self.resume()  # (this tick's output is the idle hold: it moves from the next)
        if sup.state != 'idle':
            stamp = self.get_clock().now().to_msg()
            self._ins_pub.publish(conv.insertion_msg(stamp, out.insertion_velocity))
            self._bend_pub.publish(conv.bend_msg(stamp, *out.bend))
            self.last_output = out
        self._publish_state()

    def _on_wall_timer(self) -> None:
        # the model wall follows the heartbeat only (the planner's model wall does the same)
        self.wall.step(self._now(), 0.1, np.zeros((0, 3)), self.catheter.radius)

    # ------------------------------------------------------------------ outputs
    def _publish_state(self) -> None:
        state = self.state
        if state == self._state:
            return
        if state.startswith('stopped') and self.supervisor.stop is not None:
            self.get_logger().error(f'autonomy stopped: {self.supervisor.stop.message}')
        self._state = state
        self._state_pub.publish(String(data=state))
        self._publish_diagnostics()

    def diagnostics(self) -> DiagnosticArray:
        """The node's current diagnostics."""
        sup, now = self.supervisor, self._now()
        stop = sup.stop
        if stop is not None:
            level, message = DiagnosticStatus.ERROR, f'stopped ({stop.reason}): {stop.message}'
        else:
            level, message = DiagnosticStatus.OK, self.state
        out = self.last_output
        values = [('state', self.state), ('controller', self.controller_name),
                  ('autonomy_mode', self.autonomy_mode), ('mode', self.mode),
                  ('stop_reason', stop.reason if stop else ''),
                  ('stop_message', stop.message if stop else ''), ('stops', sup.stops),
                  ('holding', ', '.join(r for r, _ in sup.holding(now))),
                  ('insertion_velocity', f'{out.insertion_velocity:.4f}' if out else ''),
                  ('bend_rad', f'{out.bend[0]:.3f}, {out.bend[1]:.3f}' if out else ''),
                  ('done', self.controller.done or ''), *self.counts.items(),
                  ('last_error', self.last_error)]
        return conv.diagnostics(self.get_clock().now().to_msg(), 'autonomy: supervisor',
                                'autonomy', level, message, values)

    def _publish_diagnostics(self) -> None:
        self._diag_pub.publish(self.diagnostics())


def main(args: list[str] | None = None) -> None:
    """Console script ``autonomy_node``."""
    run_node(AutonomyNode, 'autonomy_node', args,
             fatal=(ContractError, AnatomyError, PolicyLoadError))


if __name__ == '__main__':
    main()

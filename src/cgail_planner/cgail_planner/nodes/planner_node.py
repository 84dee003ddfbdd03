"""Planner node (``planner``): whole-path planning with the ONNX C-GAIL policy, and guidance.

``planner_type`` ``cgail`` (the policy), ``centerline`` (baseline) or ``rrt`` (the
curvature-constrained RRT of :mod:`cgail_planner.core.rrt_planner`, parameters ``rrt_*``).

Run: ``ros2 run cgail_planner planner_node --ros-args -p policy_path:=model.onnx`` (pip-only
workspace: ``scripts/ros2run cgail_planner planner_node ...``). numpy + onnxruntime only.
Its topics are its own, under its name (``~/tip_pose``, ``~/goal``, ``~/path``,
``~/next_waypoint``, ``~/suggested_bend``, ``~/markers``); below they are named as in the rig,
whose launch files remap them (docs/interfaces.md).

* ``planner/goal`` (PoseStamped): plans from the latest tip pose (a goal that arrives before a
  fresh tip pose waits for one) and publishes ``planner/path`` (latched).
* ``em_tracker/tip_pose`` (PoseStamped, sensor QoS): on every pose, with a path, publishes
  ``planner/next_waypoint`` and ``planner/suggested_bend`` (:mod:`cgail_planner.core.guidance`);
  in dynamic mode re-plans when the goal moved or the tip left the corridor around the path.
* ``planner/markers`` (visualization_msgs/MarkerArray, latched, frame ``phantom``): the goal
  (SPHERE of the goal tolerance), the path (LINE_STRIP), the next waypoint (SPHERE) and the
  suggested bend (its arc, LINE_STRIP, and the heading at the arc's end, ARROW), a full
  snapshot at most ``marker_rate_hz`` times a second, when one of them changed and someone
  subscribes (:mod:`cgail_planner.core.markers`).
* ``anatomy`` is a built-in name, a prepared anatomy directory or a mesh file; one that cannot
  be loaded ends ``planner_node`` with one line and exit status 2.
* Bad input (missing/corrupt model, goal outside the lumen or in another frame, NaN/inf or
  non-unit poses, stale poses) is logged with the reason, counted and shown on ``/diagnostics``;
  nothing is planned or guided from it.
* The catheter model (theta_max, L, step, diameter) and the observation (origin, scales, rays)
  are the policy's contract (:class:`cgail_sim.ftl_model.PolicyContract`).
  ``theta_max``, ``segment_length`` and ``anatomy`` must agree with it (0 = take the policy's;
  a path anatomy agrees when its content hash is the contract's):
  a disagreeing one raises :class:`~cgail_planner.core.errors.ContractError` at construction,
  unless ``override_policy_contract`` is set (then it wins, with a warning). A policy without a
  contract is refused unless ``override_policy_contract`` is set. A population policy (the
  ``generalist`` preset; contract ``anatomies: population``) runs in any ``anatomy``, observed
  in that anatomy's frame (its own origin and target bound ``d_max``), which the log says.
"""

from __future__ import annotations

from dataclasses import replace
import math
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from cgail_node_utils.entry_point import run_node
from cgail_planner.core.errors import ContractError, InvalidInputError, PlannerError
from cgail_planner.core.guidance import GuidanceConfig, PathFollower
from cgail_planner.core.markers import (
    MarkerConfig,
    PATH_NS,
    planner_markers,
    TARGET_NS,
    TipGuidance,
)
from cgail_planner.core.planner import (
    model_world_from_sim,
    Planner,
    PlannerConfig,
    reconcile_contract,
    replan_reason,
    ReplanConfig,
    world_observation_spec,
)
from cgail_planner.core.rrt_planner import RrtConfig
from cgail_planner.nodes import conversions as conv
from cgail_sim.ftl_model import CatheterConfig
from cgail_sim.mesh_io import AnatomyError


class PlannerNode(Node):
    """Thin rclpy wrapper around :class:`Planner` and :class:`PathFollower`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('planner', **kwargs)
        d, g, r = PlannerConfig(), GuidanceConfig(), ReplanConfig()
        policy_path = conv.declare(self, 'policy_path', '', 'ONNX policy written by cgail '
                                   "export-onnx (required by planner_type 'cgail')")
        settings = PlannerConfig(
            planner_type=conv.declare(self, 'planner_type', d.planner_type,
                                      "'cgail' (policy rollout), 'centerline' (baseline) or "
                                      "'rrt' (curvature-constrained RRT)"),
            goal_tolerance=conv.declare(self, 'goal_tolerance', d.goal_tolerance,
                                        'rollout reached the goal within this, m',
                                        lo=1e-4, hi=0.05),
            max_rollout_steps=conv.declare(self, 'max_rollout_steps', d.max_rollout_steps,
                                           'policy steps before the rollout gives up',
                                           lo=1, hi=100000),
            path_spacing=conv.declare(self, 'path_spacing', d.path_spacing,
                                      'arc-length spacing of the published path, m',
                                      lo=1e-4, hi=0.01),
            rrt=RrtConfig(
                max_iterations=conv.declare(self, 'rrt_max_iterations', d.rrt.max_iterations,
                                            'rrt: search iterations of one plan (the '
                                            'deterministic budget)', lo=1, hi=1_000_000),
                time_limit_s=conv.declare(self, 'rrt_time_limit_s', d.rrt.time_limit_s,
                                          'rrt: wall-time safety bound of one search, s',
                                          lo=1e-3, hi=60.0),
                seed=conv.declare(self, 'rrt_seed', d.rrt.seed, 'rrt: seed of every random '
                                  'draw (the same seed gives the same path)', lo=0,
                                  hi=2**31 - 1),
                clearance_margin=conv.declare(self, 'rrt_clearance_margin',
                                              d.rrt.clearance_margin, 'rrt: clearance from '
                                              'the wall beyond the catheter radius, m',
                                              lo=0.0, hi=0.005),
                range=conv.declare(self, 'rrt_range', d.rrt.range, 'rrt: longest curve one '
                                   'tree extension adds, m', lo=0.002, hi=0.2)))
        # 0 = not set: the policy's contract (or the catheter model's default) decides
        theta_max = conv.declare(self, 'theta_max', 0.0, "maximal bending angle of the model, "
                                 "rad; 0: the policy's (cgail) or the model default",
                                 lo=0.0, hi=math.pi)
        segment_length = conv.declare(self, 'segment_length', 0.0, "steerable segment length "
                                      "L of the model and the guidance, m; 0: the policy's "
                                      '(cgail) or the model default', lo=0.0, hi=0.5)
        override = conv.declare(self, 'override_policy_contract', False, 'run a policy whose '
                                'contract disagrees with theta_max, segment_length or anatomy '
                                '(logged as a warning); otherwise construction fails')
        anatomy = conv.declare(self, 'anatomy', 'default', "the anatomy planned in: a built-in "
                               "name ('default', 'elongated'), a prepared anatomy directory or a "
                               'mesh file with its <stem>.yaml landmarks')
        self.mode = conv.declare(self, 'mode', 'static', "'static' or 'dynamic' (deformable "
                                 'beating wall, re-planning)')
        if self.mode not in ('static', 'dynamic'):
            raise ValueError(f"mode must be 'static' or 'dynamic', found {self.mode!r}")
        lookahead = conv.declare(self, 'lookahead', g.lookahead,
                                 'arc length from the tip to the next waypoint, m',
                                 lo=1e-3, hi=0.2)
        max_bend = conv.declare(self, 'max_bend', g.max_bend,
                                'cap of the suggested bend magnitude, rad', lo=1e-3,
                                hi=math.pi / 2)
        self.replan_config = ReplanConfig(
            corridor_radius=conv.declare(self, 'corridor_radius', r.corridor_radius,
                                         'dynamic mode: re-plan when the tip is further from the '
                                         'path, m', lo=1e-3, hi=0.1),
            target_move_threshold=conv.declare(self, 'target_move_threshold',
                                               r.target_move_threshold,
                                               'dynamic mode: re-plan when the goal moved more, m',
                                               lo=1e-4, hi=0.1),
            min_interval_s=conv.declare(self, 'replan_min_interval_s', r.min_interval_s,
                                        'shortest time between re-plans, s', lo=0.0, hi=60.0))
        self.stale_after_s = conv.declare(self, 'stale_after_s', 0.5, 'tip poses older than '
                                          'this (header stamp vs node clock) are stale, s',
                                          lo=0.01, hi=60.0)
        self.frame_id = conv.declare(self, 'frame_id', 'phantom', 'frame of goals and outputs')
        wall_rate = conv.declare(self, 'wall_update_rate_hz', 10.0, 'dynamic mode: rate of the '
                                 'model wall (heartbeat) update, Hz', lo=0.1, hi=100.0)
        diag_period = conv.declare(self, 'diagnostics_period_s', 1.0, 'period of /diagnostics, s',
                                   lo=0.05, hi=60.0)
        marker_rate = conv.declare(self, 'marker_rate_hz', 10.0, 'highest rate of '
                                   'planner/markers (sent when they changed), Hz',
                                   lo=0.1, hi=100.0)

        from cgail_sim.anatomy_spec import anatomy_identity
        from cgail_sim.wall import DeformableWall, StaticWall
        from cgail_sim.worlds import load_world

        try:
            world = load_world(anatomy)
        except AnatomyError:
            self.destroy_node()
            raise
        label, anatomy_hash = anatomy_identity(anatomy)
        self.wall = StaticWall(world.anatomy) if self.mode == 'static' \
            else DeformableWall(world.anatomy)
        self.policy_error = ''
        policy = None
        if settings.planner_type == 'cgail':
            policy = self._load_policy(policy_path)
        overrides: dict[str, Any] = {k: v for k, v in (('theta_max', theta_max),
                                                        ('segment_length', segment_length))
                                     if v > 0.0}
        catheter = CatheterConfig(**overrides)
        self.planner: Planner | None = None
        #: Lines about the policy's contract (overrides: logged as warnings, else as info).
        self.contract_notes: list[str] = []
        if policy is not None and policy.contract is None and not override:
            self.policy_error = (f'policy not loaded: {policy_path} carries no catheter contract '
                                 '(re-export it, or set override_policy_contract to use the '
                                 'parameters and the model defaults); goals will be refused')
            self.get_logger().error(self.policy_error)
        elif policy is not None and policy.contract is not None:
            try:
                contract, self.contract_notes = reconcile_contract(
                    policy.contract, anatomy=label, anatomy_hash=anatomy_hash, mode=self.mode,
                    theta_max=theta_max or None, segment_length=segment_length or None,
                    override=override,
                    world_spec=world_observation_spec(world.scenarios, policy.contract))
                self.planner = Planner.from_contract(contract, world, self.wall, policy,
                                                     settings)
            except ContractError:
                self.destroy_node()
                raise
            catheter = contract.catheter
        else:
            if policy is not None:
                self.contract_notes.append(
                    f'override_policy_contract: {policy_path} carries no catheter contract; '
                    'using the parameters and the catheter model defaults')
            if settings.planner_type in ('centerline', 'rrt') or policy is not None:
                self.planner = Planner(replace(settings, catheter=catheter),
                                       model_world_from_sim(world), self.wall, policy)
        for note in self.contract_notes:
            (self.get_logger().warning if note.startswith('override')
             else self.get_logger().info)(note)
        self.config = self.planner.config if self.planner is not None \
            else replace(settings, catheter=catheter)
        self.guidance_config = GuidanceConfig(lookahead=lookahead, max_bend=max_bend,
                                              segment_length=catheter.segment_length)
        self.follower: PathFollower | None = None
        self.goal: np.ndarray | None = None
        self.planned_goal: np.ndarray | None = None
        self.pending_goal = False
        self.last_pose: tuple[np.ndarray, np.ndarray] | None = None
        self.last_pose_time: float | None = None
        self.last_plan_time = -math.inf
        self.counts = dict(plans=0, failed_plans=0, replans=0, rejected_goals=0,
                           rejected_poses=0, stale_poses=0, guidance_updates=0)
        self.last_error = self.policy_error
        self.last_plan_ms = float('nan')
        self.last_guidance_us = float('nan')
        self.path_points = 0
        self.marker_config = MarkerConfig()
        self.last_guidance: TipGuidance | None = None
        self._markers_changed = True
        self._markers_sent = False
        # per namespace (path, target): the Marker converted once and what it was converted from
        self._fixed_markers: dict[str, tuple[object, Marker]] = {}
        self._delete_all = Marker(action=Marker.DELETEALL)  # (restamped at each snapshot)
        self._guidance_markers: dict[tuple[str, int, str], Marker] = {}
        # per tip pose, refilled (conv.point_msg's out)
        self._wp_msg, self._bend_msg = PointStamped(), JointState()

        self._path_pub = self.create_publisher(Path, '~/path', conv.LATCHED_QOS)
        self._wp_pub = self.create_publisher(PointStamped, '~/next_waypoint', conv.SENSOR_QOS)
        self._bend_pub = self.create_publisher(JointState, '~/suggested_bend', conv.SENSOR_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                               conv.DIAGNOSTICS_QOS)
        self._markers_pub = self.create_publisher(MarkerArray, '~/markers', conv.LATCHED_QOS)
        self.create_subscription(PoseStamped, '~/tip_pose', self._on_tip_pose, conv.SENSOR_QOS)
        self.create_subscription(PoseStamped, '~/goal', self._on_goal, conv.COMMAND_QOS)
        self.create_timer(diag_period, self._on_diagnostics)
        self.create_timer(1.0 / marker_rate, self._on_marker_timer)
        if self.mode == 'dynamic':
            self._wall_dt = 1.0 / wall_rate
            self.create_timer(self._wall_dt, self._on_wall_timer)

    # ------------------------------------------------------------------ setup
    def _load_policy(self, path: str):
        from cgail_planner.core.errors import PolicyLoadError
        from cgail_planner.core.onnx_policy import OnnxPolicy

        if not path:
            self.policy_error = ("no policy: planner_type 'cgail' needs policy_path (an ONNX "
                                 'file from cgail export-onnx); goals will be refused')
        else:
            try:
                return OnnxPolicy(path)
            except PolicyLoadError as exc:
                self.policy_error = f'policy not loaded: {exc}; goals will be refused'
        self.get_logger().error(self.policy_error)
        return None

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # ------------------------------------------------------------------ callbacks
    def _on_goal(self, msg: PoseStamped) -> None:
        try:
            if msg.header.frame_id not in ('', self.frame_id):
                raise InvalidInputError(f'goal frame must be {self.frame_id!r}, found '
                                        f'{msg.header.frame_id!r}')
            if self.planner is None:
                raise InvalidInputError(self.policy_error)
            goal = self.planner.validate_goal(conv.point_from_pose_msg(msg))
        except InvalidInputError as exc:
            self._reject('rejected_goals', f'goal rejected: {exc}')
            return
        self.goal = goal
        self._markers_changed = True
        if self.planned_goal is not None and self.mode == 'dynamic' and \
                float(np.linalg.norm(goal - self.planned_goal)) \
                <= self.replan_config.target_move_threshold:
            return  # the same target, slightly moved: guidance continues on the current path
        self.pending_goal = True
        if self._pose_fresh():
            self._plan('new goal')

    def _on_tip_pose(self, msg: PoseStamped) -> None:
        t0 = time.perf_counter()
        now = self._now()
        age = now - conv.stamp_seconds(msg.header.stamp)
        if age > self.stale_after_s:
            self.counts['stale_poses'] += 1
            self.last_error = f'stale tip pose: {age:.3f} s old (limit {self.stale_after_s} s)'
            self.get_logger().warning(self.last_error, throttle_duration_sec=2.0)
            return
        try:
            position, rotation = conv.pose_from_msg(msg)
        except InvalidInputError as exc:
            self._reject('rejected_poses', f'tip pose rejected: {exc}')
            return
        self.last_pose = (position, rotation)
        self.last_pose_time = now
        if self.pending_goal:
            self._plan('new goal')
        if self.follower is None:
            return
        guide = self.follower.guide(position, rotation)
        if self.mode == 'dynamic' and self.goal is not None and self.planned_goal is not None:
            reason = replan_reason(self.replan_config, cross_track=guide.cross_track,
                                   planned_goal=self.planned_goal, goal=self.goal,
                                   since_last_plan_s=now - self.last_plan_time)
            if reason is not None and self._plan(reason):
                self.counts['replans'] += 1
                assert self.follower is not None
                guide = self.follower.guide(position, rotation)
        stamp = msg.header.stamp
        self._wp_pub.publish(conv.point_msg(stamp, self.frame_id, guide.next_waypoint,
                                            out=self._wp_msg))
        self._bend_pub.publish(conv.bend_msg(stamp, *guide.bend, out=self._bend_msg))
        self.last_guidance = TipGuidance(position, rotation, guide.next_waypoint, guide.bend,
                                         guide.distance_to_waypoint)
        self._markers_changed = True
        self.counts['guidance_updates'] += 1
        self.last_guidance_us = (time.perf_counter() - t0) * 1e6

    def _on_wall_timer(self) -> None:
        # the model wall follows the heartbeat only (no catheter body pushes it)
        self.wall.step(self._now(), self._wall_dt, np.zeros((0, 3)), self.config.catheter.radius)

    # ------------------------------------------------------------------ planning
    def _pose_fresh(self) -> bool:
        return self.last_pose_time is not None and \
            self._now() - self.last_pose_time <= self.stale_after_s

    def _plan(self, reason: str) -> bool:
        """Plan from the latest pose to the latest goal; True on success."""
        assert self.planner is not None and self.goal is not None and self.last_pose is not None
        self.pending_goal = False
        self.last_plan_time = self._now()
        try:
            result = self.planner.plan(self.last_pose[0], self.last_pose[1], self.goal)
        except PlannerError as exc:
            self.counts['failed_plans'] += 1
            self.last_error = f'planning failed ({reason}): {exc}'
            self.get_logger().error(self.last_error)
            self.follower = None
            self.planned_goal = None
            self.last_guidance = None
            self._markers_changed = True
            return False
        self.counts['plans'] += 1
        self.last_error = ''
        self.last_plan_ms = result.elapsed_s * 1e3
        self.path_points = len(result.path)
        self.follower = PathFollower(result.path, self.guidance_config)
        self.planned_goal = self.goal.copy()
        self._markers_changed = True
        self._path_pub.publish(conv.path_msg(self.get_clock().now().to_msg(), self.frame_id,
                                             result.path))
        self.get_logger().info(
            f'{result.planner_type} path planned ({reason}): {len(result.path)} points, '
            f'{self.follower.length * 1e3:.0f} mm, {result.steps} rollout steps, '
            f'{self.last_plan_ms:.1f} ms')
        return True

    def _on_marker_timer(self) -> None:
        # nobody listening (a simulated session): the change waits for a subscriber; the
        # first snapshot always goes out, for late joiners of the latched topic
        if not self._markers_changed or (self._markers_sent
                                         and self._markers_pub.get_subscription_count() == 0):
            return
        self._markers_changed = False
        self._markers_sent = True
        markers = planner_markers(
            self.marker_config, self.config.catheter, goal=self.goal,
            goal_radius=self.config.goal_tolerance,
            path=self.follower.points if self.follower is not None else None,
            guidance=self.last_guidance if self.follower is not None else None)
        # the path's LINE_STRIP (hundreds of points) is converted once per planned path and the
        # goal's SPHERE once per goal, not at every snapshot: restamped, the same message as
        # converting them again (only the guidance's markers change between snapshots)
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id=self.frame_id)
        self._delete_all.header = header
        out = [self._delete_all]
        for geometry in markers:
            source = self.follower if geometry.ns == PATH_NS else \
                self.goal if geometry.ns == TARGET_NS else None
            if source is not None:
                cached = self._fixed_markers.get(geometry.ns)
                if cached is None or cached[0] is not source:
                    cached = self._fixed_markers[geometry.ns] = (
                        source, conv.marker_msg(header, geometry))
                marker = cached[1]
                marker.header = header
            else:  # (the guidance's markers: refilled, conv.marker_msg's out)
                key = (geometry.ns, geometry.id, geometry.kind)
                marker = self._guidance_markers[key] = conv.marker_msg(
                    header, geometry, out=self._guidance_markers.get(key))
            out.append(marker)
        self._markers_pub.publish(MarkerArray(markers=out))

    def _reject(self, counter: str, text: str) -> None:
        self.counts[counter] += 1
        self.last_error = text
        self.get_logger().warning(text, throttle_duration_sec=1.0)

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self) -> DiagnosticArray:
        """The node's current diagnostics."""
        if self.planner is None:
            level, message = DiagnosticStatus.ERROR, self.policy_error
        elif self.last_pose_time is not None and not self._pose_fresh():
            level, message = DiagnosticStatus.STALE, 'no fresh tip pose'
        elif self.goal is not None and self.follower is None:
            level, message = DiagnosticStatus.ERROR, self.last_error or 'no path'
        elif self.last_error:
            level, message = DiagnosticStatus.WARN, self.last_error
        else:
            level, message = DiagnosticStatus.OK, 'guiding' if self.follower else 'waiting'
        values = [('planner_type', self.config.planner_type), ('mode', self.mode),
                  ('path_points', self.path_points), ('last_plan_ms', f'{self.last_plan_ms:.2f}'),
                  ('last_guidance_us', f'{self.last_guidance_us:.0f}'),
                  *self.counts.items(), ('last_error', self.last_error)]
        return conv.diagnostics(self.get_clock().now().to_msg(), 'planner: path planning',
                                'planner', level, message, values)

    def _on_diagnostics(self) -> None:
        self._diag_pub.publish(self.diagnostics())


def main(args: list[str] | None = None) -> None:
    """Console script ``planner_node``."""
    run_node(PlannerNode, 'planner_node', args, fatal=(ContractError, AnatomyError))


if __name__ == '__main__':
    main()

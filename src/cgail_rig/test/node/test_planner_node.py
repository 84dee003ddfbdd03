"""planner_node in-process: goal -> latched path, guidance per tip pose, bad input, diagnostics."""

from collections.abc import Callable
import math
from pathlib import Path
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from sensor_msgs.msg import JointState

from cgail_planner.nodes import conversions as conv
from cgail_planner.nodes.planner_node import PlannerNode
from cgail_sim.worlds import load_world

FIXTURES = Path(__file__).resolve().parents[3] / 'cgail_planner' / 'test' / 'fixtures'


@pytest.fixture(scope='module')
def world():
    return load_world('default')


class Rig:
    """A planner node plus a probe node that feeds it and records what it publishes."""

    def __init__(self, **params) -> None:
        self.node = PlannerNode(parameter_overrides=[Parameter(k, value=v)
                                                     for k, v in params.items()])
        self.probe = rclpy.create_node('probe')
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.pose_pub = self.probe.create_publisher(PoseStamped, '/planner/tip_pose',
                                                    conv.SENSOR_QOS)
        self.goal_pub = self.probe.create_publisher(PoseStamped, 'planner/goal',
                                                    conv.COMMAND_QOS)
        self.paths: list[PathMsg] = []
        self.waypoints: list[PointStamped] = []
        self.bends: list[JointState] = []
        self.diags: list[DiagnosticArray] = []
        self.probe.create_subscription(PathMsg, 'planner/path', self.paths.append,
                                       conv.LATCHED_QOS)
        self.probe.create_subscription(PointStamped, 'planner/next_waypoint',
                                       self.waypoints.append, conv.SENSOR_QOS)
        self.probe.create_subscription(JointState, 'planner/suggested_bend', self.bends.append,
                                       conv.SENSOR_QOS)
        self.probe.create_subscription(DiagnosticArray, '/diagnostics', self.diags.append,
                                       conv.DIAGNOSTICS_QOS)

    def spin_until(self, predicate: Callable[[], bool], timeout: float = 15.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def connected(self) -> bool:
        return (self.pose_pub.get_subscription_count() > 0
                and self.goal_pub.get_subscription_count() > 0)

    def send_pose(self, position, rotation, age: float = 0.0) -> None:
        stamp = self.node.get_clock().now() - rclpy.duration.Duration(seconds=age)
        self.pose_pub.publish(conv.pose_msg(stamp.to_msg(), 'phantom', np.asarray(position),
                                            np.asarray(rotation)))

    def send_goal(self, goal, frame: str = 'phantom') -> None:
        self.goal_pub.publish(conv.pose_msg(self.node.get_clock().now().to_msg(), frame,
                                            np.asarray(goal), np.eye(3)))

    def request_plan(self, start, goal) -> None:
        """The tip at ``start`` (a scenario start), then, once the node has it, the goal."""
        self.send_pose(start.position, start.rotation)
        self.spin_for(0.1)
        self.send_goal(goal)

    def last_status(self) -> DiagnosticStatus:
        return self.diags[-1].status[0]

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.probe.destroy_node()


def goal_ahead(world, distance: float = 0.03):
    start = world.scenarios.starts[0]
    return start, start.position + distance * start.rotation[:, 1]


def test_goal_gives_a_latched_path_and_guidance(ros, world) -> None:
    rig = Rig(policy_path=str(FIXTURES / 'straight_policy.onnx'), diagnostics_period_s=0.1)
    try:
        pub = rig.node.get_publishers_info_by_topic('/planner/path')[0]
        assert pub.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert pub.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        assert rig.spin_until(rig.connected)
        start, goal = goal_ahead(world)
        rig.send_goal(goal)  # before any pose: waits for one
        rig.spin_for(0.2)
        assert rig.paths == []
        rig.send_pose(start.position, start.rotation)
        assert rig.spin_until(lambda: rig.paths and rig.bends)
        path = conv.path_points(rig.paths[-1])
        assert rig.paths[-1].header.frame_id == 'phantom'
        assert path[0] == pytest.approx(start.position, abs=1e-9)
        assert path[-1] == pytest.approx(goal, abs=1e-9)
        assert np.linalg.norm(np.diff(path, axis=0), axis=1) == pytest.approx(0.001, rel=0.05)
        # guidance on the straight path: waypoint 25 mm ahead on the heading, no bend
        wp = rig.waypoints[-1].point
        assert [wp.x, wp.y, wp.z] == pytest.approx(
            start.position + 0.025 * start.rotation[:, 1], abs=1e-6)
        assert list(rig.bends[-1].name) == ['bend_alpha', 'bend_gamma']
        assert rig.bends[-1].position == pytest.approx([0.0, 0.0], abs=1e-6)
        # a tip 2 mm off towards +z_A: the bend turns the heading back (alpha < 0)
        rig.send_pose(start.position + 0.002 * start.rotation[:, 2], start.rotation)
        n = len(rig.bends)
        assert rig.spin_until(lambda: len(rig.bends) > n)
        alpha, gamma = rig.bends[-1].position
        assert alpha < 0.0 and gamma == pytest.approx(0.0, abs=1e-6)
        assert rig.spin_until(lambda: rig.diags and rig.last_status().level
                              == DiagnosticStatus.OK)
        # a late joiner still gets the latched path
        late = []
        rig.probe.create_subscription(PathMsg, 'planner/path', late.append, conv.LATCHED_QOS)
        assert rig.spin_until(lambda: late)
    finally:
        rig.close()


def test_centerline_planner_needs_no_model(ros, world) -> None:
    rig = Rig(planner_type='centerline')
    try:
        assert rig.spin_until(rig.connected)
        start = world.scenarios.starts[0]
        target = world.scenarios.targets[0].position
        rig.request_plan(start, target)
        assert rig.spin_until(lambda: rig.paths)
        path = conv.path_points(rig.paths[-1])
        assert path[-1] == pytest.approx(target, abs=1e-9)
        assert 0.2 < np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)) < 0.4
    finally:
        rig.close()


def test_bad_poses_and_goals_build_nothing(ros, world) -> None:
    rig = Rig(policy_path=str(FIXTURES / 'straight_policy.onnx'), diagnostics_period_s=0.1)
    try:
        assert rig.spin_until(rig.connected)
        start, goal = goal_ahead(world)
        rig.send_pose([math.nan, 0.0, 0.0], np.eye(3))                       # NaN pose
        rig.send_pose(start.position, start.rotation, age=2.0)               # stale pose
        rig.send_goal(goal)
        assert rig.spin_until(lambda: rig.node.counts['stale_poses'] == 1
                              and rig.node.counts['rejected_poses'] == 1)
        rig.spin_for(0.2)
        assert rig.paths == [] and rig.bends == []                          # nothing built
        rig.send_goal([0.5, 0.5, 0.5])                                       # outside the lumen
        rig.send_goal(goal, frame='aurora')                                  # wrong frame
        assert rig.spin_until(lambda: rig.node.counts['rejected_goals'] == 2)
        assert 'goal frame must be' in rig.node.last_error
        rig.send_pose(start.position, start.rotation)                        # fresh: plans
        assert rig.spin_until(lambda: rig.paths)
        assert conv.path_points(rig.paths[-1])[-1] == pytest.approx(goal, abs=1e-9)
    finally:
        rig.close()


def test_goal_outside_the_lumen_is_logged_and_in_diagnostics(ros) -> None:
    rig = Rig(planner_type='centerline', diagnostics_period_s=0.1)
    try:
        assert rig.spin_until(rig.connected)
        rig.send_goal([0.5, 0.5, 0.5])
        assert rig.spin_until(lambda: rig.diags and 'inside the lumen'
                              in rig.last_status().message)
        assert rig.paths == []
    finally:
        rig.close()


@pytest.mark.parametrize(('policy', 'match'), [
    ('', 'needs policy_path'),
    ('missing.onnx', 'ONNX policy not found'),
    ('corrupt_policy.onnx', 'not a loadable ONNX model'),
])
def test_missing_or_corrupt_model_refuses_goals(ros, world, policy, match) -> None:
    path = str(FIXTURES / policy) if policy else ''
    rig = Rig(policy_path=path, diagnostics_period_s=0.1)
    try:
        assert rig.spin_until(rig.connected)
        start, goal = goal_ahead(world)
        rig.send_pose(start.position, start.rotation)
        rig.send_goal(goal)
        assert rig.spin_until(lambda: rig.diags and rig.node.counts['rejected_goals'] == 1)
        status = rig.last_status()
        assert status.level == DiagnosticStatus.ERROR
        assert match in status.message
        assert rig.paths == [] and rig.bends == []
    finally:
        rig.close()


def test_failed_rollout_publishes_no_path(ros, world) -> None:
    rig = Rig(policy_path=str(FIXTURES / 'untrained_policy.onnx'), max_rollout_steps=50,
              diagnostics_period_s=0.1)
    try:
        assert rig.spin_until(rig.connected)
        start, goal = goal_ahead(world)
        rig.request_plan(start, goal)
        assert rig.spin_until(lambda: rig.node.counts['failed_plans'] == 1)
        rig.send_pose(start.position, start.rotation)
        rig.spin_for(0.2)
        assert rig.paths == [] and rig.bends == []
        assert rig.spin_until(lambda: rig.diags and 'did not reach the goal'
                              in rig.last_status().message)
    finally:
        rig.close()


def test_dynamic_mode_replans_when_the_tip_leaves_the_corridor(ros, world) -> None:
    rig = Rig(planner_type='centerline', mode='dynamic', replan_min_interval_s=0.0,
              corridor_radius=0.003)
    try:
        assert rig.spin_until(rig.connected)
        start = world.scenarios.starts[0]
        target = world.scenarios.targets[0].position
        rig.request_plan(start, target)
        assert rig.spin_until(lambda: len(rig.paths) == 1)
        rig.send_pose(start.position + 0.005 * start.rotation[:, 0], start.rotation)
        assert rig.spin_until(lambda: len(rig.paths) == 2)
        assert rig.node.counts['replans'] == 1
        assert conv.path_points(rig.paths[-1])[0] == pytest.approx(
            start.position + 0.005 * start.rotation[:, 0], abs=1e-9)
        # the target moves by 5 mm: re-planned to the new goal
        rig.send_goal(target + np.array([0.0, 0.0, 0.005]))
        assert rig.spin_until(lambda: len(rig.paths) == 3)
    finally:
        rig.close()


def test_rrt_planner_plans_a_path(ros, world) -> None:
    # the iteration budget ends the search, not the clock: the same on a loaded machine
    rig = Rig(planner_type='rrt', rrt_time_limit_s=30.0, diagnostics_period_s=0.1)
    try:
        assert rig.spin_until(rig.connected)
        start = world.scenarios.starts[1]
        target = world.scenarios.targets[3].position
        rig.request_plan(start, target)
        assert rig.spin_until(lambda: rig.paths)
        rig.send_pose(start.position, start.rotation)
        assert rig.spin_until(lambda: rig.bends)
        path = conv.path_points(rig.paths[-1])
        assert path[0] == pytest.approx(start.position, abs=1e-9)
        assert np.linalg.norm(path[-1] - target) <= 0.005
        assert np.linalg.norm(np.diff(path, axis=0), axis=1) == pytest.approx(0.001, rel=0.05)
        assert rig.node.counts['plans'] == 1 and rig.node.last_plan_ms > 0.0
        assert rig.spin_until(lambda: rig.diags and rig.last_status().level
                              == DiagnosticStatus.OK)
        values = {v.key: v.value for v in rig.last_status().values}
        assert values['planner_type'] == 'rrt'
    finally:
        rig.close()


def test_rrt_without_a_path_in_its_budget_publishes_none(ros, world) -> None:
    rig = Rig(planner_type='rrt', rrt_max_iterations=1, diagnostics_period_s=0.1)
    try:
        assert rig.spin_until(rig.connected)
        start = world.scenarios.starts[0]
        rig.request_plan(start, world.scenarios.targets[0].position)
        assert rig.spin_until(lambda: rig.node.counts['failed_plans'] == 1)
        assert rig.spin_until(lambda: rig.diags and 'rrt found no path within max_iterations '
                              '1 (1 iterations' in rig.last_status().message)
        assert rig.last_status().level == DiagnosticStatus.ERROR
        assert rig.paths == []
    finally:
        rig.close()


@pytest.mark.parametrize(('name', 'value'), [('planner_type', 'prm'), ('mode', 'beating'),
                                             ('lookahead', 0.5), ('rrt_time_limit_s', 0.0),
                                             ('rrt_max_iterations', 0),
                                             ('rrt_seed', -1), ('rrt_clearance_margin', 0.01),
                                             ('rrt_range', 1.0)])
def test_bad_parameters_raise_at_construction(ros, name, value) -> None:
    with pytest.raises(Exception, match=name):
        PlannerNode(parameter_overrides=[Parameter(name, value=value)])


@pytest.mark.parametrize(('cls_path', 'yaml_name', 'skip'), [
    ('cgail_rig.nodes.phantom_node:PhantomNode', 'phantom.yaml', ('aurora_link',)),
])
def test_yaml_defaults_equal_the_declared_defaults(ros, cls_path, yaml_name, skip) -> None:
    import importlib

    import yaml

    module, name = cls_path.split(':')
    cfg = Path(__file__).resolve().parents[2] / 'config' / yaml_name
    params = next(iter(yaml.safe_load(cfg.read_text()).values()))['ros__parameters']
    node = getattr(importlib.import_module(module), name)(
        parameter_overrides=[Parameter('simulate_aurora', value=False)]
        if 'phantom' in yaml_name else [])
    try:
        declared = {n: node.get_parameter(n).value for n in node._parameters
                    if n not in ('use_sim_time', 'simulate_aurora',
                                 'start_type_description_service')}
        assert set(declared) == set(params) - {'simulate_aurora'}
        for key, value in params.items():
            if key in skip or key == 'simulate_aurora':
                continue
            assert declared[key] == pytest.approx(value), key
    finally:
        node.destroy_node()


@pytest.fixture
def paper_code_policy(tmp_path: Path) -> str:
    """A paper_code policy (27 observations) whose constant action is ``[0, 0, -1]``, exported
    as ``train`` + ``export_onnx`` write it: with forward-only insertion it goes straight
    ahead (with ours it would retract out of the anatomy)."""
    import torch

    from cgail_learning.config import NetworkConfig
    from cgail_learning.export import export_actor
    from cgail_learning.networks import Actor
    from cgail_learning.train import sim_metadata
    from cgail_sim.config import EnvConfig

    torch.manual_seed(0)
    actor = Actor(27, 3, NetworkConfig(hidden_units=16), None)
    with torch.no_grad():
        actor.mu.weight.zero_()
        actor.mu.bias.copy_(torch.tensor([0.0, 0.0, -1.0]))
    meta = sim_metadata(EnvConfig.from_options('paper_code'))
    return str(export_actor(actor, tmp_path / 'paper_code.onnx', meta))


def test_a_paper_code_policy_plans_with_its_observation_and_insertion(
        ros, world, paper_code_policy) -> None:
    rig = Rig(policy_path=paper_code_policy)
    try:
        planner = rig.node.planner
        assert planner is not None and planner.spec.kind == 'paper_code'
        assert planner.obs_dim == 27 and planner.uses_kernel
        assert rig.node.config.catheter.forward_only
        assert rig.spin_until(rig.connected)
        start, goal = goal_ahead(world)
        rig.send_pose(start.position, start.rotation)
        rig.send_goal(goal)
        assert rig.spin_until(lambda: rig.paths)
        path = conv.path_points(rig.paths[-1])
        assert path[0] == pytest.approx(start.position, abs=1e-9)
        assert path[-1] == pytest.approx(goal, abs=1e-9)
        # straight ahead along the start heading: every point within 0.1 mm of that line
        rel = path - start.position
        off = rel - np.outer(rel @ start.rotation[:, 1], start.rotation[:, 1])
        assert np.linalg.norm(off, axis=1).max() < 1e-4
        assert rig.node.counts['plans'] == 1 and rig.node.counts['failed_plans'] == 0
    finally:
        rig.close()

"""phantom/lumen, phantom/markers and planner/markers in-process: full snapshots (DELETEALL, then
the expected namespaces and types, frame phantom), latched; a static lumen goes out once, a
dynamic one moves."""

from pathlib import Path

from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from visualization_msgs.msg import Marker, MarkerArray

from cgail_node_utils.testing import spin_until
from cgail_planner.nodes import conversions as conv
from cgail_planner.nodes.planner_node import PlannerNode
from cgail_rig.nodes.phantom_node import PhantomNode

FIXTURES = Path(__file__).resolve().parents[3] / 'cgail_planner' / 'test' / 'fixtures'
NO_DEVICES = dict(simulate_aurora=False, simulate_regulators=False, simulate_driver=False)


def kinds(msg: MarkerArray) -> list[tuple[str, int, int]]:
    """(ns, id, type) of the ADD markers, after checking the DELETEALL that opens the array."""
    first, *rest = msg.markers
    assert first.action == Marker.DELETEALL
    assert all(m.action == Marker.ADD and m.header.frame_id == 'phantom' for m in rest)
    return [(m.ns, m.id, m.type) for m in rest]


def latched(node, topic: str) -> None:
    profile = node.get_publishers_info_by_topic(topic)[0].qos_profile
    assert profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert profile.reliability == ReliabilityPolicy.RELIABLE


def with_probe(node):
    probe = rclpy.create_node('probe')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(probe)
    got: list[MarkerArray] = []
    return probe, executor, got


def test_phantom_publishes_the_lumen_once_and_the_body(ros) -> None:
    node = PhantomNode(parameter_overrides=[Parameter(k, value=v) for k, v in
                                            dict(NO_DEVICES, marker_rate_hz=5.0).items()])
    probe, ex, got = with_probe(node)
    lumens: list[MarkerArray] = []
    try:
        latched(node, '/phantom/markers')
        latched(node, '/phantom/lumen')
        # late joiners get the snapshots sent at construction (transient local)
        probe.create_subscription(MarkerArray, 'phantom/markers', got.append, conv.LATCHED_QOS)
        probe.create_subscription(MarkerArray, 'phantom/lumen', lumens.append,
                                  conv.LATCHED_QOS)
        assert spin_until(ex, lambda: got and lumens)
        assert kinds(lumens[0]) == [('lumen', 0, Marker.TRIANGLE_LIST)]
        assert kinds(got[0]) == [('catheter_body', 0, Marker.LINE_STRIP)]
        lumen, body = lumens[0].markers[1], got[0].markers[1]
        assert len(lumen.points) == 3 * len(node.lumen.faces)  # (4783 faces on AVX-512 numpy)
        assert conv.marker_points(lumen) == pytest.approx(
            node.world.anatomy.vertices[node.lumen.faces.reshape(-1)])
        assert body.scale.x == pytest.approx(0.007)
        assert conv.marker_points(body)[-1] == pytest.approx(node.physics.tip_position)
        # then the body every 1 / marker_rate_hz while subscribed, following the tip; the
        # static wall's lumen never again
        node.physics.move(0.01, (0.0, 0.0))
        n = len(got)
        assert spin_until(ex, lambda: len(got) > n + 1)
        body = got[-1].markers[1]
        assert conv.marker_points(body)[-1] == pytest.approx(node.physics.tip_position)
        assert len(lumens) == 1
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


def test_phantom_lumen_moves_in_dynamic_mode(ros) -> None:
    node = PhantomNode(parameter_overrides=[Parameter(k, value=v) for k, v in
                                            dict(NO_DEVICES, mode='dynamic',
                                                 lumen_rate_hz=10.0).items()])
    probe, ex, got = with_probe(node)
    try:
        probe.create_subscription(MarkerArray, 'phantom/lumen', got.append, conv.LATCHED_QOS)
        first: list[np.ndarray] = []

        def moved() -> bool:
            if not got:
                return False
            points = conv.marker_points(got[-1].markers[1])
            if not first:
                first.append(points)
            return float(np.linalg.norm(points - first[0], axis=1).max()) > 1e-3

        assert spin_until(ex, moved, timeout=30.0)
        assert kinds(got[-1]) == [('lumen', 0, Marker.TRIANGLE_LIST)]
        now = conv.marker_points(got[-1].markers[1])
        assert now.shape == first[0].shape                  # one topology, vertices move
        assert now == pytest.approx(node.wall.vertices[node.lumen.faces.reshape(-1)],
                                    abs=0.02)               # (the wall stepped on since)
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


def test_planner_publishes_target_path_waypoint_and_bend(ros) -> None:
    from cgail_sim.worlds import load_world

    node = PlannerNode(parameter_overrides=[
        Parameter('policy_path', value=str(FIXTURES / 'straight_policy.onnx'))])
    probe, ex, got = with_probe(node)
    try:
        latched(node, '/planner/markers')
        probe.create_subscription(MarkerArray, 'planner/markers', got.append, conv.LATCHED_QOS)
        poses = probe.create_publisher(PoseStamped, '/planner/tip_pose', conv.SENSOR_QOS)
        goals = probe.create_publisher(PoseStamped, 'planner/goal', conv.COMMAND_QOS)
        assert spin_until(ex, lambda: got)
        assert kinds(got[-1]) == []                         # nothing to show yet
        start = load_world('default').scenarios.starts[0]
        goal = start.position + 0.03 * start.rotation[:, 1]

        def send_pose() -> None:
            poses.publish(conv.pose_msg(node.get_clock().now().to_msg(), 'phantom',
                                        start.position, start.rotation))

        send_pose()
        spin_until(ex, lambda: node.last_pose is not None, 5.0)
        goals.publish(conv.pose_msg(node.get_clock().now().to_msg(), 'phantom', goal, np.eye(3)))
        assert spin_until(ex, lambda: node.follower is not None)
        send_pose()
        want = [('target', 0, Marker.SPHERE), ('path', 0, Marker.LINE_STRIP),
                ('next_waypoint', 0, Marker.SPHERE), ('suggested_bend', 0, Marker.LINE_STRIP),
                ('suggested_bend', 1, Marker.ARROW)]
        assert spin_until(ex, lambda: kinds(got[-1]) == want)
        target, path, waypoint, arc, arrow = got[-1].markers[1:]
        p = target.pose.position
        assert [p.x, p.y, p.z] == pytest.approx(goal)
        assert target.scale.x == pytest.approx(2 * node.config.goal_tolerance)
        assert conv.marker_points(path) == pytest.approx(node.follower.points)
        w = waypoint.pose.position                          # 25 mm ahead on the straight path
        assert [w.x, w.y, w.z] == pytest.approx(start.position + 0.025 * start.rotation[:, 1],
                                                abs=1e-3)
        assert conv.marker_points(arc)[0] == pytest.approx(start.position)
        assert len(arrow.points) == 2
        # a quiet planner sends nothing more (markers go out only when they changed)
        n = len(got)
        spin_until(ex, lambda: False, 0.5)
        assert len(got) == n
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()

"""operator_node in-process: idle without a path, deadman held while running, released at the
target with operator/done."""


from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState, Joy
from std_msgs.msg import Bool

from cgail_node_utils.testing import spin_until
from cgail_planner.nodes import conversions as conv
from cgail_planner.nodes.operator_node import OperatorNode


def test_operator_drives_with_the_deadman_and_stops_at_the_target(ros) -> None:
    node = OperatorNode(parameter_overrides=[Parameter('reaction_delay_s', value=0.05),
                                             Parameter('rate_hz', value=50.0)])
    probe = rclpy.create_node('probe')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(probe)
    try:
        joys: list[Joy] = []
        done: list[Bool] = []
        probe.create_subscription(Joy, '/operator/joy', joys.append, conv.SENSOR_QOS)
        probe.create_subscription(Bool, 'operator/done', done.append, conv.LATCHED_QOS)
        path_pub = probe.create_publisher(Path, '/operator/path', conv.LATCHED_QOS)
        goal_pub = probe.create_publisher(PoseStamped, '/operator/goal', conv.COMMAND_QOS)
        tip_pub = probe.create_publisher(PoseStamped, '/operator/tip_pose', conv.SENSOR_QOS)
        bend_pub = probe.create_publisher(JointState, '/operator/suggested_bend',
                                          conv.SENSOR_QOS)
        spin_until(ex, lambda: False, 0.3)
        assert joys == []  # idle: no Joy at all
        stamp = probe.get_clock().now().to_msg()
        goal = np.array([0.0, 0.1, 0.0])
        goal_pub.publish(conv.pose_msg(stamp, 'phantom', goal, np.eye(3)))
        path_pub.publish(conv.path_msg(stamp, 'phantom', np.array([[0, 0, 0], [0, 0.1, 0.0]])))
        assert spin_until(ex, lambda: node.operator.state == 'running')

        def showing(tip_y: float):
            """Show the tip at ``tip_y`` and the suggested bend at 20 Hz (a timer)."""
            def show() -> None:
                now = probe.get_clock().now().to_msg()
                tip_pub.publish(conv.pose_msg(now, 'phantom', np.array([0.0, tip_y, 0.0]),
                                              np.eye(3)))
                bend_pub.publish(conv.bend_msg(now, 0.3, 0.0))
            return probe.create_timer(0.05, show)

        def enabled() -> list[Joy]:
            return [j for j in joys if j.buttons[4] == 1]

        display = showing(0.05)
        # the deadman is held while running, and the stick follows the bend (after the delay)
        assert spin_until(ex, lambda: enabled() and enabled()[-1].axes[4] > 0.0)
        assert enabled()[-1].axes[1] > 0.0                     # inserting
        assert enabled()[-1].axes[4] > 0.0                     # bend_alpha towards 0.3 rad
        assert enabled()[-1].axes[3] == pytest.approx(0.0, abs=0.1)
        probe.destroy_timer(display)
        display = showing(0.0995)                              # 0.5 mm from the target
        assert spin_until(ex, lambda: node.done and done and done[-1].data)
        probe.destroy_timer(display)
        assert joys[-1].buttons[4] == 0 and joys[-1].axes[1] == 0.0   # deadman released
        n = len(joys)
        spin_until(ex, lambda: False, 0.3)
        assert len(joys) == n                                  # then quiet
        node.reset()
        assert node.operator.state == 'idle'
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


def test_bad_parameters_raise_at_construction(ros) -> None:
    with pytest.raises(ValueError, match='must differ'):
        OperatorNode(parameter_overrides=[Parameter('axis_bend_alpha', value=1)])

"""autonomy_node in-process: idle until resumed, drives the catheter topics while the deadman is
held, stops (latched state, diagnostics, safe commands) when it is released or on the e-stop,
and resumes only through autonomy/resume once nothing holds."""

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState, Joy
from std_msgs.msg import Header, String
from std_srvs.srv import SetBool, Trigger

from cgail_node_utils.testing import spin_until
from cgail_planner.nodes import conversions as conv
from cgail_planner.nodes.autonomy_node import AutonomyNode

#: Generous limits for the time-based conditions: on a loaded machine the test's 20 Hz timers
#: may stall; here the deadman button and the e-stop make the stops.
LENIENT = [Parameter('tracking_timeout_s', value=5.0), Parameter('command_timeout_s', value=5.0),
           Parameter('planner_timeout_s', value=10.0), Parameter('tick_timeout_s', value=5.0),
           Parameter('joy_timeout_s', value=5.0), Parameter('stall_window_s', value=30.0)]


def test_autonomy_runs_stops_latches_and_resumes(ros) -> None:
    node = AutonomyNode(parameter_overrides=LENIENT)
    probe = rclpy.create_node('probe')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(probe)
    try:
        insertions: list[JointState] = []
        bends: list[JointState] = []
        states: list[String] = []
        diags: list[DiagnosticStatus] = []
        probe.create_subscription(JointState, '/autonomy/insertion_command', insertions.append,
                                  conv.COMMAND_QOS)
        probe.create_subscription(JointState, '/autonomy/bend_command', bends.append,
                                  conv.COMMAND_QOS)
        probe.create_subscription(String, '/autonomy/state', states.append, conv.LATCHED_QOS)
        probe.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda m: diags.extend(s for s in m.status if s.name == 'autonomy: supervisor'),
            conv.DIAGNOSTICS_QOS)
        path_pub = probe.create_publisher(Path, '/autonomy/path', conv.LATCHED_QOS)
        tip_pub = probe.create_publisher(PoseStamped, '/autonomy/tip_pose', conv.SENSOR_QOS)
        wp_pub = probe.create_publisher(PointStamped, '/autonomy/next_waypoint',
                                        conv.SENSOR_QOS)
        joy_pub = probe.create_publisher(Joy, '/autonomy/joy', conv.SENSOR_QOS)
        resume = probe.create_client(Trigger, '/autonomy/resume')
        estop = probe.create_client(SetBool, '/autonomy/estop')
        deadman = {'held': 1}

        # a tip in the default anatomy's lumen (start 0) on a straight path ahead of it
        from cgail_sim.worlds import load_world

        start = load_world('default').scenarios.starts[0]
        p0, r0 = np.asarray(start.position), np.asarray(start.rotation)
        path = p0 + np.outer(np.linspace(0.0, 0.03, 31), r0[:, 1])

        def inputs() -> None:
            now = probe.get_clock().now().to_msg()
            tip_pub.publish(conv.pose_msg(now, 'phantom', p0, r0))
            wp_pub.publish(conv.point_msg(now, 'phantom', path[-1]))
            joy_pub.publish(Joy(header=Header(stamp=now, frame_id='joy'), axes=[0.0] * 5,
                                buttons=[0, 0, 0, 0, deadman['held']]))

        def call(client, request):
            assert client.wait_for_service(timeout_sec=10.0)
            future = client.call_async(request)
            assert spin_until(ex, future.done)
            return future.result()

        assert spin_until(ex, lambda: states and states[-1].data == 'idle')
        path_pub.publish(conv.path_msg(probe.get_clock().now().to_msg(), 'phantom', path))
        probe.create_timer(0.05, inputs)
        spin_until(ex, lambda: False, 0.5)
        assert insertions == [] and bends == []  # idle: nothing is commanded

        answer = call(resume, Trigger.Request())
        assert answer.success, answer.message
        assert spin_until(ex, lambda: states[-1].data == 'running' and insertions and bends
                          and insertions[-1].velocity[0] > 0.0)
        assert insertions[-1].name == ['insertion']
        assert insertions[-1].velocity[0] <= 0.005
        assert bends[-1].name == ['bend_alpha', 'bend_gamma']

        deadman['held'] = 0  # the person lets go
        assert spin_until(ex, lambda: states[-1].data == 'stopped:deadman_released')
        n = len(insertions)
        assert spin_until(ex, lambda: len(insertions) > n + 2)
        assert all(m.velocity[0] == 0.0 for m in insertions[n:])  # halted
        assert spin_until(ex, lambda: diags and diags[-1].level == DiagnosticStatus.ERROR)
        assert 'deadman_released' in diags[-1].message
        answer = call(resume, Trigger.Request())
        assert not answer.success and 'deadman_released' in answer.message
        assert states[-1].data == 'stopped:deadman_released'  # latched

        deadman['held'] = 1
        assert spin_until(ex, lambda: node.supervisor.holding(node._now()) == [])
        assert states[-1].data == 'stopped:deadman_released'  # still latched
        answer = call(resume, Trigger.Request())
        assert answer.success, answer.message
        assert spin_until(ex, lambda: states[-1].data == 'running'
                          and insertions[-1].velocity[0] > 0.0)

        answer = call(estop, SetBool.Request(data=True))
        assert answer.success
        assert spin_until(ex, lambda: states[-1].data == 'stopped:estop'
                          and insertions[-1].velocity[0] == 0.0)
        call(estop, SetBool.Request(data=False))
        assert spin_until(ex, lambda: call(resume, Trigger.Request()).success)
        assert spin_until(ex, lambda: states[-1].data == 'running')
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


def test_bad_parameters_raise_at_construction(ros) -> None:
    with pytest.raises(ValueError, match=r"^controller: expected one of \('path', 'policy'\), "
                                         r"found 'learned'"):
        AutonomyNode(parameter_overrides=[Parameter('controller', value='learned')])
    with pytest.raises(ValueError, match=r'^axis_insertion, axis_bend_alpha, axis_bend_gamma'):
        AutonomyNode(parameter_overrides=[Parameter('axis_bend_alpha', value=1)])
    from cgail_planner.core.errors import PolicyLoadError

    with pytest.raises(PolicyLoadError, match=r"^policy_path: expected an ONNX policy"):
        AutonomyNode(parameter_overrides=[Parameter('controller', value='policy')])


def test_a_mismatched_policy_is_refused_at_construction(ros) -> None:
    from pathlib import Path as FsPath

    from cgail_planner.core.errors import ContractError

    model = FsPath(__file__).resolve().parents[2] / 'cgail_planner' / 'models' \
        / 'cgail_elongated_static.onnx'
    with pytest.raises(ContractError, match=r"^anatomy: expected the policy's 'elongated'"):
        AutonomyNode(parameter_overrides=[Parameter('controller', value='policy'),
                                          Parameter('policy_path', value=str(model))])

"""phantom_node in-process: measured insertion + pressures move the tip through the plant
(bend*dl/L), no controller estimate read, devices hosted, /clock in simulated time, bad states
ignored."""

import math
import time

from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Header, String

from cgail_node_utils.testing import spin_until
from cgail_planner.nodes import conversions as conv
from cgail_rig.nodes.phantom_node import PhantomNode


def joint(names, positions) -> JointState:
    return JointState(header=Header(), name=list(names), position=list(positions))


def make(tmp_path, **params):
    defaults = dict(simulate_regulators=False, simulate_driver=False,
                    aurora_link=str(tmp_path / 'aurora'), physics_rate_hz=100.0, em_noise_m=0.0)
    defaults.update(params)
    node = PhantomNode(parameter_overrides=[Parameter(k, value=v) for k, v in defaults.items()])
    probe = rclpy.create_node('probe')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(probe)
    return node, probe, ex


def test_held_bend_curves_the_tip_by_bend_dl_over_l(ros, tmp_path) -> None:
    """Ideal plant (the controller's nominal model): the measured pressures of a 0.8 rad bend
    and 20 mm of measured insertion turn the heading by 0.8 * 20 / 50 rad, as before."""
    from pam_controller.core.bending_model import BendingModel
    from pam_controller.nodes.conversions import pressures_to_multiarray

    node, probe, ex = make(tmp_path, plant='ideal')
    try:
        ins = probe.create_publisher(JointState, '/phantom/insertion_state', conv.SENSOR_QOS)
        pressures = probe.create_publisher(Float64MultiArray, '/phantom/pressures',
                                           conv.SENSOR_QOS)
        poses: list[PoseStamped] = []
        probe.create_subscription(PoseStamped, 'phantom/tip_pose', poses.append,
                                  conv.SENSOR_QOS)
        heading0 = node.physics.tip_rotation[:, 1].copy()
        p = BendingModel().pressures_for_bend([0.8, 0.0])  # from a virgin state, as the plant
        pressures.publish(pressures_to_multiarray(p))
        ins.publish(joint(['insertion'], [0.010]))  # reference reading
        assert spin_until(ex, lambda: node.insertion == pytest.approx(0.010)
                          and node.bend == pytest.approx((0.8, 0.0), abs=1e-9))
        spin_until(ex, lambda: False, 0.1)
        for k in range(1, 41):  # 20 mm inserted with the bend held, 0.5 mm per reading
            ins.publish(joint(['insertion'], [0.010 + 0.0005 * k]))
            assert spin_until(ex, lambda k=k: node.insertion == pytest.approx(0.010 + 0.0005 * k))
            spin_until(ex, lambda: False, 0.02)
        assert spin_until(ex, lambda: node.physics.inserted >= 0.02 - 1e-12)
        turned = math.acos(float(np.clip(node.physics.tip_rotation[:, 1] @ heading0, -1, 1)))
        assert turned == pytest.approx(0.8 * 0.020 / 0.05, rel=1e-3)
        assert spin_until(ex, lambda: poses)
        assert poses[-1].header.frame_id == 'phantom'
        # malformed states are ignored
        ins.publish(joint(['insertion'], [math.nan]))
        pressures.publish(Float64MultiArray(data=[1.0, 2.0]))
        spin_until(ex, lambda: False, 0.2)
        assert node.insertion == pytest.approx(0.030)
        assert node.pressures == pytest.approx(p)
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


@pytest.mark.parametrize('hosted', [False, True])
def test_the_phantom_never_listens_to_a_controller_estimate(ros, tmp_path, hosted) -> None:
    node, probe, ex = make(tmp_path, simulate_regulators=hosted, simulate_driver=hosted,
                           pam_channel=f'pam_{tmp_path.name}',
                           driver_channel=f'drv_{tmp_path.name}')
    try:
        topics = {sub.topic_name for sub in node.subscriptions}
        assert not any(t.endswith('bend_state') for t in topics)
        expected = set() if hosted else {'/phantom/insertion_state', '/phantom/pressures'}
        assert topics == expected
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


def test_the_true_plant_bends_with_the_banks_pressures_and_slips(ros, tmp_path) -> None:
    """Hosted bank and driver, true plant: the bend comes from the pressures the bank holds,
    the tip advances less than the driver's gripper."""
    node, probe, ex = make(tmp_path, simulate_regulators=True, simulate_driver=True,
                           plant='true', plant_seed=3, pam_channel=f'pam_{tmp_path.name}',
                           driver_channel=f'drv_{tmp_path.name}')
    try:
        node.bank.step = lambda dt: None      # the bank holds what we set (no host here)
        node.driver.step = lambda dt: None
        node.bank.pressures_pa = np.array([250e3, 50e3, 150e3, 150e3])
        for k in range(200):  # 2 s, 20 mm at the gripper
            node.driver.mechanism.catheter_position = 0.0001 * k
            node.advance(0.01)
        static = node.plant.static_pair_bend(node.bank.pressures_pa)
        assert node.bend[0] > 0.5 and node.bend[0] != pytest.approx(static[0], abs=1e-3)
        eta = node.plant.params.insertion_efficiency
        assert node.physics.inserted < 0.0199 * eta
        assert node.physics.inserted > 0.0199 * eta - node.plant.params.backlash_m - 1e-9
        assert node.plant.params == node.plant.params.sample(np.random.default_rng(3))
        values = {v.key: v.value for v in node.diagnostics().status[0].values}
        assert values['plant'] == 'true' and values['plant_seed'] == '3'
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


def test_publishes_the_aurora_port_and_simulated_clock(ros, tmp_path) -> None:
    node, probe, ex = make(tmp_path, publish_clock=True, time_scale=5.0)
    try:
        ports: list[String] = []
        clocks: list[Clock] = []
        probe.create_subscription(String, 'phantom/aurora_port', ports.append, conv.LATCHED_QOS)
        probe.create_subscription(Clock, '/clock', clocks.append, 10)
        assert spin_until(ex, lambda: ports and len(clocks) > 20)
        assert ports[-1].data == str(tmp_path / 'aurora')
        assert (tmp_path / 'aurora').is_symlink()
        t0 = time.monotonic()
        sim0 = node.sim_time
        spin_until(ex, lambda: False, 1.0)
        ratio = (node.sim_time - sim0) / (time.monotonic() - t0)
        assert 1.5 < ratio <= 5.5  # faster than real time, never faster than asked
        c = clocks[-1].clock
        assert c.sec + 1e-9 * c.nanosec == pytest.approx(node._clock_offset + node.sim_time,
                                                         abs=0.1)
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


def test_reset_puts_the_tip_back_at_the_start(ros, tmp_path) -> None:
    node, probe, ex = make(tmp_path, start_id=1, target_id=2)
    try:
        start = node.world.scenarios.starts[1]
        node.physics.move(0.01, (0.0, 0.0))
        assert not np.allclose(node.physics.tip_position, start.position)
        node.reset_trial(1, 2)
        assert node.physics.tip_position == pytest.approx(start.position)
        assert node.target_position() == pytest.approx(node.world.scenarios.targets[2].position)
        with pytest.raises(ValueError, match='start_id must be in'):
            node.reset_trial(7, 0)
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()


@pytest.mark.parametrize(('name', 'value'), [('mode', 'beating'), ('start_id', 5),
                                             ('time_scale', 0.0), ('plant', 'perfect')])
def test_bad_parameters_raise_at_construction(ros, tmp_path, name, value) -> None:
    with pytest.raises(Exception, match=name):
        PhantomNode(parameter_overrides=[Parameter(name, value=value),
                                         Parameter('simulate_aurora', value=False)])


def test_a_wall_error_freezes_the_physics_and_is_reported(ros, tmp_path) -> None:
    """A deformable wall beyond its bound (WallError) stops the physics, not the node: the
    catheter and the wall freeze, the error is logged once and /diagnostics says ERROR."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from cgail_sim.wall import WallError

    node, probe, ex = make(tmp_path, mode='dynamic')
    try:
        calls = []

        def blown_up(*args) -> None:
            calls.append(args)
            raise WallError('deformable wall: expected every particle within 40 mm ...')

        node.physics.step = blown_up
        node.advance(0.01)
        node.advance(0.01)
        assert len(calls) == 1
        assert node.physics_error.startswith('physics stopped: deformable wall: expected')
        status = node.diagnostics().status[0]
        assert status.level == DiagnosticStatus.ERROR
        assert status.message == node.physics_error
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()

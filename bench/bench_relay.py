"""Figures for the sleeve driver: relay duty cycle, controller and codec cost, node state rate.

Run: ``ROS_DOMAIN_ID=<id> scripts/ws python bench/bench_relay.py``
"""

from __future__ import annotations

import time
import uuid

import _localhost  # noqa: F401  (before rclpy starts: discovery on this machine only)

from catheter_driver.core.mechanism import SleeveMechanism
from catheter_driver.core.relay import Phase, RelayConfig, RelayController
from catheter_driver.hw.can_protocol import DriverCodec, DriverCommand


def mean_insertion_rate(cfg: RelayConfig, command: float, seconds: float, rate_hz: float):
    """Simulated catheter advance for a constant command; returns (mean rate, relays)."""
    dt = 1.0 / rate_hz
    mech = SleeveMechanism(cfg)
    ctrl = RelayController(cfg, mech.feedback())
    relays, previous = 0, ctrl.phase
    for _ in range(int(seconds * rate_hz)):
        cmd = ctrl.step(command, mech.feedback(), dt)
        mech.step(cmd, dt)
        if previous == Phase.DRIVE and ctrl.phase == Phase.CLOSE_FIXED:
            relays += 1
        previous = ctrl.phase
    return mech.catheter_position / seconds, relays


def controller_step_cost(n: int = 50_000) -> float:
    """Microseconds per RelayController.step + SleeveMechanism.step."""
    cfg = RelayConfig()
    mech = SleeveMechanism(cfg)
    ctrl = RelayController(cfg, mech.feedback())
    start = time.perf_counter()
    for _ in range(n):
        mech.step(ctrl.step(0.005, mech.feedback(), 0.02), 0.02)
    return (time.perf_counter() - start) / n * 1e6


def codec_cost(n: int = 20_000) -> float:
    """Microseconds per DRV_COMMAND encode + decode."""
    codec = DriverCodec()
    start = time.perf_counter()
    for i in range(n):
        codec.decode_command(codec.encode_command(DriverCommand(0.005, True, False, i)))
    return (time.perf_counter() - start) / n * 1e6


def node_state_rate(seconds: float = 3.0) -> float:
    """Sustained catheter/insertion_state rate of the driver node with the simulated device."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.lifecycle import TransitionCallbackReturn
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from catheter_driver.nodes import conversions as conv
    from catheter_driver.nodes.driver_node import DriverNode

    rclpy.init()
    try:
        node = DriverNode(parameter_overrides=[
            Parameter('can_channel', value=f'bench_{uuid.uuid4().hex}')])
        # a lifecycle node: it publishes its state only once configured and active
        if (node.trigger_configure() != TransitionCallbackReturn.SUCCESS
                or node.trigger_activate() != TransitionCallbackReturn.SUCCESS):
            raise SystemExit('bench_relay: driver_node did not become active')
        probe = rclpy.create_node('bench_probe')
        got: list[float] = []
        probe.create_subscription(JointState, '/sleeve_driver/insertion_state',
                                  lambda _m: got.append(time.monotonic()), conv.SENSOR_QOS)
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        ex.add_node(probe)
        end = time.monotonic() + 1.0 + seconds
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
        window = [t for t in got if t >= end - seconds]
        ex.shutdown()
        node.trigger_deactivate()
        node.trigger_cleanup()
        node.destroy_node()
        probe.destroy_node()
        return len(window) / seconds
    finally:
        rclpy.try_shutdown()


def main() -> None:
    cfg = RelayConfig()
    for command in (0.005, 0.0025, -0.005):
        # Retraction from the homed position needs room below 0: widen the travel limit.
        c = RelayConfig(position_min=-1.0) if command < 0 else cfg
        rate, relays = mean_insertion_rate(c, command, 120.0, 50.0)
        print(f'relay duty cycle: command {command * 1e3:+.2f} mm/s -> mean catheter rate '
              f'{rate * 1e3:+.3f} mm/s over 120 s ({relays} relays, stroke '
              f'{(cfg.stroke_max - cfg.stroke_min) * 1e3:.0f} mm, 50 Hz control)')
    print(f'controller + mechanism step: {controller_step_cost():.2f} us')
    print(f'DRV_COMMAND encode + decode (cantools): {codec_cost():.2f} us')
    print(f'driver node catheter/insertion_state rate: {node_state_rate():.1f} Hz '
          f'(control_rate_hz 50)')


if __name__ == '__main__':
    main()

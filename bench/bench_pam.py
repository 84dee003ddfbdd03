"""Benchmark of pam_controller: model and codec cost, command -> CAN setpoint latency.

Run: ``ROS_DOMAIN_ID=22 scripts/ws python bench/bench_pam.py``
Prints figures; asserts nothing. The latency is measured from publishing a bend command to the
first ``PAM_SETPOINTS`` frame on the (virtual) bus that differs from the steady one, so it
includes DDS delivery and the wait for the next control tick. The command is published right
after a setpoint frame is seen, i.e. just after a tick: the worst phase, so the figure is about
one control period (20 ms at 50 Hz) plus delivery and processing.
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time

import _localhost  # noqa: F401  (before rclpy starts: discovery on this machine only)
import can
import numpy as np


def bench_model(n: int) -> None:
    from pam_controller.core.bending_model import BendingModel

    model = BendingModel()
    rng = np.random.default_rng(0)
    radius = np.pi / 2 * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    bends = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    t0 = time.perf_counter()
    pressures = [model.pressures_for_bend(b) for b in bends]
    t1 = time.perf_counter()
    for p in pressures:
        model.bend_from_pressures(p)
    t2 = time.perf_counter()
    print(f'model: pressures_for_bend {1e6 * (t1 - t0) / n:.1f} us/call, '
          f'bend_from_pressures {1e6 * (t2 - t1) / n:.1f} us/call (n={n})')


def bench_codec(n: int) -> None:
    from pam_controller.hw import can_protocol as proto

    p = np.array([123e3, 45e3, 300e3, 0.0])
    t0 = time.perf_counter()
    msgs = [proto.encode_setpoints(p, i) for i in range(n)]
    t1 = time.perf_counter()
    for m in msgs:
        proto.decode(m)
    t2 = time.perf_counter()
    print(f'codec: encode_setpoints {1e6 * (t1 - t0) / n:.1f} us/frame, '
          f'decode {1e6 * (t2 - t1) / n:.1f} us/frame (n={n})')


def bench_latency(commands: int) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from pam_controller.hw import can_protocol as proto
    from pam_controller.nodes.pam_node import PamNode

    channel = 'pam_bench'
    rclpy.init()
    node = PamNode(parameter_overrides=[Parameter('can_channel', value=channel)])
    node.trigger_configure()
    node.trigger_activate()
    peer = Node('pam_bench_peer')
    pub = peer.create_publisher(JointState, '/pam_controller/bend_command',
                                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(peer)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    observer = can.Bus(interface='virtual', channel=channel)
    latencies = []
    try:
        time.sleep(1.0)
        for k in range(commands):
            alpha = 0.6 if k % 2 == 0 else -0.6
            while observer.recv(timeout=0.0) is not None:
                pass
            d0 = None
            while d0 is None:   # the steady setpoint just before the command
                msg = observer.recv(timeout=0.1)
                if msg is not None and msg.arbitration_id == proto.SETPOINTS_ID:
                    sp = proto.decode(msg)
                    assert isinstance(sp, proto.Setpoints)
                    d0 = sp.pressures_pa
            t0 = time.perf_counter()
            pub.publish(JointState(name=['bend_alpha', 'bend_gamma'], position=[alpha, 0.0]))
            deadline = t0 + 0.5
            while time.perf_counter() < deadline:
                msg = observer.recv(timeout=0.05)
                if msg is None or msg.arbitration_id != proto.SETPOINTS_ID:
                    continue
                sp = proto.decode(msg)
                assert isinstance(sp, proto.Setpoints)
                if np.max(np.abs(sp.pressures_pa - d0)) > 1.0:
                    latencies.append(time.perf_counter() - t0)
                    break
            time.sleep(0.3)   # the ramp settles; below command_timeout_s, so no watchdog vent
    finally:
        observer.shutdown()
        executor.shutdown()
        spinner.join(timeout=5.0)
        node.trigger_deactivate()  # vents and stops the regulator bank's thread
        node.trigger_cleanup()
        peer.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown()
    ms = sorted(1e3 * x for x in latencies)
    print(f'node: bend_command -> first PAM_SETPOINTS that moves: '
          f'median {statistics.median(ms):.1f} ms, p95 {ms[int(0.95 * (len(ms) - 1))]:.1f} ms, '
          f'max {ms[-1]:.1f} ms over {len(ms)}/{commands} commands (control_rate_hz 50)')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--n', type=int, default=5000, help='calls per micro-benchmark')
    parser.add_argument('--commands', type=int, default=30, help='commands for the latency')
    args = parser.parse_args()
    bench_model(args.n)
    bench_codec(args.n)
    bench_latency(args.commands)


if __name__ == '__main__':
    main()

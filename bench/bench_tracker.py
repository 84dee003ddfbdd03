"""Benchmark of the Aurora tracker node: pose latency and sustained publish rate.

Runs the simulated Aurora on a pty in its own process (as a real device would be: it does not
compete for this interpreter's GIL) and ``aurora_node`` in this process (its reader thread and
the ndicapi child process as in production), with a subscriber on its ``~/tip_pose`` (the
rig's ``em_tracker/tip_pose``).

Latency = time the subscriber receives the message - time the device generated the frame
(the simulated device's frame ``k`` exists from ``TSTART + k / 40 Hz``). The generation time
travels in the pose itself: the simulated device sets x = 10 mm/s * (CLOCK_MONOTONIC of the
frame mod 30 s) - 150 mm, which TX's 0.01 mm resolution carries to 1 ms (BX: float32, finer).

    scripts/ws python bench/bench_tracker.py            # TX then BX, 10 s each
    scripts/ws python bench/bench_tracker.py --mode bx --duration 20
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import _localhost  # noqa: F401  (before rclpy starts: discovery on this machine only)
from geometry_msgs.msg import PoseStamped
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data

from em_tracker.hw.sim_aurora import SimAurora
from em_tracker.nodes.aurora_node import AuroraNode

SPEED_MM_PER_S = 10.0
RATE_HZ = 40.0
WRAP_S = 30.0


def serve_sim(link: str) -> None:
    """Child mode: a simulated Aurora whose x encodes the frame's monotonic time."""
    holder: list[SimAurora] = []

    def pose_source(t_s: float) -> tuple[np.ndarray, np.ndarray]:
        t_gen = holder[0].tracking_start_time + t_s
        return (np.array([SPEED_MM_PER_S * (t_gen % WRAP_S) - 150.0, 20.0, -200.0]),
                np.array([1.0, 0.0, 0.0, 0.0]))

    sim = SimAurora(pose_source, link_path=link, frame_rate_hz=RATE_HZ)
    holder.append(sim)
    sim.start()
    try:
        sys.stdin.read()  # until the parent closes our stdin
    finally:
        sim.close()


def run(mode: str, duration_s: float, isolate: bool) -> dict[str, float]:
    """Run one mode (``'tx'`` or ``'bx'``) and return the figures."""
    link = os.path.join(tempfile.mkdtemp(prefix='bench_tracker_'), 'aurora')
    sim = subprocess.Popen([sys.executable, __file__, '--serve-sim', link],
                           stdin=subprocess.PIPE)
    deadline = time.monotonic() + 10.0
    while not os.path.exists(link) and time.monotonic() < deadline:
        time.sleep(0.02)
    node = AuroraNode(parameter_overrides=[
        Parameter('port', value=link), Parameter('use_bx', value=mode == 'bx'),
        Parameter('isolate_device', value=isolate)])
    # a lifecycle node: configure (open the port, start-up handshake) and activate (publish)
    if (node.trigger_configure() != TransitionCallbackReturn.SUCCESS
            or node.trigger_activate() != TransitionCallbackReturn.SUCCESS):
        raise SystemExit(f'bench_tracker: aurora_node did not become active on {link}')
    listener = rclpy.create_node('bench_tracker_listener')
    # (receive monotonic time, x in m, receive time - header.stamp in s)
    arrivals: list[tuple[float, float, float]] = []

    def on_pose(msg: PoseStamped) -> None:
        stamp_s = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        arrivals.append((time.monotonic(), msg.pose.position.x, time.time() - stamp_s))

    listener.create_subscription(PoseStamped, '/aurora/tip_pose', on_pose,
                                 qos_profile_sensor_data)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(listener)
    try:
        deadline = time.monotonic() + 10.0
        while not arrivals and time.monotonic() < deadline:  # start-up, not measured
            executor.spin_once(timeout_sec=0.05)
        arrivals.clear()
        start = time.monotonic()
        while time.monotonic() - start < duration_s:
            executor.spin_once(timeout_sec=0.05)
        elapsed = time.monotonic() - start
        latencies, transport = [], []
        for received, x_m, since_stamp in arrivals:
            t_mod = (x_m * 1000.0 + 150.0) / SPEED_MM_PER_S
            t_gen = t_mod + WRAP_S * np.floor((received - t_mod) / WRAP_S)
            latencies.append(received - t_gen)
            transport.append(since_stamp)
        if not arrivals:
            raise SystemExit(f'bench_tracker: no pose received in {duration_s:.0f} s '
                             f'({mode} mode); node health: {node.health}')
        lat_ms = np.array(latencies) * 1e3
        # header.stamp = time the reply was read, so the latency splits into
        # device frame -> reply read (polling phase + serial) and reply -> subscriber.
        transport_ms = np.array(transport) * 1e3
        health = node.health
        return {
            'messages': len(arrivals), 'rate_hz': len(arrivals) / elapsed,
            'mean_ms': float(lat_ms.mean()), 'p50_ms': float(np.percentile(lat_ms, 50)),
            'p95_ms': float(np.percentile(lat_ms, 95)), 'max_ms': float(lat_ms.max()),
            'read_p50_ms': float(np.percentile(lat_ms - transport_ms, 50)),
            'deliver_p50_ms': float(np.percentile(transport_ms, 50)),
            'dropped': health.frames.dropped, 'repeated_polls': health.frames.repeated,
            'bad_replies': health.bad_replies,
        }
    finally:
        executor.shutdown()
        node.destroy_node()
        listener.destroy_node()
        if sim.stdin is not None:
            sim.stdin.close()
        sim.wait(timeout=5)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--mode', choices=('tx', 'bx', 'both'), default='both')
    parser.add_argument('--duration', type=float, default=10.0, help='seconds per mode')
    parser.add_argument('--in-process', action='store_true',
                        help='run ndicapi in the node process (isolate_device:=false)')
    parser.add_argument('--serve-sim', metavar='LINK', help=argparse.SUPPRESS)
    ns = parser.parse_args()
    if ns.serve_sim:
        serve_sim(ns.serve_sim)
        return
    rclpy.init()
    try:
        modes = ('tx', 'bx') if ns.mode == 'both' else (ns.mode,)
        print(f'aurora_node vs simulated Aurora at {RATE_HZ:.0f} Hz, {ns.duration:.0f} s per '
              f'mode, ndicapi {"in-process" if ns.in_process else "in a child process"}')
        print(f'{"mode":4} {"msgs":>5} {"rate Hz":>8} {"mean ms":>8} {"p50 ms":>7} '
              f'{"p95 ms":>7} {"max ms":>7} {"dropped":>7} {"bad":>4}  '
              f'(p50 split: device->reply read | reply->subscriber)')
        for mode in modes:
            r = run(mode, ns.duration, not ns.in_process)
            print(f'{mode:4} {r["messages"]:5d} {r["rate_hz"]:8.2f} {r["mean_ms"]:8.2f} '
                  f'{r["p50_ms"]:7.2f} {r["p95_ms"]:7.2f} {r["max_ms"]:7.2f} '
                  f'{r["dropped"]:7d} {r["bad_replies"]:4d}  '
                  f'{r["read_p50_ms"]:.2f} | {r["deliver_p50_ms"]:.2f} ms')
    finally:
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()

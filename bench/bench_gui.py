"""Latency of the guidance page: tip pose published -> the page's frame that draws it.

Starts ``gui_node`` in-process (port 0, default anatomy, raycasts on), a publisher of the
tip pose at the tracker's rate (with the planner's waypoint and bend alongside), and headless
Chromium on the page. Each tip pose carries the publish time in its header stamp; the page
records, for every animation frame that draws a new tip pose, ``now - stamp`` (same machine
clock, ``performance.timeOrigin + performance.now()``). Prints mean / p50 / p95 / max in ms,
the share of poses drawn (the rest were merged into a later frame: coalescing) and the frame
rate. Needs Debian ``chromium``.

Run: ``ROS_DOMAIN_ID=<id> scripts/ws python bench/bench_gui.py [--rate 40] [--seconds 10]``.
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import _localhost  # noqa: F401  (before rclpy starts: discovery on this machine only)
from geometry_msgs.msg import PointStamped, PoseStamped
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import JointState
from websockets.sync.client import connect

from cgail_gui.cdp import Chromium
from cgail_gui.demo import centerline_scene
from cgail_gui.nodes.gui_node import GuiNode
from cgail_sim.anatomy import build_anatomy
from cgail_sim.centerline import compute_centerlines


def _node_latency(port: int | None, seconds: float) -> np.ndarray:
    """ms from the header stamp to a state message at a Python WebSocket client that acks."""
    out = []
    deadline = time.monotonic() + seconds
    with connect(f'ws://127.0.0.1:{port}/ws', max_size=None) as ws:
        while time.monotonic() < deadline:
            try:
                msg = json.loads(ws.recv(timeout=0.5))
            except TimeoutError:
                continue
            now = time.time()
            ws.send('{"type":"ack"}')
            tip = msg['items'].get('tip')
            if tip and not msg['full']:
                out.append((now - tip['stamp']) * 1e3)
    return np.array(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rate', type=float, default=40.0, help='tip pose rate, Hz')
    parser.add_argument('--seconds', type=float, default=10.0, help='measured duration, s')
    parser.add_argument('--window', default='1600x980', help='browser window, WxH pixels')
    args = parser.parse_args()
    path = compute_centerlines(build_anatomy('default'))['left'].points
    rclpy.init()
    node = GuiNode(parameter_overrides=[Parameter('port', value=0)])
    pub = rclpy.create_node('bench_gui_tracker')
    tip = pub.create_publisher(PoseStamped, '/gui/tip_pose', qos_profile_sensor_data)
    wp = pub.create_publisher(PointStamped, '/gui/next_waypoint', qos_profile_sensor_data)
    bend = pub.create_publisher(JointState, '/gui/suggested_bend', qos_profile_sensor_data)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(pub)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    stop = threading.Event()
    sent = [0]

    def publish_loop() -> None:
        period = 1.0 / args.rate
        k = 0
        nxt = time.monotonic()
        while not stop.is_set():
            pose = centerline_scene(path, 10.0 + (k % 3000) * 0.02)
            msg = PoseStamped()
            msg.header.frame_id = 'phantom'
            w = PointStamped()
            w.point.x, w.point.y, w.point.z = (float(v) for v in pose.waypoint)
            wp.publish(w)
            bend.publish(JointState(name=['bend_alpha', 'bend_gamma'],
                                    position=[float(pose.bend[0]), float(pose.bend[1])]))
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = \
                (float(v) for v in pose.position)
            (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
             msg.pose.orientation.w) = (float(v) for v in pose.quaternion)
            t = time.time()
            msg.header.stamp.sec = int(t)
            msg.header.stamp.nanosec = int((t - int(t)) * 1e9)
            tip.publish(msg)
            sent[0] += 1
            k += 1
            nxt += period
            stop.wait(max(0.0, nxt - time.monotonic()))

    try:
        width, height = (int(v) for v in args.window.lower().split('x'))
        with Chromium.launch(width=width, height=height) as browser:
            page = browser.open(node.url)
            page.wait_for('window.gui && window.gui.connected && window.gui.drawn.meshVertices',
                          timeout=60)
            publisher = threading.Thread(target=publish_loop, daemon=True)
            publisher.start()
            time.sleep(2.0)                                   # warm-up (JIT, first frames)
            page.evaluate('window.gui.latencies.length = 0, window.gui.rxLatencies.length = 0, '
                          'window.gui.frames0 = window.gui.frames, 0')
            sent0 = sent[0]
            t0 = time.monotonic()
            node_ms = _node_latency(node.port, args.seconds)   # a scripted page, meanwhile
            lat = page.evaluate('window.gui.latencies')
            rx = page.evaluate('window.gui.rxLatencies')
            render = np.array(page.evaluate('window.gui.renderMs.slice(-50)') or [[0.0, 0.0]])
            renderer = page.evaluate('window.gui.glRenderer')
            scale = page.evaluate('window.gui.renderScale')
            frames = page.evaluate('window.gui.frames - window.gui.frames0')
            elapsed = time.monotonic() - t0
            n_sent = sent[0] - sent0
            stop.set()
            publisher.join(2)
    finally:
        executor.shutdown()
        spinner.join(5)
        node.destroy_node()
        pub.destroy_node()
        rclpy.try_shutdown()
    ms = np.array([x[1] for x in lat])
    if ms.size == 0:
        raise SystemExit('bench_gui: no tip pose was drawn')
    print(f'bench_gui: tip pose published -> page frame drawn, {args.rate:g} Hz for '
          f'{elapsed:.1f} s (default anatomy, {node.config.ray_count + 1} rays per pose, '
          f'window {args.window})')
    print(f'  latency ms: mean {ms.mean():.1f}  p50 {np.percentile(ms, 50):.1f}  '
          f'p95 {np.percentile(ms, 95):.1f}  max {ms.max():.1f}  (n = {ms.size})')
    rx_ms = np.array([x[1] for x in rx])
    if rx_ms.size:
        print(f'  of which published -> WebSocket message in the page: mean {rx_ms.mean():.1f}  '
              f'p95 {np.percentile(rx_ms, 95):.1f} ms (n = {rx_ms.size}); the rest is drawing '
              f'(WebGL renderer: {renderer})')
    print(f'  WebGL render calls per frame (last 50): external {render[:, 0].mean():.1f} ms, '
          f'internal {render[:, 1].mean():.1f} ms; resolution scale at the end {scale} '
          f'(software WebGL lowers it while frames are slow)')
    print(f'  node alone (published -> state message at a scripted WebSocket client): mean '
          f'{node_ms.mean():.1f}  p95 {np.percentile(node_ms, 95):.1f} ms (n = {node_ms.size})')
    print(f'  poses published {n_sent}, drawn {ms.size} ({100.0 * ms.size / max(n_sent, 1):.0f} '
          f'%; the rest merged into later frames), page frames {frames} '
          f'({frames / elapsed:.1f} fps)')


if __name__ == '__main__':
    main()

"""The guidance page in headless Chromium: it receives and draws a path and a moving tip.

Skipped only when no Chromium binary is installed (Debian: ``apt-get install -y chromium``).
The screenshot goes to ``$CGAIL_GUI_SCREENSHOT`` when set (``docs/img/gui.png`` is made with
``CGAIL_GUI_SCREENSHOT=docs/img/gui.png``), else to the test's tmp dir.
"""

from __future__ import annotations

from collections.abc import Iterator
import os
from pathlib import Path
import socket
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState

from cgail_gui.cdp import Chromium, find_chromium
from cgail_gui.demo import centerline_scene
from cgail_gui.nodes.gui_node import GuiNode
from cgail_rig.launch_spec import default_launch_file, load_launch_file
from cgail_sim.anatomy import build_anatomy
from cgail_sim.centerline import compute_centerlines

pytestmark = pytest.mark.skipif(find_chromium() is None,
                                reason='chromium not installed (apt-get install -y chromium)')

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
START_INDEX = 55.0


class Scene:
    """Publishes a planner + tracker scene along the left centreline of the default aorta."""

    def __init__(self, node: Node) -> None:
        anatomy = build_anatomy('default')
        self.path = compute_centerlines(anatomy)['left'].points
        self.node = node
        self.tip = node.create_publisher(PoseStamped, 'em_tracker/tip_pose',
                                         qos_profile_sensor_data)
        self.path_pub = node.create_publisher(PathMsg, 'planner/path', LATCHED)
        self.goal = node.create_publisher(PoseStamped, 'planner/goal', 10)
        self.wp = node.create_publisher(PointStamped, 'planner/next_waypoint',
                                        qos_profile_sensor_data)
        self.bend = node.create_publisher(JointState, 'planner/suggested_bend',
                                          qos_profile_sensor_data)
        self.diag = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.published: list[np.ndarray] = []

    def publish_plan(self) -> None:
        msg = PathMsg()
        msg.header.frame_id = 'phantom'
        for p in self.path:
            ps = PoseStamped()
            ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = (float(v) for v in p)
            msg.poses.append(ps)
        self.path_pub.publish(msg)
        goal = PoseStamped()
        goal.header.frame_id = 'phantom'
        goal.pose.position.x, goal.pose.position.y, goal.pose.position.z = \
            (float(v) for v in self.path[-1])
        self.goal.publish(goal)
        self.diag.publish(DiagnosticArray(status=[DiagnosticStatus(
            level=DiagnosticStatus.OK, name='aurora: EM tracker', message='tracking',
            hardware_id='ndi_aurora:sim', values=[KeyValue(key='rms_error_mm', value='0.3')])]))

    def publish_tip(self, index: float) -> None:
        pose = centerline_scene(self.path, index)
        msg = PoseStamped()
        msg.header.frame_id = 'phantom'
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = \
            (float(v) for v in pose.position)
        (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
         msg.pose.orientation.w) = (float(v) for v in pose.quaternion)
        wp = PointStamped()
        wp.header = msg.header
        wp.point.x, wp.point.y, wp.point.z = (float(v) for v in pose.waypoint)
        self.wp.publish(wp)
        self.bend.publish(JointState(name=['bend_alpha', 'bend_gamma'],
                                     position=[float(pose.bend[0]), float(pose.bend[1])]))
        self.tip.publish(msg)
        self.published.append(pose.position)


REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return int(s.getsockname()[1])


@pytest.fixture
def gui() -> Iterator[tuple[GuiNode, Scene]]:
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)  # SIGTERM ends the run
    # the scene publishes on the rig's names: the gui takes the sim rig's remaps onto them
    (spec,) = load_launch_file(default_launch_file()).select(['gui']).nodes
    remaps = ['--ros-args',
              *(w for rule in spec.remappings.items() for w in ('-r', ':='.join(rule)))]
    node = GuiNode(parameter_overrides=[Parameter('port', value=free_port()),
                                        Parameter('anatomy', value='default'),
                                        Parameter('stale_after_s', value=3.0),
                                        Parameter('bags_dir', value=str(REPO / 'bags'))],
                   cli_args=remaps)
    pub = rclpy.create_node('gui_browser_scene')
    scene = Scene(pub)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(pub)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield node, scene
    finally:
        executor.shutdown()
        thread.join(5)
        node.destroy_node()
        pub.destroy_node()
        rclpy.try_shutdown()


COLOUR_COUNT = """(() => {
  const c = document.querySelector('#external-box canvas');
  const t = document.createElement('canvas'); t.width = c.width; t.height = c.height;
  const x = t.getContext('2d'); x.drawImage(c, 0, 0);
  const d = x.getImageData(0, 0, t.width, t.height).data;
  let path = 0, tip = 0;
  for (let i = 0; i < d.length; i += 4) {
    const r = d[i], g = d[i + 1], b = d[i + 2];
    if (b > 180 && g > 150 && r < 120) path++;                 // path cyan #35d0ff
    if (r > 200 && g > 110 && g < 200 && b < 90) tip++;        // tip orange #ff9f1c
  }
  return {path, tip};
})()"""


def test_page_receives_and_draws_path_and_moving_tip(gui: tuple[GuiNode, Scene],
                                                     tmp_path: Path) -> None:
    node, scene = gui
    scene.publish_plan()
    index = START_INDEX
    with Chromium.launch() as browser:
        page = browser.open(node.url)
        page.wait_for('window.gui && window.gui.connected', timeout=30)
        page.wait_for('window.gui.drawn.meshVertices > 0 && window.gui.drawn.pathPoints > 0',
                      timeout=60)
        assert page.evaluate('window.gui.webgl') is True
        assert page.evaluate('window.gui.drawn.pathPoints') == len(scene.path)
        # a moving tip: publish at ~40 Hz and watch the drawn tip follow
        seen = []
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len({tuple(s) for s in seen}) < 5:
            scene.publish_tip(index)
            index += 0.25
            time.sleep(0.025)
            drawn = page.evaluate('window.gui.drawn.tipMm')
            if drawn:
                seen.append(drawn)
        assert len({tuple(s) for s in seen}) >= 5, seen
        last = np.array(page.evaluate('window.gui.drawn.tipMm')) / 1000.0
        assert min(np.linalg.norm(np.array(scene.published) - last, axis=1)) < 1e-6
        state = page.evaluate('({t: window.gui.drawn.target, w: window.gui.drawn.waypoint, '
                              'b: window.gui.drawn.bendArrow, f: window.gui.frames, '
                              'wall: document.getElementById("ro-wall").textContent, '
                              'tgt: document.getElementById("ro-target").textContent, '
                              'trk: document.getElementById("tracker").textContent, '
                              'timer: document.getElementById("timer").className})')
        assert state['t'] and state['w'] and state['b'] is not None and state['f'] > 5
        assert state['tgt'].endswith(' mm') and state['wall'].endswith(' mm')
        assert state['trk'] == 'Tracker: OK'
        assert 'running' in state['timer']        # the clock started when the tip moved
        pixels = page.evaluate(COLOUR_COUNT)
        assert pixels['path'] > 200 and pixels['tip'] > 30, pixels
        # a still scene: software WebGL returns to full resolution, then the screenshot
        scene.publish_tip(index)
        page.wait_for('window.gui.renderScale === undefined || window.gui.renderScale === 1',
                      timeout=10)
        time.sleep(0.5)
        png = page.screenshot()
        # the node's server goes away and comes back: the page reconnects, gets everything
        node._server.stop()
        page.wait_for('!window.gui.connected', timeout=10)
        assert page.evaluate('document.getElementById("conn").textContent').startswith('Disc')
        node._server.start()
        page.wait_for('window.gui.connected && window.gui.fullStates >= 2', timeout=15)
        page.wait_for(f'window.gui.drawn.pathPoints === {len(scene.path)}', timeout=10)
        # replay a bag from the page's own controls, then back to live
        page.evaluate('(() => { const s = document.getElementById("replay-bag"); '
                      's.value = "fixtures/cgail_trial"; '
                      'document.getElementById("replay-rate").value = "4"; '
                      'document.getElementById("replay-play").click(); return s.value; })()')
        page.wait_for('document.getElementById("source").textContent.startsWith("REPLAY") '
                      '&& window.gui.drawn.pathPoints === 40 && window.gui.drawn.tipSeq > 10',
                      timeout=15)
        page.evaluate('document.getElementById("replay-live").click()')
        page.wait_for('document.getElementById("source").textContent === "LIVE" && '
                      f'window.gui.drawn.pathPoints === {len(scene.path)}', timeout=10)
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 20_000
    out = Path(os.environ.get('CGAIL_GUI_SCREENSHOT') or tmp_path / 'gui.png')
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(png)

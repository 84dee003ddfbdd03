"""A short simulated trial of ``planner_node`` in the lean rig install (test/test_lean_rig.py).

Run inside the lean install (``CGAIL_PREFIX=... scripts/ws python test/lean_rig_trial.py``)
while ``planner_node`` runs there with a committed policy. This probe plays the rig around the
planner: the tracked tip (``planner/tip_pose``) at the default anatomy's first start, then the
goal (``planner/goal``, that scenario set's first target); once the path is planned the tip
follows it as the follow-the-leader catheter does, one pose per path point, and every pose must
get its guidance (``planner/next_waypoint`` and ``planner/suggested_bend``) before the next one
is sent (lockstep: no wall-clock pacing). Prints one line per check and a summary JSON line;
exits 1 on the first check that fails.
"""

from __future__ import annotations

import json
import math
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

from cgail_planner.nodes import conversions as conv
from cgail_sim.worlds import load_world

# generous bounds on a loaded machine: a fresh install compiles the numba kernels on first use
PLAN_TIMEOUT_S = 300.0
REPLY_TIMEOUT_S = 60.0


def fail(message: str) -> None:
    print(f'FAIL: {message}', flush=True)
    sys.exit(1)


def heading_frames(path: np.ndarray, first: np.ndarray) -> list[np.ndarray]:
    """Tip rotations along ``path`` (columns x, y = heading, z), rotating ``first`` minimally."""
    frames, rot = [], first.copy()
    for i in range(len(path)):
        j = min(i + 1, len(path) - 1)
        d = path[j] - path[j - 1]
        y = d / np.linalg.norm(d)
        x = rot[:, 0] - np.dot(rot[:, 0], y) * y
        x /= np.linalg.norm(x)
        rot = np.column_stack([x, y, np.cross(x, y)])
        frames.append(rot)
    return frames


def main() -> None:
    world = load_world('default')
    start = world.scenarios.starts[0]
    goal = np.asarray(world.scenarios.targets[0].position, dtype=float)
    rclpy.init()
    node = rclpy.create_node('lean_rig_probe')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    pose_pub = node.create_publisher(PoseStamped, 'planner/tip_pose', conv.SENSOR_QOS)
    goal_pub = node.create_publisher(PoseStamped, 'planner/goal', conv.COMMAND_QOS)
    paths: list[Path] = []
    waypoints: list[PointStamped] = []
    bends: list[JointState] = []
    diags: list[DiagnosticArray] = []
    node.create_subscription(Path, 'planner/path', paths.append, conv.LATCHED_QOS)
    node.create_subscription(PointStamped, 'planner/next_waypoint', waypoints.append,
                             conv.SENSOR_QOS)
    node.create_subscription(JointState, 'planner/suggested_bend', bends.append,
                             conv.SENSOR_QOS)
    node.create_subscription(DiagnosticArray, '/diagnostics', diags.append,
                             conv.DIAGNOSTICS_QOS)

    def spin_until(predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not predicate():
            executor.spin_once(timeout_sec=0.05)
        return bool(predicate())

    def send_pose(position: np.ndarray, rotation: np.ndarray) -> None:
        pose_pub.publish(conv.pose_msg(node.get_clock().now().to_msg(), 'phantom',
                                       position, rotation))

    if not spin_until(lambda: pose_pub.get_subscription_count() > 0
                      and goal_pub.get_subscription_count() > 0, PLAN_TIMEOUT_S):
        fail('planner_node did not subscribe to planner/tip_pose and planner/goal')
    print('ok: planner_node is up', flush=True)

    # the tip at the start, then the goal; the pose is sent again until a path comes back
    # (best-effort sensor QoS may drop one)
    goal_pub.publish(conv.pose_msg(node.get_clock().now().to_msg(), 'phantom', goal,
                                   np.eye(3)))
    t0 = time.monotonic()
    while not paths and time.monotonic() - t0 < PLAN_TIMEOUT_S:
        send_pose(start.position, start.rotation)
        spin_until(lambda: bool(paths), 1.0)
    if not paths:
        fail(f'no planner/path within {PLAN_TIMEOUT_S:.0f} s of the goal')
    path = conv.path_points(paths[-1])
    plan_s = time.monotonic() - t0
    print(f'ok: path of {len(path)} points planned in {plan_s:.1f} s', flush=True)
    if not np.all(np.isfinite(path)):
        fail('the path holds non-finite points')
    if np.linalg.norm(path[0] - start.position) > 0.005:
        fail(f'the path starts {np.linalg.norm(path[0] - start.position) * 1e3:.1f} mm '
             'from the tip, expected within 5 mm')
    inside = world.anatomy.contains(path)
    if inside.mean() < 0.99:
        fail(f'only {inside.mean():.0%} of the path lies inside the lumen, expected >= 99%')

    # the catheter follows the path (follow the leader); every pose gets its guidance
    replies = 0
    for position, rotation in zip(path, heading_frames(path, start.rotation), strict=True):
        n_wp, n_bend = len(waypoints), len(bends)

        def answered(n_wp: int = n_wp, n_bend: int = n_bend) -> bool:
            return len(waypoints) > n_wp and len(bends) > n_bend

        ok = False
        for _ in range(int(REPLY_TIMEOUT_S)):
            send_pose(position, rotation)
            if spin_until(answered, 1.0):
                ok = True
                break
        if not ok:
            fail(f'no guidance for pose {replies} within {REPLY_TIMEOUT_S:.0f} s')
        bend = np.asarray(bends[-1].position, dtype=float)
        if bend.shape != (2,) or not np.all(np.isfinite(bend)):
            fail(f'suggested bend {bend.tolist()}: expected two finite angles')
        replies += 1
    tip_to_goal = float(np.linalg.norm(path[-1] - goal))
    tolerance = 0.010
    if tip_to_goal > tolerance:
        fail(f'the tip ends {tip_to_goal * 1e3:.1f} mm from the goal, expected within '
             f'{tolerance * 1e3:.0f} mm')
    print(f'ok: {replies} poses along the path, each with its guidance; '
          f'the tip ends {tip_to_goal * 1e3:.1f} mm from the goal', flush=True)
    statuses = [(s.level, s.message) for d in diags for s in d.status
                if s.name.startswith('planner')]
    if (DiagnosticStatus.OK, 'guiding') not in statuses:
        fail(f'planner_node reported no OK guiding diagnostics during the trial: {statuses[-5:]}')
    print('ok: planner diagnostics OK', flush=True)
    print(json.dumps({'path_points': len(path), 'plan_s': round(plan_s, 1),
                      'guided_poses': replies, 'tip_to_goal_mm': round(tip_to_goal * 1e3, 2),
                      'path_length_mm': round(float(np.sum(np.linalg.norm(
                          np.diff(path, axis=0), axis=1))) * 1e3, 1),
                      'torch_loaded': 'torch' in sys.modules,
                      'max_bend_deg': round(math.degrees(max(
                          float(np.max(np.abs(b.position))) for b in bends)), 1)}),
          flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    main()

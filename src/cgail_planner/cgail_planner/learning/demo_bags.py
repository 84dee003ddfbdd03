"""Demonstration bags: rosbag2 MCAP (``rosbags``, ``Stores.ROS2_JAZZY``) <-> (obs, act) arrays.

One bag holds many episodes of one anatomy. Topics (standard messages, SI units, frame
``phantom``):

===========================  ==============================  ==================================
topic                        type                            content
===========================  ==============================  ==================================
``demo/episode``             std_msgs/msg/String             JSON at each episode start:
                                                             index, anatomy, mode, start,
                                                             target, steps, success
``demo/tip_pose``            geometry_msgs/msg/PoseStamped   tip pose after each step
``demo/action``              sensor_msgs/msg/JointState      commanded step: ``bend_alpha``,
                                                             ``bend_gamma`` (rad),
                                                             ``insertion`` (m, delta_l)
``demo/target``              geometry_msgs/msg/PointStamped  target position at each step
===========================  ==============================  ==================================

Episode ``e`` step ``t`` is stamped ``e * 1000 s + t * dt``. The bags hold no observation
vectors (that keeps them small): :func:`load_demo_bag` re-simulates each episode from its start
and target with the recorded commands (normalised back with
:func:`cgail_planner.sim.catheter.command_to_action`) and checks that the re-simulated tip
follows the recorded poses, so the (obs, act) arrays always match the current observation
layout; a mismatch raises :class:`DemoError`.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.writer import CompressionFormat, CompressionMode
from rosbags.typesys import get_typestore, Stores

from cgail_planner.learning.errors import DemoError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
EPISODE_PERIOD_NS = 1000 * 10**9
POSE_TOLERANCE_M = 1e-6


@dataclass
class DemoEpisode:
    """One recorded demonstration."""

    start: int
    target: int
    alpha: np.ndarray      # (T,) rad
    gamma: np.ndarray      # (T,) rad
    delta_l: np.ndarray    # (T,) m
    tip_position: np.ndarray   # (T, 3) after each step
    tip_quaternion: np.ndarray  # (T, 4) x, y, z, w
    target_position: np.ndarray  # (T, 3)
    success: bool


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (x, y, z, w) unit quaternion (Shepperd's method)."""
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i] = s / 4
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
    out = np.asarray(q, dtype=np.float64)
    return out / np.linalg.norm(out)


def _stamp(ns: int) -> Any:
    T = TYPESTORE.types
    return T['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9)


def zstd_available() -> bool:
    """Whether the ``zstandard`` package (MCAP chunk compression) is importable."""
    try:
        import zstandard  # noqa: F401
    except ImportError:
        return False
    return True


def write_demo_bag(path: Path, episodes: list[DemoEpisode], *, anatomy: str, mode: str,
                   dt: float, compress: bool | None = None) -> Path:
    """Write ``episodes`` to a new MCAP bag directory ``path`` (must not exist).

    ``compress`` (default: when ``zstandard`` is installed) zstd-compresses the MCAP chunks,
    about 5x smaller.
    """
    if compress is None:
        compress = zstd_available()
    T = TYPESTORE.types
    Header = T['std_msgs/msg/Header']
    if path.exists():
        raise DemoError(f'demo bag already exists: {path} (remove it first)')
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compress:
        # zstd chunk compression inside the MCAP file (needs the zstandard package)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.set_custom_data('cgail_planner.demos', json.dumps(
        {'anatomy': anatomy, 'mode': mode, 'dt': dt, 'episodes': len(episodes)}))
    with writer:
        c_ep = writer.add_connection('demo/episode', 'std_msgs/msg/String', typestore=TYPESTORE)
        c_pose = writer.add_connection('demo/tip_pose', 'geometry_msgs/msg/PoseStamped',
                                       typestore=TYPESTORE)
        c_act = writer.add_connection('demo/action', 'sensor_msgs/msg/JointState',
                                      typestore=TYPESTORE)
        c_tgt = writer.add_connection('demo/target', 'geometry_msgs/msg/PointStamped',
                                      typestore=TYPESTORE)
        for e, ep in enumerate(episodes):
            t0 = e * EPISODE_PERIOD_NS
            info = {'index': e, 'anatomy': anatomy, 'mode': mode, 'start': ep.start,
                    'target': ep.target, 'steps': len(ep.alpha), 'success': ep.success}
            msg = T['std_msgs/msg/String'](data=json.dumps(info))
            writer.write(c_ep, t0, TYPESTORE.serialize_cdr(msg, 'std_msgs/msg/String'))
            for t in range(len(ep.alpha)):
                ns = t0 + round((t + 1) * dt * 1e9)
                hdr = Header(stamp=_stamp(ns), frame_id='phantom')
                p, q = ep.tip_position[t], ep.tip_quaternion[t]
                pose = T['geometry_msgs/msg/PoseStamped'](header=hdr, pose=T[
                    'geometry_msgs/msg/Pose'](
                    position=T['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
                    orientation=T['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2],
                                                                  w=q[3])))
                writer.write(c_pose, ns, TYPESTORE.serialize_cdr(
                    pose, 'geometry_msgs/msg/PoseStamped'))
                js = T['sensor_msgs/msg/JointState'](
                    header=hdr, name=['bend_alpha', 'bend_gamma', 'insertion'],
                    position=np.array([ep.alpha[t], ep.gamma[t], ep.delta_l[t]]),
                    velocity=np.zeros(0), effort=np.zeros(0))
                writer.write(c_act, ns, TYPESTORE.serialize_cdr(js, 'sensor_msgs/msg/JointState'))
                g = ep.target_position[t]
                pt = T['geometry_msgs/msg/PointStamped'](
                    header=hdr, point=T['geometry_msgs/msg/Point'](x=g[0], y=g[1], z=g[2]))
                writer.write(c_tgt, ns, TYPESTORE.serialize_cdr(
                    pt, 'geometry_msgs/msg/PointStamped'))
    return path


def read_demo_bag(path: Path) -> tuple[dict[str, Any], list[DemoEpisode]]:
    """Episodes of a demo bag (no simulation)."""
    if not path.exists():
        raise DemoError(f'demo bag not found: {path}')
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises several unrelated types for unreadable bags
        raise DemoError(f'{path}: not a readable rosbag2 bag ({exc})') from None
    try:
        heads: list[dict[str, Any]] = []
        rows: dict[str, list[list[Any]]] = {}
        for conn, _, raw in reader.messages():
            msg: Any = TYPESTORE.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == 'demo/episode':
                heads.append(json.loads(msg.data))
                rows = {'pose': [], 'act': [], 'tgt': []}
                heads[-1]['_rows'] = rows
            elif conn.topic == 'demo/tip_pose':
                p, o = msg.pose.position, msg.pose.orientation
                rows['pose'].append([p.x, p.y, p.z, o.x, o.y, o.z, o.w])
            elif conn.topic == 'demo/action':
                rows['act'].append(list(msg.position))
            elif conn.topic == 'demo/target':
                rows['tgt'].append([msg.point.x, msg.point.y, msg.point.z])
    except ImportError as exc:
        raise DemoError(f'{path}: zstd-compressed bag; install the reader: '
                        f'pip install zstandard==0.25.0 ({exc})') from None
    finally:
        reader.close()
    if not heads:
        raise DemoError(f'{path}: expected demo/episode messages, found none')
    meta = {'anatomy': heads[0]['anatomy'], 'mode': heads[0]['mode']}
    episodes = []
    for h in heads:
        r = h.pop('_rows')
        pose, act = np.asarray(r['pose']), np.asarray(r['act'])
        if len(pose) != h['steps'] or len(act) != h['steps']:
            raise DemoError(f'{path}: episode {h["index"]}: expected {h["steps"]} steps, '
                            f'found {len(pose)} poses and {len(act)} actions')
        episodes.append(DemoEpisode(h['start'], h['target'], act[:, 0], act[:, 1], act[:, 2],
                                    pose[:, :3], pose[:, 3:], np.asarray(r['tgt']),
                                    bool(h['success'])))
    return meta, episodes


def resimulate(env: Any, episodes: list[DemoEpisode]) -> tuple[np.ndarray, np.ndarray]:
    """(obs, act) of ``episodes`` replayed in ``env`` (a CatheterNavEnv of the bag's anatomy)."""
    from cgail_planner.sim.catheter import command_to_action

    eng = env.unwrapped.engine
    cat = eng.config.catheter
    obs_l, act_l = [], []
    for k, ep in enumerate(episodes):
        obs, _ = env.reset(options={'start': ep.start, 'target': ep.target})
        acts = command_to_action(ep.alpha, ep.gamma, ep.delta_l, eng.catheter.theta_max,
                                 cat.segment_length, cat.max_step_insertion).astype(np.float32)
        for t, a in enumerate(acts):
            obs_l.append(obs)
            act_l.append(a)
            obs, _, te, tr, _ = env.step(a)
            err = float(np.linalg.norm(eng.catheter.tip_position[0] - ep.tip_position[t]))
            if err > POSE_TOLERANCE_M:
                raise DemoError(f'episode {k} step {t}: re-simulated tip is {err * 1e3:.3f} mm '
                                'from the recorded pose: expected the same simulator and '
                                'anatomy as when recorded')
            if (te or tr) and t < len(acts) - 1:
                raise DemoError(f'episode {k}: re-simulation ended at step {t}, expected '
                                f'{len(acts)} steps')
    return np.stack(obs_l).astype(np.float32), np.stack(act_l).astype(np.float32)


def load_demo_bag(path: Path, only_successful: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(obs, act) arrays of a demo bag, re-simulated in the static simulator."""
    from cgail_planner.sim.config import EnvConfig
    from cgail_planner.sim.env import CatheterNavEnv

    meta, episodes = read_demo_bag(path)
    if only_successful:
        episodes = [e for e in episodes if e.success]
    if not episodes:
        raise DemoError(f'{path}: no successful demonstrations')
    env = CatheterNavEnv(EnvConfig(mode='static', anatomy=meta.get('anatomy', 'default')))
    return resimulate(env, episodes)

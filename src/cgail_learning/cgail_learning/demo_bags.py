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

Episode ``e`` step ``t`` is stamped ``e * 1000 s + t * dt``. The bag's rosbag2 custom data
(``metadata.yaml``, key ``cgail_planner.demos``) holds JSON with the anatomy name (a built-in
name, or a path anatomy's label), mode, dt, episode count and, in bags written since it was
added, ``anatomy_hash``: the :attr:`~cgail_sim.anatomy.Anatomy.content_hash` of the
mesh the episodes were recorded in, and ``numpy_simd``, the numpy SIMD targets of the
recording process; a bag recorded in a path anatomy also holds ``anatomy_path``, the absolute
path it was loaded from, which :func:`replay_demo_bag` re-simulates in unless told otherwise.

A bag converted from teleoperated session bags (``make_demos --from-bags``,
:mod:`cgail_learning.teleop_demos`) has the same topics; its custom data also holds
``source``: the bags, the conversion's settings and how much of the recorded motion the
catheter model could not follow (clipped steps, deviation). Its ``demo/tip_pose`` are the
simulated poses of the conversion, so it replays under the same tolerance.

A **population bag** (``make_demos --population N``; custom data ``population: true``) holds
episodes of many population anatomies: each episode's ``demo/episode`` JSON names its anatomy
(``population-<seed>``) and its content hash, and :func:`replay_demo_bag` rebuilds each
anatomy (:func:`~cgail_sim.population.sample_anatomy`) and re-simulates its episodes
there, under the same tolerance; the report's anatomy hash is :func:`population_hash` of the
episodes' (in bag order).

The bags hold no observation vectors (that keeps them small): :func:`load_demo_bag` re-simulates
each episode with the recorded commands (normalised back with
:func:`cgail_sim.ftl_model.command_to_action`), so the (obs, act) arrays always match the
current observation layout. A built-in anatomy is not bit-identical across CPUs (numpy's SIMD
ufuncs differ in the last bits and the remeshing amplifies that, see
:mod:`cgail_sim.disk_cache`): the scenario's start pose, taken from the Voronoi
centerline, moves by tens of micrometres and up to ~1.3 deg, which an open-loop replay grows
into millimetres over a 200 mm path. So each episode is replayed from the pose it was recorded
from (:func:`recorded_start_pose`; on the recording machine that is the scenario's start pose
itself) and the replay is held to a physical tolerance, :data:`POSE_TOLERANCE_M` (1 mm), not to
bit equality:

* the recorded start's offset from the scenario's start, the recorded target's from the
  scenario's target and the re-simulated tip's from every recorded pose must stay within it;
  the start offsets and the tip drift (max / mean) are logged and returned in a
  :class:`ReplayReport`;
* a recorded anatomy hash that differs from the current anatomy's issues a
  :class:`~cgail_learning.errors.DemoAnatomyWarning` naming both hashes and the
  offsets; bags without a hash (recorded before it was stored) load without one;
* a distance beyond the tolerance, or a re-simulation that collides or exits before the
  recorded end, raises a one-line :class:`~cgail_learning.errors.DemoError`. A
  re-simulation that reaches the target before the recorded end (a target moved by the
  remeshing moves the 10 mm success boundary) keeps the steps up to there
  (``ReplayReport.ended_early``).
"""

from __future__ import annotations

from dataclasses import dataclass
import json
import logging
from pathlib import Path
from typing import Any, NamedTuple
import warnings

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin
from rosbags.rosbag2.writer import CompressionFormat, CompressionMode
from rosbags.typesys import get_typestore, Stores

from cgail_bags.bagio import JazzyWriter
from cgail_learning.errors import DemoAnatomyWarning, DemoError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
EPISODE_PERIOD_NS = 1000 * 10**9
CUSTOM_DATA_KEY = 'cgail_planner.demos'
"""Key of the bag's JSON metadata in the rosbag2 ``custom_data`` of ``metadata.yaml``.

A format name, not a module path: it names the package that wrote the first demonstration bags
(before ``cgail_planner`` was split), and stays so that every bag recorded since still reads."""
POSE_TOLERANCE_M = 1e-3
"""Largest distance (m) of a recorded start, target or tip pose from the re-simulation that still
counts as the same demonstration: 1 mm, about the accuracy of the Aurora EM tracker the rig
tracks the tip with (0.48 mm RMS). Another CPU's build of the built-in anatomies moves the
scenario starts by 0.05-0.12 mm (measured with numpy's AVX-512 and AVX2 paths); the replay
itself follows the recorded poses to ~1e-16 m."""

_LOG = logging.getLogger(__name__)


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
    anatomy: str | None = None
    """The anatomy this episode ran in when it is not the bag's (a population bag:
    ``population-<seed>``, :func:`~cgail_sim.population.population_name`)."""
    anatomy_hash: str | None = None
    """Content hash of that anatomy as recorded (population bags)."""


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


@dataclass(frozen=True)
class ReplayReport:
    """How the episodes of a demo bag re-simulated in the current simulator."""

    source: str
    """The bag."""
    episodes: int
    """Episodes re-simulated."""
    steps: int
    """(obs, act) pairs produced."""
    max_start_offset_m: float
    """Largest distance of an episode's recorded start from the scenario's start pose, m."""
    mean_start_offset_m: float
    """Mean of that distance over the episodes, m."""
    max_drift_m: float
    """Largest distance of a re-simulated tip from its recorded pose, m."""
    mean_drift_m: float
    """Mean of that distance over every re-simulated step, m."""
    ended_early: int
    """Episodes whose re-simulation reached the target before the recorded last step."""
    recorded_anatomy_hash: str | None
    """Content hash of the anatomy the bag was recorded in (None: an older bag without one)."""
    anatomy_hash: str
    """Content hash of the anatomy it was re-simulated in."""
    tolerance_m: float
    """The drift allowed, m."""

    @property
    def same_anatomy(self) -> bool | None:
        """Whether the hashes agree (None when the bag has no hash)."""
        if self.recorded_anatomy_hash is None:
            return None
        return self.recorded_anatomy_hash == self.anatomy_hash

    def summary(self) -> str:
        """One line: episodes, steps, start offset and drift (max / mean), anatomy hashes."""
        if self.same_anatomy is None:
            anatomy = f'anatomy {self.anatomy_hash} (the bag records no anatomy hash)'
        elif self.same_anatomy:
            anatomy = f'anatomy {self.anatomy_hash}, as recorded'
        else:
            anatomy = (f'anatomy {self.anatomy_hash}, recorded in '
                       f'{self.recorded_anatomy_hash}')
        early = f', {self.ended_early} reached the target early' if self.ended_early else ''
        return (f'{self.source}: {self.episodes} episodes, {self.steps} steps re-simulated'
                f'{early}; recorded starts off the scenario starts by max '
                f'{self.max_start_offset_m * 1e3:.3g} mm, mean '
                f'{self.mean_start_offset_m * 1e3:.3g} mm; tip drift from the recorded poses '
                f'max {self.max_drift_m * 1e3:.3g} mm, mean {self.mean_drift_m * 1e3:.3g} mm '
                f'(tolerance {self.tolerance_m * 1e3:g} mm); {anatomy}')


class Replay(NamedTuple):
    """Re-simulated demonstrations: ``(obs, act)`` pairs and how the replay went."""

    obs: np.ndarray
    """(M, obs_dim) float32 observations."""
    act: np.ndarray
    """(M, 3) float32 actions in [-1, 1]."""
    report: ReplayReport


def write_demo_bag(path: Path, episodes: list[DemoEpisode], *, anatomy: str, mode: str,
                   dt: float, compress: bool | None = None,
                   anatomy_hash: str | None = None, anatomy_path: str | None = None,
                   scenario_seed: int = 0, env_options: str = 'ours',
                   population: bool = False, source: dict[str, Any] | None = None) -> Path:
    """Write ``episodes`` to a new MCAP bag directory ``path`` (must not exist).

    ``compress`` (default: when ``zstandard`` is installed) zstd-compresses the MCAP chunks,
    about 5x smaller. ``anatomy_hash`` (the recording anatomy's
    :attr:`~cgail_sim.anatomy.Anatomy.content_hash`) is stored in the custom data with
    the numpy SIMD targets of this process, and ``anatomy_path`` (the absolute path of a path
    anatomy; ``anatomy`` is then its label) too. ``scenario_seed`` is the target set the
    episodes' target ids refer to (``EnvConfig.scenario_seed``); stored when it is not 0.
    ``env_options`` is the env option set the episodes were recorded in (informational: a
    replay uses its caller's); stored when it is not ``ours``. ``population`` marks a bag whose
    episodes each ran in their own population anatomy (``DemoEpisode.anatomy``, written into
    each episode's ``demo/episode`` JSON with its content hash); ``anatomy`` is then the
    population's label and ``anatomy_hash`` :func:`population_hash` of the episodes'.
    ``source`` (JSON-ready) says where episodes not recorded by the scripted expert come from
    (``make_demos --from-bags``: the session bags, the conversion's settings, clipping and
    deviation; :mod:`cgail_learning.teleop_demos`); stored as is, informational.
    """
    if compress is None:
        compress = zstd_available()
    T = TYPESTORE.types
    Header = T['std_msgs/msg/Header']
    if path.exists():
        raise DemoError(f'demo bag already exists: {path} (remove it first)')
    writer = JazzyWriter(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compress:
        # zstd chunk compression inside the MCAP file (needs the zstandard package)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    info: dict[str, Any] = {'anatomy': anatomy, 'mode': mode, 'dt': dt,
                            'episodes': len(episodes)}
    if anatomy_hash is not None:
        from cgail_sim.disk_cache import numpy_simd_targets

        info['anatomy_hash'] = anatomy_hash
        info['numpy_simd'] = ','.join(numpy_simd_targets())
    if anatomy_path is not None:
        info['anatomy_path'] = anatomy_path
    if scenario_seed:
        info['scenario_seed'] = int(scenario_seed)
    if env_options != 'ours':
        info['env_options'] = env_options
    if population:
        from cgail_sim.anatomy import ANATOMY_NAMES
        from cgail_sim.anatomy_spec import is_named

        missing = [e for e, ep in enumerate(episodes) if not is_named(ep.anatomy or '')]
        if missing:
            raise DemoError(f'population bag: expected every episode in a population anatomy '
                            f'(population-<seed>) or a built-in one {sorted(ANATOMY_NAMES)}, '
                            f'found episodes {missing[:5]} without one')
        info['population'] = True
    if source is not None:
        info['source'] = source
    writer.set_custom_data(CUSTOM_DATA_KEY, json.dumps(info))
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
            info = {'index': e, 'anatomy': ep.anatomy or anatomy, 'mode': mode,
                    'start': ep.start, 'target': ep.target, 'steps': len(ep.alpha),
                    'success': ep.success}
            if ep.anatomy_hash is not None:
                info['anatomy_hash'] = ep.anatomy_hash
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
    """Episodes of a demo bag (no simulation).

    Returns:
        ``(meta, episodes)``: ``meta`` has ``anatomy``, ``mode``, ``env_options`` (only when
        recorded in another option set than ``ours``) and ``scenario_seed`` (0 when
        the bag does not record one), and ``anatomy_hash``, ``numpy_simd`` and
        ``anatomy_path`` when the bag records them, and ``population`` (True) for a bag
        whose episodes each name their own population anatomy.
    """
    if not path.exists():
        raise DemoError(f'demo bag not found: {path}')
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises several unrelated types for unreadable bags
        raise DemoError(f'{path}: not a readable rosbag2 bag ({exc})') from None
    # rosbags exposes a bag directory's metadata.yaml custom_data only on its storage reader
    custom = custom_info(path, getattr(getattr(reader.storage, 'metadata', None), 'custom',
                                        None))
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
    meta.update({k: str(custom[k]) for k in ('anatomy_hash', 'numpy_simd', 'anatomy_path',
                                             'env_options') if k in custom})
    meta['scenario_seed'] = custom.get('scenario_seed', 0)
    if custom.get('population'):  # (the episodes name their own anatomies)
        meta['population'] = True
        meta['anatomy'] = str(custom.get('anatomy', 'population'))
    if not isinstance(meta['scenario_seed'], int) or meta['scenario_seed'] < 0:
        raise DemoError(f'{path}: expected an int scenario_seed >= 0 in its custom data, found '
                        f'{meta["scenario_seed"]!r}')
    episodes = []
    for h in heads:
        r = h.pop('_rows')
        pose, act = np.asarray(r['pose']), np.asarray(r['act'])
        if len(pose) != h['steps'] or len(act) != h['steps']:
            raise DemoError(f'{path}: episode {h["index"]}: expected {h["steps"]} steps, '
                            f'found {len(pose)} poses and {len(act)} actions')
        own = meta.get('population', False)
        episodes.append(DemoEpisode(h['start'], h['target'], act[:, 0], act[:, 1], act[:, 2],
                                    pose[:, :3], pose[:, 3:], np.asarray(r['tgt']),
                                    bool(h['success']), h['anatomy'] if own else None,
                                    h.get('anatomy_hash') if own else None))
    return meta, episodes


def custom_info(path: Path, custom: dict[str, str] | None) -> dict[str, Any]:
    """The bag's JSON custom data (empty for bags without it)."""
    text = (custom or {}).get(CUSTOM_DATA_KEY)
    if text is None:
        return {}
    try:
        info = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DemoError(f'{path}: expected JSON in custom data {CUSTOM_DATA_KEY}, found '
                        f'{text[:60]!r} ({exc})') from None
    if not isinstance(info, dict):
        raise DemoError(f'{path}: expected a JSON object in custom data {CUSTOM_DATA_KEY}, '
                        f'found {type(info).__name__}')
    return info


class ReplayDrift(NamedTuple):
    """How far a replay strayed from its recording (:func:`resimulate`)."""

    start_max_m: float
    """Largest distance of a recorded start from the scenario's start pose, m."""
    start_mean_m: float
    """Mean of that distance over the episodes, m."""
    max_m: float
    """Largest distance of a re-simulated tip from its recorded pose, m."""
    mean_m: float
    """Mean of that distance over the steps, m."""
    ended_early: int
    """Episodes that reached the target before their recorded end."""


def recorded_start_pose(ep: DemoEpisode) -> tuple[np.ndarray, np.ndarray] | None:
    """The tip pose an episode was recorded from, or None when its first step is no insertion.

    Inverts the first follow-the-leader step (:mod:`cgail_sim.ftl_model`):
    ``R1 = R0 Rx(alpha) Rz(gamma)`` and ``p1 = p0 + delta_l y_A(R1)``, from the first recorded
    pose ``[R1 | p1]`` and command.
    """
    from cgail_planner.core.rotations import quaternion_to_matrix
    from cgail_sim.ftl_model import bend_rotation

    if len(ep.delta_l) == 0 or not ep.delta_l[0] > 0.0:
        return None
    r1 = quaternion_to_matrix(ep.tip_quaternion[0])
    r0 = r1 @ bend_rotation(np.asarray(ep.alpha[0]), np.asarray(ep.gamma[0])).T
    p0 = np.asarray(ep.tip_position[0], dtype=np.float64) - float(ep.delta_l[0]) * r1[:, 1]
    return p0, r0


def resimulate(env: Any, episodes: list[DemoEpisode], *,
               tolerance_m: float = POSE_TOLERANCE_M, source: str = 'demonstrations',
               anatomy_note: str = '') -> tuple[np.ndarray, np.ndarray, ReplayDrift]:
    """(obs, act) of ``episodes`` replayed in ``env`` (a CatheterNavEnv of the bag's anatomy).

    Each episode is replayed from the pose it was recorded from (:func:`recorded_start_pose`),
    which is the scenario's start pose up to how the anatomy was meshed: on the recording
    machine they agree to rounding (then the scenario's pose is used as is, so the replay is
    the recording), elsewhere by tens of micrometres and a fraction of a degree, which an
    open-loop replay from the scenario's pose would grow into millimetres over a 200 mm path.
    Checked against ``tolerance_m``: the recorded start's distance from the scenario's start,
    the recorded targets' from the scenario's target, and every re-simulated tip position's
    from the recorded one.

    Returns:
        ``(obs, act, drift)``; ``drift`` holds the start offsets (max / mean over episodes),
        the tip drift (max / mean over steps) and the episodes that reached the target early.

    Raises:
        DemoError: a distance beyond ``tolerance_m``, or an episode that collides, exits or
            times out before its recorded end.
    """
    from cgail_sim.ftl_model import command_to_action

    eng = env.unwrapped.engine
    cat = eng.config.catheter
    sc = eng.scenarios
    obs_l, act_l = [], []
    starts: list[float] = []
    drift_max, drift_sum, n_steps, early = 0.0, 0.0, 0, 0

    def check(dist: float, what: str) -> None:
        if not dist <= tolerance_m:
            raise DemoError(
                f'{source}: {what}: expected it within {tolerance_m * 1e3:g} mm of the '
                f'recording, found {dist * 1e3:.3f} mm{anatomy_note}: re-record the '
                'demonstrations (cgail make-demos)')

    for k, ep in enumerate(episodes):
        if not (0 <= ep.start < len(sc.starts) and 0 <= ep.target < len(sc.targets)):
            raise DemoError(f'{source}: episode {k}: expected start < {len(sc.starts)} and '
                            f'target < {len(sc.targets)}, found {ep.start} and {ep.target}')
        start = sc.starts[ep.start]
        pose = recorded_start_pose(ep)
        options: dict[str, Any] = {'start': ep.start, 'target': ep.target}
        if pose is not None:
            offset = float(np.linalg.norm(pose[0] - start.position))
            check(offset, f'episode {k}: the recorded start')
            starts.append(offset)
            if offset > 1e-9 or float(np.abs(pose[1] - start.rotation).max()) > 1e-9:
                options['start_pose'] = pose
        target = sc.targets[ep.target].position
        check(float(np.linalg.norm(ep.target_position - target, axis=1).max()),
              f'episode {k}: the recorded target')
        if cat.forward_only and (np.asarray(ep.delta_l) < 0.0).any():
            t = int(np.argmax(np.asarray(ep.delta_l) < 0.0))
            raise DemoError(f'{source}: episode {k}: expected forward insertion only (the env '
                            f'options insert |a2|), found a retraction at step {t}')
        obs, _ = env.reset(options=options)
        acts = command_to_action(ep.alpha, ep.gamma, ep.delta_l, eng.catheter.theta_max,
                                 cat.segment_length, cat.max_step_insertion).astype(np.float32)
        for t, a in enumerate(acts):
            obs_l.append(obs)
            act_l.append(a)
            obs, _, te, tr, info = env.step(a)
            err = float(np.linalg.norm(eng.catheter.tip_position[0] - ep.tip_position[t]))
            drift_max = max(drift_max, err)
            drift_sum += err
            n_steps += 1
            check(err, f'episode {k} step {t}: the re-simulated tip')
            if (te or tr) and t < len(acts) - 1:
                if te and info['success']:
                    early += 1  # a moved target moved the 10 mm success boundary by a step
                    break
                why = ('a collision' if info['collision'] else 'leaving the anatomy'
                       if info['exited'] else 'the step limit')
                raise DemoError(f'{source}: episode {k}: expected the re-simulation to last '
                                f'{len(acts)} steps, found it ended by {why} at step {t}'
                                f'{anatomy_note}')
    obs_all = np.stack(obs_l).astype(np.float32)
    act_all = np.stack(act_l).astype(np.float32)
    drift = ReplayDrift(max(starts, default=0.0), float(np.mean(starts or [0.0])), drift_max,
                        drift_sum / max(n_steps, 1), early)
    return obs_all, act_all, drift


def replay_demo_bag(path: Path, only_successful: bool = True, *,
                    tolerance_m: float = POSE_TOLERANCE_M, anatomy: Any = None,
                    env_options: str = 'ours') -> Replay:
    """Re-simulate a demo bag in the static simulator of its anatomy (module docstring).

    Logs :meth:`ReplayReport.summary` and warns (:class:`DemoAnatomyWarning`) when the bag
    was recorded in an anatomy with another content hash.

    Args:
        path: the bag.
        only_successful: replay only the episodes that reached their target.
        tolerance_m: the replay tolerance, m.
        anatomy: the anatomy to re-simulate in (a name, a path or an ``Anatomy``); None: the
            bag's own, its recorded ``anatomy_path`` or its built-in anatomy name.
        env_options: the env option set to re-simulate in
            (:data:`cgail_sim.config.OPTION_SETS`): the observations are that set's.
            The bag stores no observation, so one recorded in either set replays in either
            (``paper_code``'s forward-only insertion cannot replay a retraction).

    Raises:
        DemoError: unreadable bag, no successful episode, a replay beyond ``tolerance_m``, or
            a bag recorded in a path anatomy that is no longer there (pass ``anatomy``).
    """
    from cgail_sim.anatomy_spec import is_named
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    if not (isinstance(tolerance_m, (int, float)) and 0.0 < tolerance_m < 1.0):
        raise DemoError(f'tolerance_m must be in (0, 1) m, found {tolerance_m!r}')
    meta, episodes = read_demo_bag(path)
    if only_successful:
        episodes = [e for e in episodes if e.success]
    if not episodes:
        raise DemoError(f'{path}: no successful demonstrations')
    if meta.get('population'):
        return _replay_population(path, meta, episodes, tolerance_m, anatomy, env_options)
    if anatomy is None:
        anatomy = meta.get('anatomy_path') or meta.get('anatomy', 'default')
        if not is_named(anatomy) and not Path(anatomy).exists():
            raise DemoError(
                f'{path}: expected the anatomy it was recorded in, {meta.get("anatomy")!r} '
                f'(content hash {meta.get("anatomy_hash")}) at {anatomy}, found no such path: '
                'give its prepared directory (train --anatomy DIR)')
    env = CatheterNavEnv(EnvConfig.from_options(env_options, mode='static', anatomy=anatomy,
                                                scenario_seed=meta['scenario_seed']))
    current = env.anatomy.content_hash
    recorded = meta.get('anatomy_hash')
    note = ''
    if recorded is not None and recorded != current:
        note = (f' (recorded in anatomy {recorded}, numpy SIMD '
                f'{meta.get("numpy_simd", "unknown")}; re-simulated in {current})')
    obs, act, drift = resimulate(env, episodes, tolerance_m=tolerance_m, source=str(path),
                                 anatomy_note=note)
    report = ReplayReport(source=str(path), episodes=len(episodes), steps=len(obs),
                          max_start_offset_m=drift.start_max_m,
                          mean_start_offset_m=drift.start_mean_m,
                          max_drift_m=drift.max_m, mean_drift_m=drift.mean_m,
                          ended_early=drift.ended_early, recorded_anatomy_hash=recorded,
                          anatomy_hash=current, tolerance_m=tolerance_m)
    if report.same_anatomy is False:
        from cgail_sim.disk_cache import numpy_simd_targets

        warnings.warn(DemoAnatomyWarning(
            f'{path}: recorded in {meta["anatomy"]!r} anatomy {recorded} (numpy SIMD '
            f'{meta.get("numpy_simd", "unknown")}), re-simulated in anatomy {current} (numpy '
            f'SIMD {",".join(numpy_simd_targets())}): another CPU or commit built a different '
            f'mesh; the recorded starts lie up to {drift.start_max_m * 1e3:.3g} mm from the '
            f'scenario starts and the re-simulated tip drifts up to {drift.max_m * 1e3:.3g} mm, '
            f'within the {tolerance_m * 1e3:g} mm tolerance'), stacklevel=2)
    _LOG.info(report.summary())
    return Replay(obs, act, report)


def population_hash(hashes: list[str]) -> str:
    """One content hash for the anatomies of a population bag's episodes (in episode order):
    the first 16 hex digits of the SHA-256 of their content hashes, one a line."""
    import hashlib

    return hashlib.sha256('\n'.join(hashes).encode()).hexdigest()[:16]


def _replay_population(path: Path, meta: dict[str, Any], episodes: list[DemoEpisode],
                       tolerance_m: float, anatomy: Any, env_options: str) -> Replay:
    """:func:`replay_demo_bag` of a population bag: each episode re-simulated in its own
    population anatomy (``DemoEpisode.anatomy``, rebuilt with
    :func:`~cgail_sim.population.sample_anatomy`; a built-in name, ``make_demos
    --include``, with :func:`~cgail_sim.anatomy_spec.resolve_anatomy`), the drift
    checked as for any bag."""
    from cgail_sim.anatomy import ANATOMY_NAMES
    from cgail_sim.anatomy_spec import is_named, resolve_anatomy
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    if anatomy is not None:
        raise DemoError(f'{path}: a population bag re-simulates each episode in its own '
                        f'anatomy: expected no anatomy to re-simulate in, found {anatomy!r}')
    groups: dict[str, list[DemoEpisode]] = {}
    for ep in episodes:
        groups.setdefault(str(ep.anatomy), []).append(ep)
    current: dict[str, str] = {}
    obs_l, act_l, drifts, moved = [], [], [], []
    for name, eps in groups.items():
        if not is_named(name):
            raise DemoError(f'{path}: expected population-<seed> or built-in episode anatomies '
                            f'{sorted(ANATOMY_NAMES)}, found {name!r}')
        built = resolve_anatomy(name)
        current[name] = built.content_hash
        recorded = eps[0].anatomy_hash
        note = ''
        if recorded is not None and recorded != built.content_hash:
            moved.append(name)
            note = f' (recorded in {name} {recorded}, re-simulated in {built.content_hash})'
        env = CatheterNavEnv(EnvConfig.from_options(env_options, mode='static', anatomy=built,
                                                    scenario_seed=meta['scenario_seed']))
        obs, act, drift = resimulate(env, eps, tolerance_m=tolerance_m,
                                     source=f'{path} [{name}]', anatomy_note=note)
        obs_l.append(obs)
        act_l.append(act)
        drifts.append((drift, len(eps), len(obs)))
    steps = sum(n for _, _, n in drifts)
    report = ReplayReport(
        source=str(path), episodes=len(episodes), steps=steps,
        max_start_offset_m=max(d.start_max_m for d, _, _ in drifts),
        mean_start_offset_m=sum(d.start_mean_m * e for d, e, _ in drifts) / len(episodes),
        max_drift_m=max(d.max_m for d, _, _ in drifts),
        mean_drift_m=sum(d.mean_m * n for d, _, n in drifts) / max(steps, 1),
        ended_early=sum(d.ended_early for d, _, _ in drifts),
        recorded_anatomy_hash=None if any(ep.anatomy_hash is None for ep in episodes)
        else population_hash([str(ep.anatomy_hash) for ep in episodes]),
        anatomy_hash=population_hash([current[str(ep.anatomy)] for ep in episodes]),
        tolerance_m=tolerance_m)
    if moved:
        warnings.warn(DemoAnatomyWarning(
            f'{path}: {len(moved)} of {len(groups)} population anatomies ({", ".join(moved[:3])}'
            f'...) differ from the recording (another CPU or commit built a different mesh); '
            f'the re-simulated tip drifts up to {report.max_drift_m * 1e3:.3g} mm, within the '
            f'{tolerance_m * 1e3:g} mm tolerance'), stacklevel=3)
    _LOG.info(report.summary())
    return Replay(np.concatenate(obs_l), np.concatenate(act_l), report)


def load_demo_bag(path: Path, only_successful: bool = True, *,
                  tolerance_m: float = POSE_TOLERANCE_M) -> tuple[np.ndarray, np.ndarray]:
    """(obs, act) arrays of a demo bag, re-simulated in the static simulator
    (:func:`replay_demo_bag` without its report)."""
    replay = replay_demo_bag(path, only_successful, tolerance_m=tolerance_m)
    return replay.obs, replay.act

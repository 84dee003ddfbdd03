"""Demonstrations recorded live in the simulator (``record_demos``), as pure logic (no rclpy).

:class:`DemoRecorder` owns one :class:`~cgail_sim.env.CatheterNavEnv` and turns the
catheter commands that ``teleop_node`` publishes (the bend setpoint, a segment bend in rad, and
the insertion velocity in m/s) into one env action per control step, with the catheter model's
own conversion (:func:`command_action`: :func:`~cgail_sim.ftl_model.segment_bend_step`
and :func:`~cgail_sim.ftl_model.command_to_action`), steps the env and keeps the
episode's rows in the demonstration bag format (:mod:`cgail_learning.demo_bags`).

**Episodes.** Episode ``k`` starts at the scenario's start ``k % n_starts`` and target
``(k // n_starts) % n_targets`` (``order='sequential'``, as ``make_demos``) or at a start and
target drawn with ``seed`` (``order='random'``). It waits at the start pose until the first
inserting step, then runs until success, a non-minor collision, leaving the anatomy, or
``time_limit_s`` of simulated time since that first step; :meth:`DemoRecorder.discard` drops
it, and the same start and target come again. After an episode a pause of ``pause_s`` shows
its outcome, then the next one starts. Only steps that insert or retract are recorded: with no
insertion the follow-the-leader catheter does not move (bends act only while inserting), so a
pause of the demonstrator adds no (obs, act) pair that tells the policy to idle.

**What a saved episode is.** Every episode that ended (success or not; not a discarded one) is
saved with its success flag; the loader trains on the successful ones. A demo bag is replayed in
the *static* simulator (:func:`~cgail_learning.demo_bags.resimulate`), so each episode is
replayed there once when it ends: ``demo/target`` holds the target's rest position (in dynamic
mode the target moves with its wall particle), and a successful episode whose static replay
fails (in dynamic mode the beating wall may have let the tip pass where the rest wall stands)
is saved as unsuccessful, with the reason in the recording's metadata, so that
``train --demos`` always accepts the bag.

**Saved after every episode.** The bag is rewritten after each saved episode (into a sibling
directory, then swapped in), so an interrupted recording keeps every episode saved so far.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
import json
import math
from pathlib import Path
import shutil
from typing import Any

import numpy as np

from cgail_learning.demo_bags import DemoEpisode, resimulate, write_demo_bag
from cgail_learning.errors import DemoError

ORDERS = ('sequential', 'random')
"""How episodes walk through the scenario's starts and targets."""
DEVICES = ('gamepad', 'keyboard', 'scripted')
"""Input devices a demonstration can come from."""
RECORDING_DATA_KEY = 'cgail_planner.record_demos'
"""Key of the recording's JSON (who, devices, per-episode outcomes) in the bag's rosbag2
``custom_data`` (``metadata.yaml``), beside :data:`~cgail_learning.demo_bags.
CUSTOM_DATA_KEY`; like it, a format name kept so that recorded bags still read."""


@dataclass(frozen=True)
class RecorderConfig:
    """How a recording runs (``record_demos`` options)."""

    episodes: int = 10
    """Episodes to save (discarded ones do not count); in [1, 10000]."""
    order: str = 'sequential'
    """``sequential`` (every start x target pair, as ``make_demos``) or ``random``."""
    seed: int = 0
    """Seed of the random order (and of the scripted driver's episodes); >= 0."""
    time_limit_s: float = 180.0
    """Simulated time an episode may last after its first insertion, s (the paper's 3
    minutes); in (0, 3600]."""
    pause_s: float = 2.0
    """Simulated time the outcome is shown before the next episode starts, s; in [0, 60]."""
    who: str = ''
    """Who recorded the episodes (free text, at most 100 characters)."""

    def __post_init__(self) -> None:
        if isinstance(self.episodes, bool) or not isinstance(self.episodes, int) \
                or not 1 <= self.episodes <= 10000:
            raise ValueError(f'episodes must be an int in [1, 10000], found {self.episodes!r}')
        if self.order not in ORDERS:
            raise ValueError(f'order must be one of {ORDERS}, found {self.order!r}')
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f'seed must be an int >= 0, found {self.seed!r}')
        for name, low, high in (('time_limit_s', 0.0, 3600.0), ('pause_s', -1e-12, 60.0)):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and low < value <= high):
                raise ValueError(f'{name} must be in ({max(low, 0.0):g}, {high:g}] s, found '
                                 f'{value!r}')
        if not isinstance(self.who, str) or len(self.who) > 100:
            raise ValueError(f'who must be text of at most 100 characters, found {self.who!r}')


def command_action(bend: tuple[float, float], velocity: float, *, theta_max: float,
                   segment_length: float, max_step_insertion: float, dt: float) -> np.ndarray:
    """The env action of teleop's commands held over one control step.

    ``bend`` is the segment bend setpoint (rad, ``catheter/bend_command``) and ``velocity`` the
    insertion velocity (m/s, ``catheter/insertion_command``): the step inserts ``velocity * dt``
    (capped at the step's maximum) and bends by :func:`~cgail_sim.ftl_model.
    segment_bend_step`; :func:`~cgail_sim.ftl_model.command_to_action` normalises it.

    Returns:
        (3,) float32 action in [-1, 1] (zeros when nothing is inserted).
    """
    from cgail_sim.ftl_model import command_to_action, segment_bend_step

    delta_l = min(max(float(velocity) * dt, -max_step_insertion), max_step_insertion)
    alpha, gamma = segment_bend_step(bend, delta_l, theta_max, segment_length)
    return command_to_action(alpha, gamma, delta_l, theta_max, segment_length,
                             max_step_insertion).astype(np.float32)


def scenario_pairs(n_starts: int, n_targets: int, order: str, seed: int
                   ) -> Iterator[tuple[int, int]]:
    """The (start, target) of episode 0, 1, 2...: ``make_demos``'s order (every start with
    target 0, then target 1, ...) or drawn uniformly with ``seed``."""
    rng = np.random.default_rng(seed)
    k = 0
    while True:
        if order == 'random':
            yield int(rng.integers(n_starts)), int(rng.integers(n_targets))
        else:
            yield k % n_starts, (k // n_starts) % n_targets
        k += 1


@dataclass(frozen=True)
class EpisodeEnd:
    """How an episode ended."""

    outcome: str
    """``success``, ``collision``, ``exited``, ``timeout`` or ``discarded``."""
    steps: int
    """Recorded steps."""
    saved: bool
    """Whether it went into the bag."""
    note: str = ''
    """Why a successful episode was saved as unsuccessful (its static replay failed)."""


class DemoRecorder:
    """One recording: the live env, the episode state machine and the episodes saved.

    Phases: ``waiting`` (at the start pose, until the first insertion), ``running``, ``pause``
    (the last outcome is shown) and ``done`` (every episode saved).

    Args:
        env: the live :class:`~cgail_sim.env.CatheterNavEnv` (static or dynamic).
        config: the recording's settings.
        out: the bag directory written after every saved episode (must not exist yet).
        anatomy: the ``--anatomy`` given (a built-in name or a path), recorded in the bag.
        driver: the device the demonstrator uses (:data:`DEVICES`), recorded in the bag.
        replay_env: a static env of the same anatomy for the replay check (default: ``env``
            when it is static; a dynamic recording needs one).
        extra: more JSON-able fields for the recording's metadata (time scale, ...).

    Raises:
        ValueError: ``out`` exists, an unknown driver, or a dynamic env without a replay env.
    """

    def __init__(self, env: Any, config: RecorderConfig, out: Path, *, anatomy: str,
                 driver: str, replay_env: Any = None, extra: dict[str, Any] | None = None
                 ) -> None:
        if driver not in DEVICES:
            raise ValueError(f'driver must be one of {DEVICES}, found {driver!r}')
        if out.exists():
            raise ValueError(f'--out {out}: expected a new bag directory, found it exists '
                             '(choose another name or remove it)')
        self.env = env
        self.config = config
        self.out = out
        self.anatomy = anatomy
        self.driver = driver
        self.mode = env.unwrapped.config.mode
        if replay_env is None and self.mode != 'static':
            raise ValueError('a dynamic recording needs a static replay_env')
        self.replay_env = replay_env if replay_env is not None else env
        self.extra = dict(extra or {})
        eng = env.unwrapped.engine
        self._eng = eng
        cat = eng.config.catheter
        self._convert = {'theta_max': cat.theta_max, 'segment_length': cat.segment_length,
                         'max_step_insertion': cat.max_step_insertion, 'dt': cat.dt}
        self.dt = cat.dt
        self._pairs = scenario_pairs(len(eng.scenarios.starts), len(eng.scenarios.targets),
                                     config.order, config.seed)
        self.episodes: list[DemoEpisode] = []
        self.records: list[dict[str, Any]] = []
        self.discarded = 0
        self.serial = 0
        """Counts episode starts (a retry after a discard is a new start)."""
        self.last: EpisodeEnd | None = None
        self.phase = 'waiting'
        self.start, self.target = next(self._pairs)
        self._pause_left = 0.0
        self._begin()

    # ------------------------------------------------------------------ state
    @property
    def saved(self) -> int:
        """Episodes saved so far."""
        return len(self.episodes)

    @property
    def successes(self) -> int:
        """Saved episodes that reached their target."""
        return sum(1 for e in self.episodes if e.success)

    @property
    def done(self) -> bool:
        """Every episode asked for is saved."""
        return self.phase == 'done'

    @property
    def elapsed_s(self) -> float:
        """Simulated time since the episode's first insertion, s (0 while waiting)."""
        if self._t_first is None:
            return 0.0
        return float(self._eng.time[0]) - self._t_first

    @property
    def tip(self) -> tuple[np.ndarray, np.ndarray]:
        """The tip's (position (3,), rotation (3, 3)) now."""
        return (self._eng.catheter.tip_position[0].copy(),
                self._eng.catheter.tip_rotation[0].copy())

    @property
    def target_position(self) -> np.ndarray:
        """The target's position now (it moves with the wall in dynamic mode)."""
        return self._eng.target[0].copy()

    def _begin(self) -> None:
        self.env.reset(options={'start': self.start, 'target': self.target})
        self.serial += 1
        self.phase = 'waiting'
        self._t_first: float | None = None
        self._rows: dict[str, list[Any]] = {'al': [], 'ga': [], 'dl': [], 'p': [], 'q': []}
        self._devices: set[str] = set()

    # ------------------------------------------------------------------ stepping
    def step(self, bend: tuple[float, float], velocity: float,
             devices: set[str] | frozenset[str] = frozenset()) -> EpisodeEnd | None:
        """One control step (``dt`` of simulated time) with teleop's latest commands.

        Args:
            bend: the bend setpoint, rad.
            velocity: the insertion velocity, m/s (0 while the deadman is released).
            devices: the devices whose input moved the catheter since the last step.

        Returns:
            How the episode ended, when it ended in this step; else None.
        """
        if self.phase == 'done':
            return None
        if self.phase == 'pause':
            self._pause_left -= self.dt
            if self._pause_left <= 1e-9:
                self.start, self.target = self._next_pair
                self._begin()
            return None
        action = command_action(bend, velocity, **self._convert)
        if self.phase == 'waiting' and action[2] == 0.0:
            return None  # (the wall starts beating with the first insertion)
        from cgail_planner.core.rotations import matrix_to_quaternion

        _, _, te, tr, info = self.env.step(action)
        if info['insertion'] != 0.0:
            if self._t_first is None:
                self._t_first = float(self._eng.time[0]) - self.dt
                self.phase = 'running'
            rows = self._rows
            rows['al'].append(float(info['bend'][0]))
            rows['ga'].append(float(info['bend'][1]))
            rows['dl'].append(float(info['insertion']))
            rows['p'].append(self._eng.catheter.tip_position[0].copy())
            rows['q'].append(matrix_to_quaternion(self._eng.catheter.tip_rotation[0]))
            self._devices.update(devices)
        if info['success']:
            return self._finish('success')
        if info['collision']:
            return self._finish('collision')
        if info['exited']:
            return self._finish('exited')
        if tr or te or self.elapsed_s >= self.config.time_limit_s - 1e-9:
            return self._finish('timeout')
        return None

    def discard(self) -> EpisodeEnd | None:
        """Drop the episode in progress (its start and target come again after the pause)."""
        if self.phase not in ('waiting', 'running'):
            return None
        self.discarded += 1
        end = EpisodeEnd('discarded', len(self._rows['dl']), False)
        self._pause(end, retry=True)
        return end

    def _pause(self, end: EpisodeEnd, retry: bool) -> None:
        self.last = end
        if self.saved >= self.config.episodes:
            self.phase = 'done'
            return
        self._next_pair = (self.start, self.target) if retry else next(self._pairs)
        self.phase = 'pause'
        self._pause_left = self.config.pause_s

    def _finish(self, outcome: str) -> EpisodeEnd:
        rows = self._rows
        steps = len(rows['dl'])
        if steps == 0:  # ended before anything was recorded: nothing to save, try again
            end = EpisodeEnd(outcome, 0, False)
            self._pause(end, retry=True)
            return end
        target = self._eng.scenarios.targets[self.target].position
        episode = DemoEpisode(self.start, self.target, np.asarray(rows['al']),
                              np.asarray(rows['ga']), np.asarray(rows['dl']),
                              np.asarray(rows['p']), np.asarray(rows['q']),
                              np.tile(np.asarray(target, dtype=np.float64), (steps, 1)),
                              outcome == 'success')
        note = self._replay_note(episode) if episode.success else ''
        if note:
            episode.success = False
        devices = sorted(self._devices) or [self.driver]
        self.episodes.append(episode)
        self.records.append({'index': len(self.records), 'start': self.start,
                             'target': self.target, 'outcome': outcome, 'steps': steps,
                             'duration_s': round(self.elapsed_s, 3),
                             'who': self.config.who, 'device': '+'.join(devices),
                             **({'static_replay': note} if note else {})})
        end = EpisodeEnd(outcome, steps, True, note)
        self.save()
        self._pause(end, retry=False)
        return end

    def _replay_note(self, episode: DemoEpisode) -> str:
        """'' when the episode replays in the static simulator as the loader will replay it,
        else why not."""
        try:
            resimulate(self.replay_env, [episode], source='the static replay')
        except DemoError as exc:
            return str(exc)
        return ''

    def status(self) -> dict[str, Any]:
        """The JSON-ready ``record`` item of the guidance page: the episode (1-based), its
        start and target, phase, time used and left, counts, and the last outcome."""
        last = self.last
        limit = self.config.time_limit_s
        return {'phase': self.phase, 'episode': min(self.saved + 1, self.config.episodes),
                'episodes': self.config.episodes, 'saved': self.saved,
                'successes': self.successes, 'discarded': self.discarded,
                'start': self.start, 'target': self.target,
                'elapsed_s': round(self.elapsed_s, 2),
                'time_left_s': round(max(limit - self.elapsed_s, 0.0), 2), 'limit_s': limit,
                'pause_left_s': round(max(self._pause_left, 0.0), 2) if self.phase == 'pause'
                else 0.0,
                'last': None if last is None else {'outcome': last.outcome, 'steps': last.steps,
                                                   'saved': last.saved, 'note': last.note[:200]},
                'who': self.config.who, 'driver': self.driver, 'mode': self.mode,
                'out': str(self.out)}

    # ------------------------------------------------------------------ saving
    def metadata(self) -> dict[str, Any]:
        """The recording's JSON (:data:`RECORDING_DATA_KEY`): who, driver, mode, settings and
        one entry per saved episode (outcome, steps, duration, who, device)."""
        return {'tool': 'record_demos', 'who': self.config.who, 'driver': self.driver,
                'mode': self.mode, 'order': self.config.order, 'seed': self.config.seed,
                'time_limit_s': self.config.time_limit_s, 'discarded': self.discarded,
                **self.extra, 'episodes': self.records}

    def save(self) -> Path:
        """Write every saved episode to :attr:`out` (a new bag, swapped in for the old one).

        Raises:
            DemoError: the bag cannot be written.
        """
        from cgail_sim.anatomy_spec import anatomy_label, is_named

        env = self.env.unwrapped
        partial = self.out.with_name(self.out.name + '.partial')
        old = self.out.with_name(self.out.name + '.old')
        for leftover in (partial, old):
            if leftover.exists():
                shutil.rmtree(leftover)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        write_demo_bag(partial, self.episodes, anatomy=anatomy_label(self.anatomy),
                       mode=self.mode, dt=self.dt, anatomy_hash=env.anatomy.content_hash,
                       anatomy_path=None if is_named(self.anatomy)
                       else str(Path(self.anatomy).expanduser().resolve()),
                       scenario_seed=env.config.scenario_seed,
                       env_options=env.config.options)
        add_custom_data(partial, RECORDING_DATA_KEY, json.dumps(self.metadata()))
        if self.out.exists():
            self.out.rename(old)
        partial.rename(self.out)
        if old.exists():
            shutil.rmtree(old)
        return self.out


def add_custom_data(bag: Path, key: str, text: str) -> None:
    """Add one ``custom_data`` entry to a closed bag's ``metadata.yaml`` (written through a
    temporary file, as :class:`~cgail_bags.bagio.JazzyWriter` rewrites it). The MCAP
    file's own metadata record is left as written.

    Raises:
        DemoError: the bag has no readable ``metadata.yaml``.
    """
    import yaml

    meta = bag / 'metadata.yaml'
    try:
        doc = yaml.safe_load(meta.read_text())
        info = doc['rosbag2_bagfile_information']
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise DemoError(f'{bag}: expected a rosbag2 metadata.yaml, found none readable '
                        f'({exc})') from None
    custom = info.get('custom_data') or {}
    custom[key] = text
    info['custom_data'] = custom
    tmp = meta.with_suffix('.yaml.tmp')
    tmp.write_text(yaml.safe_dump(doc, default_flow_style=False, sort_keys=False))
    tmp.replace(meta)


def read_recording(bag: Path) -> dict[str, Any] | None:
    """The recording's JSON of a bag made by ``record_demos`` (None for another bag)."""
    import yaml

    try:
        doc = yaml.safe_load((bag / 'metadata.yaml').read_text())
        text = (doc['rosbag2_bagfile_information'].get('custom_data') or {}).get(
            RECORDING_DATA_KEY)
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return None
    return None if text is None else json.loads(text)

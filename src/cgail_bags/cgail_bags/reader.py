"""Decode one trial's bag into the arrays of :class:`cgail_planner.core.metrics.TrialData`.

Topics read (matched with or without a leading ``/`` or a namespace prefix):

* ``em_tracker/tip_pose`` (geometry_msgs/PoseStamped): the EM tip trajectory;
* ``planner/path`` (nav_msgs/Path): the planned path(s), a new message = a replan;
* ``planner/goal`` (geometry_msgs/PoseStamped): the target.

Times are the messages' ``header.stamp`` (the measurement time, unchanged by a replay at another
rate); a zero stamp falls back to the bag's log time. Positions are in metres (phantom frame).

Condition label of a trial, first match wins: the ``condition`` argument (CLI ``--condition``),
the bag's ``metadata.yaml`` ``custom_data: {condition: ...}`` (written by ``cgail bag record
--condition``), the name of the directory the bag sits in when that directory was given as a
set of trials, else ``unlabelled``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cgail_bags.bagio import bag_custom_data, iter_raw, open_bag, TYPESTORE
from cgail_bags.errors import BagError
from cgail_planner.core.metrics import TrialData

#: custom_data key holding a trial's condition label.
CONDITION_KEY = 'condition'


@dataclass(frozen=True)
class TrialTopics:
    """Names of the topics a trial is read from (relative names, as in docs/interfaces.md)."""

    tip_pose: str = 'em_tracker/tip_pose'
    """geometry_msgs/msg/PoseStamped tip poses."""
    path: str = 'planner/path'
    """nav_msgs/msg/Path planned path."""
    goal: str = 'planner/goal'
    """geometry_msgs/msg/PoseStamped target."""

    def __post_init__(self) -> None:
        for name in ('tip_pose', 'path', 'goal'):
            value = getattr(self, name)
            if not value or not value.strip('/'):
                raise ValueError(f'{name} must be a topic name, found {value!r}')


def topic_matches(recorded: str, wanted: str) -> bool:
    """Whether a recorded (absolute) topic is ``wanted`` (relative), possibly namespaced."""
    rec = recorded.strip('/')
    want = wanted.strip('/')
    return rec == want or rec.endswith('/' + want)


def _stamp(header: object, log_ns: int) -> float:
    stamp = header.stamp  # type: ignore[attr-defined]
    if stamp.sec == 0 and stamp.nanosec == 0:
        return log_ns * 1e-9
    return stamp.sec + stamp.nanosec * 1e-9


def read_trial(
    path: Path | str,
    condition: str | None = None,
    topics: TrialTopics | None = None,
    group: str | None = None,
) -> TrialData:
    """Read one trial bag.

    Args:
        path: Bag directory or ``.mcap`` file.
        condition: Condition label overriding the bag's metadata.
        topics: Topic names; defaults to :class:`TrialTopics`.
        group: Label to use when neither ``condition`` nor the metadata gives one (the
            directory name of a set of trials).

    Raises:
        BagError: Unreadable bag or a needed topic missing.
    """
    names = topics or TrialTopics()
    bag = Path(path)
    tip_t: list[float] = []
    tip_p: list[tuple[float, float, float]] = []
    goal_t: list[float] = []
    goal_p: list[tuple[float, float, float]] = []
    path_t: list[float] = []
    paths: list[np.ndarray] = []
    with open_bag(bag) as reader:
        label = condition or bag_custom_data(reader).get(CONDITION_KEY) or group or 'unlabelled'
        roles: dict[str, str] = {}
        for conn in reader.connections:
            for role in ('tip_pose', 'path', 'goal'):
                if topic_matches(conn.topic, getattr(names, role)):
                    roles[conn.topic] = role
        missing = [getattr(names, r) for r in ('tip_pose', 'path', 'goal')
                   if r not in roles.values()]
        if missing:
            found = sorted(c.topic for c in reader.connections)
            raise BagError(f'{bag}: expected topics {missing} for a trial, found {found}')
        deserialize = TYPESTORE.deserialize_cdr
        for conn, log_ns, raw in iter_raw(reader, topics=list(roles)):
            role = roles[conn.topic]
            msg: Any = deserialize(raw, conn.msgtype)
            if role == 'path':
                path_t.append(_stamp(msg.header, log_ns))
                paths.append(np.array([(q.pose.position.x, q.pose.position.y,
                                        q.pose.position.z) for q in msg.poses],
                                      dtype=np.float64).reshape(-1, 3))
                continue
            pos = msg.pose.position
            if role == 'tip_pose':
                tip_t.append(_stamp(msg.header, log_ns))
                tip_p.append((pos.x, pos.y, pos.z))
            else:
                goal_t.append(_stamp(msg.header, log_ns))
                goal_p.append((pos.x, pos.y, pos.z))
    tip = _sorted(np.array(tip_t), np.array(tip_p).reshape(-1, 3))
    goal = _sorted(np.array(goal_t), np.array(goal_p).reshape(-1, 3))
    return TrialData(
        name=bag.name,
        condition=label,
        tip_t=tip[0],
        tip_p=tip[1],
        goal_t=goal[0],
        goal_p=goal[1],
        path_t=np.array(path_t, dtype=np.float64),
        paths=tuple(paths),
    )


def _sorted(t: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(t, kind='stable')
    return t[order].astype(np.float64), p[order].astype(np.float64)


def is_bag(path: Path) -> bool:
    """A rosbag2 directory (has metadata.yaml or an .mcap file) or a bare .mcap file."""
    if path.is_file():
        return path.suffix == '.mcap'
    return path.is_dir() and ((path / 'metadata.yaml').exists() or any(path.glob('*.mcap')))


def find_trials(paths: Sequence[Path | str]) -> list[tuple[Path, str | None]]:
    """Expand CLI arguments into ``(bag, group)``: a bag is one trial; a directory that is
    not a bag holds one bag per trial (its direct children), ``group`` = its name.

    Raises:
        BagError: A path that is neither a bag nor a directory containing bags.
    """
    trials: list[tuple[Path, str | None]] = []
    for item in map(Path, paths):
        if is_bag(item):
            trials.append((item, None))
        elif item.is_dir():
            children = sorted(c for c in item.iterdir() if is_bag(c))
            if not children:
                raise BagError(f'{item}: expected a bag or a directory of bags, found no bag')
            trials.extend((c, item.name) for c in children)
        else:
            raise BagError(f'{item}: no such bag (expected a rosbag2 directory, an .mcap file '
                           f'or a directory of bags)')
    return trials

"""Demonstration loading: (obs, act) arrays from rosbag2 MCAP demo bags or ``.npz`` files."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cgail_learning.errors import DemoError


class Demos(NamedTuple):
    """Demonstrations as training consumes them."""

    obs: np.ndarray
    """(M, obs_dim) float32 observations."""
    act: np.ndarray
    """(M, 3) float32 actions in [-1, 1]."""
    episodes: int | None
    """How many episodes the pairs come from (GAIL's absorbing state needs it); None when an
    ``.npz`` source does not say."""


def demo_source(path: Path) -> str:
    """Who made the demonstrations of ``path``: ``record_demos`` (with the device and who
    recorded them, :func:`~cgail_learning.recorder.read_recording`), teleoperated
    session bags (``make_demos --from-bags``: a ``source`` in the bag's custom data), the
    scripted expert (``make_demos``), or ``.npz`` arrays."""
    import yaml

    from cgail_learning.demo_bags import custom_info
    from cgail_learning.recorder import read_recording

    if path.suffix == '.npz':
        return 'npz arrays'
    rec = read_recording(path)
    if rec is not None:
        return f"cgail record-demos ({rec.get('driver', '?')} driver, by {rec.get('who', '?')})"
    try:
        doc = yaml.safe_load((path / 'metadata.yaml').read_text())
        custom = doc['rosbag2_bagfile_information'].get('custom_data')
        info = custom_info(path, custom)
    except (OSError, yaml.YAMLError, KeyError, TypeError, DemoError):
        return 'unknown (no readable metadata.yaml)'
    if info.get('source'):
        return 'teleoperated session bags (cgail make-demos --from-bags)'
    return 'scripted expert (cgail make-demos)'


def load_demos(paths: Sequence[Path], report: Callable[[str], None] | None = None,
               anatomy: Any = None, env_options: str = 'ours',
               sources: list[dict[str, Any]] | None = None) -> Demos:
    """Concatenate the (obs, act) pairs of every demonstration source in ``paths``.

    A source is an ``.npz`` with ``obs`` (M, D) and ``act`` (M, 3) arrays (and optionally
    ``episodes``, the number of episodes they hold), or a demo bag directory
    written by ``make_demos`` (see :mod:`cgail_learning.demo_bags`), re-simulated within
    :data:`~cgail_learning.demo_bags.POSE_TOLERANCE_M` of its recorded poses.

    Args:
        paths: the sources.
        report: called with one line per demo bag: its re-simulated tip drift (max / mean)
            and anatomy hashes (:meth:`~cgail_learning.demo_bags.ReplayReport.summary`).
        anatomy: the anatomy to re-simulate demo bags in (a name, a path or an ``Anatomy``);
            None: each bag's own (:func:`~cgail_learning.demo_bags.replay_demo_bag`).
        env_options: the env option set demo bags are re-simulated in, so that their
            observations are the trained policy's (``.npz`` sources are taken as they are and
            must have its observation size).
        sources: if given, one ``{'path', 'source', 'episodes'}`` per path is appended
            (:func:`demo_source`: scripted, teleoperated, recorded with a gamepad ...).

    Raises:
        DemoError: no path given, a path missing, or no samples.
    """
    if not paths:
        raise DemoError('expected at least one demonstration path (--demos), found none')
    obs_l, act_l = [], []
    episodes: int | None = 0
    for path in paths:
        if not path.exists():
            raise DemoError(f'demonstration path not found: {path}')
        if path.suffix == '.npz':
            with np.load(path) as data:
                if 'obs' not in data or 'act' not in data:
                    raise DemoError(f'{path}: expected arrays obs and act, found {list(data)}')
                obs, act = data['obs'], data['act']
                n_ep = int(data['episodes']) if 'episodes' in data else None
        else:
            from cgail_learning.demo_bags import replay_demo_bag

            obs, act, replay = replay_demo_bag(path, anatomy=anatomy, env_options=env_options)
            if report is not None:
                report(replay.summary())
            n_ep = replay.episodes
        episodes = None if episodes is None or n_ep is None else episodes + n_ep
        if sources is not None:
            sources.append({'path': str(path), 'source': demo_source(path), 'episodes': n_ep})
        obs_l.append(np.asarray(obs, np.float32))
        act_l.append(np.asarray(act, np.float32))
    obs_all, act_all = np.concatenate(obs_l), np.concatenate(act_l)
    if len(obs_all) == 0:
        raise DemoError(f'no demonstration samples in {[str(p) for p in paths]}')
    return Demos(obs_all, act_all, episodes)

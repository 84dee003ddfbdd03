"""The expert's actions on the learner's own states: one round of DAgger's data aggregation
(Ross, Gordon and Bagnell, AISTATS 2011).

Behavioural cloning learns the expert's action on the states the *expert* visits. A cloned
policy drifts a little off them, meets states no demonstration covers, and its errors compound;
in this task they show at the end of the path, where a target lies ~10 mm off the branch
centerline and the tip must leave the centerline to reach it. DAgger runs the learner, asks the
expert what it would do in each state the learner reached, and clones the union of the
demonstrations and these labels.

The scripted expert (:class:`~cgail_learning.expert.ScriptedExpert`) is a planner over
the simulator's state, so it can label any state: :meth:`~cgail_learning.expert.
ScriptedExpert.label` re-plans from it. Labelling costs one expert plan (~3 ms), so only every
``every``-th state of an episode is labelled; the learner still drives every step.

This is not part of the paper's method. ``plan_patient`` uses it to warm-start C-GAIL within
minutes (see :mod:`cgail_patient.plan`); the labels feed the warm start only, never
GAIL's expert buffer.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from cgail_learning.expert import ScriptedExpert

__all__ = ['expert_labels']


def expert_labels(env: Any, policy: Callable[[np.ndarray], np.ndarray], episodes: int,
                  seed: int = 0, every: int = 4, stop: Callable[[], bool] | None = None,
                  first: int = 0) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Run ``policy`` in ``env`` and label the states it visits with the expert's action.

    Args:
        env: a :class:`~cgail_sim.env.CatheterNavEnv` (the expert reads its state).
        policy: observation -> action in [-1, 1]^3; it drives every step.
        episodes: episode k uses start ``k % n_starts``, target ``(k // n_starts) % n_targets``
            and seed ``seed + k`` (as :func:`~cgail_learning.demos_cli.record_episodes`);
            in an env that draws its targets (``EnvConfig.targets == "sphere"``), a target
            drawn anew from that seed instead.
        seed: base seed.
        every: label steps 0, every, 2 * every, ... of each episode (>= 1).
        stop: checked before each episode; True ends the collection early (a time budget).
        first: the index of the first episode: episodes ``first .. first + episodes - 1`` run,
            so a collection split into consecutive chunks (worker processes) labels what one
            call over all the episodes labels.

    Returns:
        ``(obs (M, D) float32, expert actions (M, 3) float32, stats)``; stats: ``episodes`` run,
        ``labels`` (M) and ``policy_success`` (the learner's success rate in those episodes).
    """
    if not isinstance(every, int) or every < 1:
        raise ValueError(f'every must be an int >= 1, found {every!r}')
    if not isinstance(episodes, int) or episodes < 0:
        raise ValueError(f'episodes must be an int >= 0, found {episodes!r}')
    if not isinstance(first, int) or first < 0:
        raise ValueError(f'first must be an int >= 0, found {first!r}')
    expert = ScriptedExpert(env)
    sc = env.unwrapped.engine.scenarios
    n_s, n_t = len(sc.starts), len(sc.targets)
    drawn = env.unwrapped.config.targets == 'sphere'
    obs_l: list[np.ndarray] = []
    act_l: list[np.ndarray] = []
    wins: list[bool] = []
    for k in range(first, first + episodes):
        if stop is not None and stop():
            break
        options = {'start': k % n_s} if drawn else {'start': k % n_s,
                                                    'target': (k // n_s) % n_t}
        obs, _ = env.reset(seed=seed + k, options=options)
        expert.reset(None)  # (no score jitter: one label per state)
        i = 0
        while True:
            if i % every == 0:
                obs_l.append(np.asarray(obs, np.float32))
                act_l.append(np.asarray(expert.label(), np.float32))
            obs, _, te, tr, info = env.step(np.asarray(policy(obs), np.float32))
            i += 1
            if te or tr:
                break
        wins.append(bool(info['success']))
    dim = env.observation_space.shape[0]
    obs_a = np.stack(obs_l) if obs_l else np.zeros((0, dim), np.float32)
    act_a = np.stack(act_l) if act_l else np.zeros((0, 3), np.float32)
    return obs_a, act_a, {'episodes': float(len(wins)), 'labels': float(len(obs_a)),
                          'policy_success': float(np.mean(wins)) if wins else float('nan')}

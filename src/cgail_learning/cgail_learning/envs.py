"""The batched-environment protocol the trainer uses, and a synchronous adapter for gym envs.

The trainer needs ``step`` with *same-step* auto-reset: when env i ends at step t, ``obs[i]`` is
already the first observation of its next episode and ``infos[i]['final_obs']`` holds the last
observation of the ended one (used to bootstrap truncated episodes).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol, SupportsFloat

import gymnasium as gym
import numpy as np

StepResult = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]


class VecEnv(Protocol):
    """What the trainer needs from a batched environment."""

    num_envs: int
    single_observation_space: gym.spaces.Box
    single_action_space: gym.spaces.Box

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset every env; env i is seeded ``seed + i``. Returns (N, obs_dim) float32."""
        ...

    def step(self, actions: np.ndarray) -> StepResult:
        """Step all envs with (N, act_dim) actions in [-1, 1]; same-step auto-reset."""
        ...

    def set_theta_max(self, theta_max: float) -> None:
        """Set the maximum bending angle (rad) of every env (curriculum)."""
        ...


def is_success(info: dict[str, Any]) -> bool:
    """Success flag of a final-step info dict (``is_success``, gymnasium's convention)."""
    return bool(info.get('is_success', info.get('success', False)))


class SyncVecEnv:
    """Runs N gymnasium envs one after the other in this process, with same-step auto-reset.

    Ours, not ``gymnasium.vector.SyncVectorEnv``: gymnasium 1.4.0's, with
    ``autoreset_mode=AutoresetMode.SAME_STEP``, steps and resets the envs the same way (checked
    on 4 :class:`~cgail_learning.testing.PointReach` envs, 400 steps of seeded random actions
    and 42 ended episodes: equal observations, float32 rewards, terminations, truncations and
    ``final_obs``), but its infos are not the :class:`VecEnv` protocol's. It returns one dict
    of arrays (with ``_key`` masks) instead of a list of per-env dicts, and for an env that
    ended it puts the ended step's info under ``final_info`` and the *reset's* info at the top
    level: its ``is_success`` there was False in the 3 episodes where this class (and the
    trainer, which reads ``infos[i]``) says True. An adapter back to this protocol would be
    longer than this class. ``AsyncVectorEnv`` (subprocesses) does not help either: the
    catheter simulator batches its envs in one process itself
    (:class:`~cgail_sim.vec_env.CatheterNavVecEnv`, the trainer's env); this class serves the
    tests' and benches' small gym envs.
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]]) -> None:
        if not env_fns:
            raise ValueError('env_fns must hold at least one env factory, found none')
        self.envs = [fn() for fn in env_fns]
        self.num_envs = len(self.envs)
        obs_space = self.envs[0].observation_space
        act_space = self.envs[0].action_space
        if not isinstance(obs_space, gym.spaces.Box) or not isinstance(act_space, gym.spaces.Box):
            raise ValueError(f'expected Box observation and action spaces, found {obs_space} '
                             f'and {act_space}')
        self.single_observation_space = obs_space
        self.single_action_space = act_space

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset all envs (env i gets ``seed + i`` when a seed is given)."""
        obs = [env.reset(seed=None if seed is None else seed + i)[0]
               for i, env in enumerate(self.envs)]
        return np.stack(obs).astype(np.float32)

    def step(self, actions: np.ndarray) -> StepResult:
        """Step every env; an ended env is reset at once and reports ``final_obs``."""
        n = self.num_envs
        obs_out = np.zeros((n, *self.single_observation_space.shape), np.float32)
        rew = np.zeros(n, np.float32)
        term = np.zeros(n, bool)
        trunc = np.zeros(n, bool)
        infos: list[dict[str, Any]] = []
        for i, env in enumerate(self.envs):
            o, r, te, tr, info = env.step(actions[i])
            info = dict(info)
            if te or tr:
                info['final_obs'] = np.asarray(o, np.float32)
                o, _ = env.reset()
            obs_out[i], rew[i], term[i], trunc[i] = o, r, te, tr
            infos.append(info)
        return obs_out, rew, term, trunc, infos

    def set_theta_max(self, theta_max: float) -> None:
        """Forward to every env that supports it (the catheter simulator does)."""
        for env in self.envs:
            fn = getattr(env.unwrapped, 'set_theta_max', None)
            if fn is not None:
                fn(theta_max)

    def close(self) -> None:
        """Close every env."""
        for env in self.envs:
            env.close()


class ConcatVecEnv:
    """Several batched envs stepped as one: env ``i`` of the whole is env ``i - offset`` of its
    part, in order. Used to train over several target sets of one anatomy at once (one
    :class:`~cgail_sim.vec_env.CatheterNavVecEnv` per scenario seed).

    ``reset(seed)`` seeds the whole's env ``i`` with ``seed + i``, as one batched env would.
    """

    def __init__(self, parts: Sequence[Any]) -> None:
        if not parts:
            raise ValueError('parts must hold at least one batched env, found none')
        self.parts = list(parts)
        first = self.parts[0]
        for p in self.parts[1:]:
            if (p.single_observation_space.shape != first.single_observation_space.shape
                    or p.single_action_space.shape != first.single_action_space.shape):
                raise ValueError('expected parts with equal observation and action spaces, '
                                 f'found {first.single_observation_space} and '
                                 f'{p.single_observation_space}')
        self.single_observation_space = first.single_observation_space
        self.single_action_space = first.single_action_space
        self._bounds = np.cumsum([0] + [p.num_envs for p in self.parts])
        self.num_envs = int(self._bounds[-1])

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset every part (the whole's env i gets ``seed + i``)."""
        return np.concatenate([
            p.reset(seed=None if seed is None else seed + int(lo))
            for p, lo in zip(self.parts, self._bounds[:-1], strict=False)]).astype(np.float32)

    def step(self, actions: np.ndarray) -> StepResult:
        """Step every part with its slice of ``actions``."""
        outs = [p.step(actions[lo:hi]) for p, lo, hi in
                zip(self.parts, self._bounds[:-1], self._bounds[1:], strict=True)]
        infos: list[dict[str, Any]] = [i for o in outs for i in o[4]]
        return (np.concatenate([o[0] for o in outs]).astype(np.float32),
                np.concatenate([o[1] for o in outs]).astype(np.float32),
                np.concatenate([o[2] for o in outs]), np.concatenate([o[3] for o in outs]),
                infos)

    def set_theta_max(self, theta_max: float) -> None:
        """Set theta_max of every part."""
        for p in self.parts:
            p.set_theta_max(theta_max)

    def close(self) -> None:
        """Close every part."""
        for p in self.parts:
            getattr(p, 'close', lambda: None)()


class PopulationVecEnv(ConcatVecEnv):
    """Batched training across a pool of anatomies: ``num_envs`` workers, each a one-env
    batched env in one anatomy of the pool at a time, drawing another one (uniformly or by
    ``weights``, with its own generator) after every ``redraw_every`` episodes.

    Building an anatomy costs seconds (:func:`cgail_sim.population.sample_anatomy`), so
    the pool is built once by the caller; a worker's env in a drawn anatomy is cheap (~10 ms
    static, ~35 ms dynamic: its rigid wall or deformable wall and catheter buffers), so it is
    built afresh at each redraw. Same-step auto-reset holds across a redraw: when worker i's
    episode ends and it moves to another anatomy, ``obs[i]`` is the first observation of its
    next episode there.

    Seeding: ``reset(seed)`` gives worker i the generator ``SeedSequence([seed, i])`` for its
    anatomy draws and seeds its env ``seed + i``; a redraw seeds the new env with an integer
    from the worker's generator. The run is a function of ``seed`` and the pool.

    Args:
        make_part: ``anatomy -> batched env`` with one env (a
            :class:`~cgail_sim.vec_env.CatheterNavVecEnv` of that anatomy).
        anatomies: the pool (anatomy specs or :class:`~cgail_sim.anatomy.Anatomy`).
        num_envs: workers (>= 1).
        redraw_every: episodes a worker runs in one anatomy before it draws again (>= 1).
        weights: relative draw weights, one per anatomy (> 0); None draws uniformly.
    """

    def __init__(self, make_part: Callable[[Any], Any], anatomies: Sequence[Any],
                 num_envs: int, redraw_every: int = 4,
                 weights: Sequence[float] | None = None) -> None:
        if not anatomies:
            raise ValueError('anatomies must hold at least one anatomy, found none')
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f'num_envs must be an int >= 1, found {num_envs!r}')
        if isinstance(redraw_every, bool) or not isinstance(redraw_every, int) \
                or redraw_every < 1:
            raise ValueError(f'redraw_every must be an int >= 1, found {redraw_every!r}')
        self._p: np.ndarray | None = None
        if weights is not None:
            w = np.asarray(weights, dtype=float)
            if w.shape != (len(anatomies),) or not np.all(np.isfinite(w)) or np.any(w <= 0):
                raise ValueError(f'weights must be {len(anatomies)} finite numbers > 0 (one '
                                 f'per anatomy), found {list(weights)!r}')
            self._p = w / w.sum()
        self.make_part = make_part
        self._theta_max: float | None = None
        self.anatomies = list(anatomies)
        self.redraw_every = redraw_every
        self.current = [i % len(self.anatomies) for i in range(num_envs)]
        """Index into ``anatomies`` of each worker's anatomy."""
        super().__init__([self._part(j) for j in self.current])
        if self._bounds[-1] != num_envs:
            raise ValueError(f'make_part must build a one-env batched env, found '
                             f'{self._bounds[-1]} envs for {num_envs} workers')
        self._rngs = [np.random.default_rng([0, i]) for i in range(num_envs)]
        self._episodes = [0] * num_envs

    def _part(self, j: int) -> Any:
        part = self.make_part(self.anatomies[j])
        if self._theta_max is not None:
            part.set_theta_max(self._theta_max)
        return part

    def _redraw(self, i: int, env_seed: int | None = None) -> np.ndarray:
        """Move worker i to an anatomy drawn from the pool and reset it there (seeded
        ``env_seed``, else from the worker's generator); its first observation."""
        rng = self._rngs[i]
        j = int(rng.integers(len(self.anatomies)) if self._p is None
                else rng.choice(len(self.anatomies), p=self._p))
        drawn = int(rng.integers(2**31))
        if j != self.current[i]:
            self.parts[i].close()
            self.parts[i] = self._part(j)
            self.current[i] = j
        return self.parts[i].reset(seed=drawn if env_seed is None else env_seed)

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Draw every worker's anatomy and reset it (the class docstring: seeding)."""
        if seed is not None:
            self._rngs = [np.random.default_rng([seed, i]) for i in range(self.num_envs)]
        self._episodes = [0] * self.num_envs
        return np.concatenate([
            self._redraw(i, None if seed is None else seed + i)
            for i in range(self.num_envs)]).astype(np.float32)

    def step(self, actions: np.ndarray) -> StepResult:
        """Step every worker; one whose episode ended and whose count reached
        ``redraw_every`` moves to a newly drawn anatomy."""
        obs, rew, term, trunc, infos = super().step(actions)
        for i in np.flatnonzero(term | trunc).tolist():
            infos[i]['anatomy'] = self.current[i]
            self._episodes[i] += 1
            if self._episodes[i] % self.redraw_every == 0:
                obs[i] = self._redraw(i)[0]
        return obs, rew, term, trunc, infos

    def set_theta_max(self, theta_max: float) -> None:
        """Set theta_max of every worker, and of the envs later redraws build."""
        self._theta_max = float(theta_max)
        super().set_theta_max(theta_max)


class AnatomyCycleEnv:
    """A single env over several anatomies for the periodic evaluation: ``reset(seed=s)``
    runs the episode in anatomy ``s % len(envs)`` (so consecutive evaluation seeds visit every
    anatomy in turn).

    Args:
        envs: one catheter env per anatomy (:class:`~cgail_sim.env.CatheterNavEnv`;
            equal observation and action spaces).
    """

    def __init__(self, envs: Sequence[Any]) -> None:
        if not envs:
            raise ValueError('envs must hold at least one env, found none')
        self.envs = list(envs)
        self.observation_space = self.envs[0].observation_space
        self.action_space = self.envs[0].action_space
        for e in self.envs[1:]:
            if e.observation_space.shape != self.observation_space.shape:
                raise ValueError(f'expected envs with equal observation spaces, found '
                                 f'{self.observation_space} and {e.observation_space}')
        self._env = self.envs[0]

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset the env of anatomy ``seed % len(envs)`` (the first without a seed)."""
        self._env = self.envs[0 if seed is None else seed % len(self.envs)]
        return self._env.reset(seed=seed, options=options)

    def step(self, action: np.ndarray) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        """Step the current anatomy's env."""
        return self._env.step(action)

    def set_theta_max(self, theta_max: float) -> None:
        """Set theta_max of every env (the catheter simulator's, :class:`~cgail_sim.
        env.CatheterNavEnv`)."""
        for e in self.envs:
            e.unwrapped.set_theta_max(theta_max)

    def close(self) -> None:
        """Close every env."""
        for e in self.envs:
            e.close()

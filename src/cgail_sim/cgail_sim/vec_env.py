"""Batched catheter navigation for training throughput.

:class:`CatheterNavVecEnv` steps ``num_envs`` episodes together on one
:class:`~cgail_sim.env.NavEngine`: catheter kinematics, observations and reward are numpy
vectorised over the batch and, in static mode, all raycasts of a step are one call on the shared
rigid wall. Dynamic mode keeps one deformable wall per environment (stepped one after the other).

Semantics equal :class:`~cgail_sim.env.CatheterNavEnv` (a test compares them step by
step) with *same-step* auto-reset, the protocol of ``cgail_learning.envs.VecEnv``: when
environment ``i`` ends at a step, ``obs[i]`` is already the first observation of its next
episode and ``infos[i]['final_obs']`` holds the last observation of the ended one.

Seeding: ``reset(seed)`` gives environment ``i`` its own generator seeded ``seed + i`` (as
``SyncVecEnv`` does with ``env.reset(seed=seed + i)``), which draws the start and target ids of
each of its episodes exactly as a single env reset with ``seed + i`` would (with
``EnvConfig.targets == "sphere"``: the start id and a newly drawn target).
"""

from __future__ import annotations

from typing import Any

from gymnasium import spaces
import numpy as np
from numpy.typing import NDArray

from cgail_sim.config import EnvConfig
from cgail_sim.env import _observation_space, NavEngine, validate_actions
from cgail_sim.pbd import PBDConfig


class CatheterNavVecEnv:
    """``num_envs`` catheter navigation environments stepped as one batch.

    Args:
        config: environment configuration shared by every environment.
        num_envs: batch size N >= 1.
        pbd_config: wall solver of the dynamic mode (default
            :data:`~cgail_sim.env.DYNAMIC_PBD_CONFIG`), see
            :class:`~cgail_sim.env.NavEngine`.
    """

    def __init__(self, config: EnvConfig | None = None, num_envs: int = 8,
                 pbd_config: PBDConfig | None = None) -> None:
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, found {num_envs!r}")
        if config is not None and not isinstance(config, EnvConfig):
            raise ValueError(f"config must be an EnvConfig, found {type(config).__name__}")
        self.config = config or EnvConfig()
        self.num_envs = num_envs
        self.engine = NavEngine(self.config, num_envs, pbd_config)
        self.single_observation_space = _observation_space(self.engine.spec)
        self.single_action_space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
        self._rngs = [np.random.default_rng() for _ in range(num_envs)]
        self._started = False

    def set_theta_max(self, theta_max: float) -> None:
        """Set the maximal bending angle theta_max (rad) of every environment (curriculum)."""
        self.engine.catheter.set_theta_max(theta_max)

    def _draw_reset(self, i: int) -> None:
        sc = self.engine.scenarios
        rng = self._rngs[i]
        start = int(rng.integers(len(sc.starts)))
        if self.config.targets == "sphere":
            self.engine.reset_env(i, start, -1, target=self.engine.draw_target(rng))
        else:
            self.engine.reset_env(i, start, int(rng.integers(len(sc.targets))))

    def reset(self, seed: int | None = None) -> NDArray[np.float32]:
        """Reset every environment (env ``i`` seeded ``seed + i``); returns (N, obs_dim)."""
        if seed is not None:
            self._rngs = [np.random.default_rng(seed + i) for i in range(self.num_envs)]
        for i in range(self.num_envs):
            self._draw_reset(i)
        self._started = True
        return self.engine.observe()

    def step(self, actions: Any) -> tuple[NDArray[np.float32], NDArray[np.float32],
                                          NDArray[np.bool_], NDArray[np.bool_],
                                          list[dict[str, Any]]]:
        """Step all environments with (N, 3) normalised actions; same-step auto-reset.

        Returns:
            ``(obs, rewards, terminations, truncations, infos)`` with ``infos[i]`` holding the
            keys of :class:`CatheterNavEnv`'s info plus ``final_obs`` when env ``i`` ended.
        """
        if not self._started:
            raise RuntimeError("call reset() before step()")
        a = validate_actions(actions, self.num_envs)
        engine = self.engine
        reward, terminated, truncated, arrays = engine.step(a)
        obs = engine.observe()
        done = terminated | truncated
        keys = list(arrays)
        cols = [arrays[k].tolist() for k in keys]
        infos: list[dict[str, Any]] = [dict(zip(keys, row, strict=True)) for row in zip(*cols,
                                                                                         strict=True)]
        for i, info in enumerate(infos):
            info["is_success"] = info["success"]
            info["start"] = int(engine.start_id[i])
            info["target"] = int(engine.target_id[i])
        if done.any():
            for i in np.flatnonzero(done).tolist():
                infos[i]["final_obs"] = obs[i].copy()
                self._draw_reset(i)
            obs = engine.observe()
        return obs, reward.astype(np.float32), terminated, truncated, infos

    def close(self) -> None:
        """Nothing to release (kept for the VecEnv protocol)."""

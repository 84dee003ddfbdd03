"""In-silico world of the planner: beating-aorta simulator and the catheter navigation env.

Pure python + numpy/scipy/numba/trimesh (no rclpy, no torch). Public entry points:

* ``gymnasium.make("CatheterNav-v0")`` (static, rigid wall) and
  ``gymnasium.make("CatheterNavDynamic-v0")`` (deformable beating wall, moving target), or
  ``CatheterNavEnv(EnvConfig(...))`` directly;
* :class:`CatheterNavVecEnv` for batched training;
* :data:`OBS_LAYOUT` / :func:`obs_layout_dict` describing the observation vector.

The exports are imported lazily, so ``import cgail_planner.sim.anatomy`` stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

import gymnasium

__all__ = [
    "OBS_DIM",
    "OBS_LAYOUT",
    "RAY_DIRECTIONS",
    "CatheterConfig",
    "CatheterNavEnv",
    "CatheterNavVecEnv",
    "EnvConfig",
    "RewardConfig",
    "obs_layout_dict",
]

_EXPORTS = {
    "OBS_DIM": "cgail_planner.sim.env",
    "OBS_LAYOUT": "cgail_planner.sim.env",
    "RAY_DIRECTIONS": "cgail_planner.sim.env",
    "CatheterNavEnv": "cgail_planner.sim.env",
    "obs_layout_dict": "cgail_planner.sim.env",
    "CatheterNavVecEnv": "cgail_planner.sim.vec_env",
    "EnvConfig": "cgail_planner.sim.config",
    "CatheterConfig": "cgail_planner.sim.ftl_model",
    "RewardConfig": "cgail_planner.sim.reward",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _dynamic_env(**kwargs: Any) -> Any:
    """Entry point of ``CatheterNavDynamic-v0``: ``CatheterNavEnv`` with ``mode='dynamic'``."""
    import dataclasses

    from cgail_planner.sim.config import EnvConfig
    from cgail_planner.sim.env import CatheterNavEnv

    config = kwargs.pop("config", None) or EnvConfig()
    return CatheterNavEnv(dataclasses.replace(config, mode="dynamic"), **kwargs)


def _register() -> None:
    if "CatheterNav-v0" not in gymnasium.registry:
        gymnasium.register(id="CatheterNav-v0", entry_point="cgail_planner.sim.env:CatheterNavEnv",
                           max_episode_steps=None)
    if "CatheterNavDynamic-v0" not in gymnasium.registry:
        gymnasium.register(id="CatheterNavDynamic-v0",
                           entry_point="cgail_planner.sim:_dynamic_env", max_episode_steps=None)


_register()

"""In-silico world of the planner: beating-aorta simulator and the catheter navigation env.

Pure python + numpy/scipy/numba/trimesh (no rclpy, no torch). Public entry points:

* ``gymnasium.make("CatheterNav-v0")`` (static, rigid wall) and
  ``gymnasium.make("CatheterNavDynamic-v0")`` (deformable beating wall, moving target), or
  ``CatheterNavEnv(EnvConfig(...))`` directly;
* :class:`CatheterNavVecEnv` for batched training;
* :data:`OBS_LAYOUT` / :func:`obs_layout_dict` describing the observation vector.

The exports are imported lazily, so ``import cgail_sim.anatomy`` stays light.
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
    "OBS_DIM": "cgail_sim.env",
    "OBS_LAYOUT": "cgail_sim.env",
    "RAY_DIRECTIONS": "cgail_sim.env",
    "CatheterNavEnv": "cgail_sim.env",
    "obs_layout_dict": "cgail_sim.env",
    "CatheterNavVecEnv": "cgail_sim.vec_env",
    "EnvConfig": "cgail_sim.config",
    "CatheterConfig": "cgail_sim.ftl_model",
    "RewardConfig": "cgail_sim.reward",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _register() -> None:
    if "CatheterNav-v0" not in gymnasium.registry:
        gymnasium.register(id="CatheterNav-v0", entry_point="cgail_sim.env:CatheterNavEnv",
                           max_episode_steps=None)
    if "CatheterNavDynamic-v0" not in gymnasium.registry:
        gymnasium.register(id="CatheterNavDynamic-v0",
                           entry_point="cgail_sim.env:make_dynamic_env", max_episode_steps=None)


_register()

"""The simulator's worlds: an anatomy with its centerlines and scenario set, built once.

:func:`load_world` takes an anatomy as a built-in name, a population sample, a prepared
directory, a mesh file or an :class:`~cgail_sim.anatomy.Anatomy`
(:func:`~cgail_sim.anatomy_spec.resolve_anatomy`) and caches the
:class:`~cgail_sim.scenarios.World` per ``(anatomy content hash, name, n_waypoints, seed)`` so
many environments share one copy. (Apart from :mod:`cgail_sim.scenarios`, which builds the
scenario set from an anatomy alone: resolving a name may build and screen a population sample,
and the screening builds scenario sets.)
"""

from __future__ import annotations

import math

from cgail_sim.anatomy_spec import AnatomySpec, resolve_anatomy
from cgail_sim.centerline import compute_centerlines
from cgail_sim.scenarios import build_scenarios, ScenarioError, World

__all__ = ["load_world"]

_WORLDS: dict[tuple[str, str, int, int], World] = {}
_WORLDS_MAX = 64  # (a world is small; plan_patient uses ~25 target sets of one anatomy)


def load_world(anatomy: AnatomySpec, n_waypoints: int = 100, seed: int = 0) -> World:
    """Build (once per process) the anatomy, its centerlines and scenarios.

    Args:
        anatomy: a built-in name, a prepared anatomy directory, a mesh file with its
            ``<stem>.yaml`` landmarks, or an :class:`~cgail_sim.anatomy.Anatomy`
            (:func:`~cgail_sim.anatomy_spec.resolve_anatomy`).
        n_waypoints: waypoints per centerline.
        seed: seed of the target sampling.

    Returns:
        The world, shared by every caller with the same anatomy content, name and arguments
        (the centerlines come from the disk cache keyed by the content hash).

    Raises:
        AnatomyError: an anatomy that cannot be resolved or loaded (the message names it).
        ScenarioError: an anatomy that does not admit the scenario set (e.g. no introducer
            inside the lumen behind a start).
    """
    resolved = resolve_anatomy(anatomy)
    key = (resolved.content_hash, resolved.name, int(n_waypoints), int(seed))
    world = _WORLDS.get(key)
    if world is None:
        centerlines = compute_centerlines(resolved, n_waypoints=n_waypoints)
        scenarios = build_scenarios(resolved, centerlines, seed=seed)
        if not math.isfinite(scenarios.d_max) or scenarios.d_max <= 0.0:
            raise ScenarioError(f"expected a positive d_max, found {scenarios.d_max}")
        world = World(anatomy=resolved, centerlines=centerlines, scenarios=scenarios)
        if len(_WORLDS) >= _WORLDS_MAX:
            _WORLDS.pop(next(iter(_WORLDS)))
        _WORLDS[key] = world
    return world

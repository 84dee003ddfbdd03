"""Full-length catheter-wall contact trials: the deformable wall under a catheter riding it.

A contact trial drives the catheter of a dynamic :class:`~cgail_sim.env.NavEngine`
along the target branch's centerline with its tip aimed ``depth`` beyond the wall, to one side
(a lateral direction per trial), so that the body presses the beating wall for the whole
trial. The engine is stepped directly for ``steps`` steps: collisions do not end the trial (the
point is the wall, not the task); the trial stops early only when the tip leaves the lumen
through the exit or the wall faults (the engine's ``simulation_fault``). Once the tip
reaches the end of the centerline it stops inserting and keeps pressing while the heart beats.

What it measures: the largest particle displacement from rest over the trial, and how deep the
catheter body lay beyond the REST wall at that moment (the indentation that displacement has to
explain: the heartbeat moves the root by ~11 mm, a dent adds about its depth). A sound wall
stays within a few mm of ``heartbeat + indentation``.

``bench/bench_wall.py --contact`` runs it on any anatomy; the default test suite runs it on
the built-in aortas and the committed patient mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cgail_sim.anatomy_spec import AnatomySpec
from cgail_sim.config import EnvConfig
from cgail_sim.env import NavEngine
from cgail_sim.ftl_model import steer_towards
from cgail_sim.pbd import PBDConfig
from cgail_sim.wall import DeformableWall, StaticWall

__all__ = ["LATERAL_DIRECTIONS", "ContactTrial", "run_contact_trials"]

#: The side each trial presses towards (trial k uses entry ``k % 6``), world axes.
LATERAL_DIRECTIONS = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                               [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class ContactTrial:
    """Outcome of one contact trial (lengths in mm)."""

    start: int
    target: int
    direction: int
    """Index into :data:`LATERAL_DIRECTIONS`."""
    steps: int
    """Steps run (``steps`` unless the tip exited or the wall faulted)."""
    contact_steps: int
    """Steps with the tip in contact with the wall."""
    max_displacement_mm: float
    """Largest particle distance from rest over the trial."""
    indentation_mm: float
    """How far the catheter body's surface lay beyond the rest wall when that displacement
    was reached (negative: clear of it)."""
    end: str
    """``full`` (ran every step), ``exited`` or ``simulation fault``."""
    fault: str = ""
    """The wall's message when it faulted."""


def _aim(engine: NavEngine, lateral: np.ndarray, depth: float, progress: int
         ) -> tuple[np.ndarray, int]:
    """(action (3,), progress): the tip aimed ``depth`` beyond the wall, to the ``lateral``
    side of the centerline point a few waypoints ahead; no insertion at the centerline's end."""
    line = engine.world.centerlines[engine.branch[0]]
    pts, radii = np.asarray(line.points), np.asarray(line.radii)
    tip = engine.catheter.tip_position[0]
    progress = max(progress, int(np.argmin(np.linalg.norm(pts - tip, axis=1))))
    c = min(progress + 5, len(pts) - 1)
    t = pts[min(c + 1, len(pts) - 1)] - pts[max(c - 1, 0)]
    t = t / max(float(np.linalg.norm(t)), 1e-12)
    side = lateral - (lateral @ t) * t
    if np.linalg.norm(side) < 1e-6:
        side = np.cross(t, [1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.cross(t, [0.0, 1.0, 0.0])
    side = side / np.linalg.norm(side)
    goal = pts[c] + (radii[c] + depth) * side
    hold = progress >= len(pts) - 8
    cat = engine.catheter
    a = steer_towards(tip[None], cat.tip_rotation[0][None], goal[None], cat.config,
                      cat.theta_max)[0]
    if hold:
        a[2] = 0.0
    return a, progress


def run_contact_trials(anatomy: AnatomySpec, trials: int = 6, steps: int = 2000,
                       depth: float = 0.001, pbd_config: PBDConfig | None = None,
                       first: int = 0) -> list[ContactTrial]:
    """``trials`` contact trials of ``steps`` steps in a dynamic env of ``anatomy``: trials
    ``first`` .. ``first + trials - 1``.

    Trial k starts at start ``k % n_starts``, heads for target ``k % n_targets`` and presses
    towards :data:`LATERAL_DIRECTIONS` ``[k % 6]``, its tip aimed ``depth`` (m) beyond the
    wall. ``pbd_config``: the wall solver (default: the dynamic env's).
    """
    if not isinstance(trials, int) or trials < 1:
        raise ValueError(f"trials must be an int >= 1, found {trials!r}")
    if not isinstance(first, int) or first < 0:
        raise ValueError(f"first must be an int >= 0, found {first!r}")
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an int >= 1, found {steps!r}")
    if not (isinstance(depth, (int, float)) and 0.0 <= depth <= 0.01):
        raise ValueError(f"depth must be in [0, 0.01] m, found {depth!r}")
    engine = NavEngine(EnvConfig(anatomy=anatomy, mode="dynamic", max_steps=steps), 1,
                       pbd_config)
    rest = StaticWall(engine.world.anatomy).bvh  # the rest wall
    sc = engine.scenarios
    out: list[ContactTrial] = []
    for k in range(first, first + trials):
        start, target = k % len(sc.starts), k % len(sc.targets)
        engine.reset_env(0, start, target)
        wall = engine.walls[0]
        assert isinstance(wall, DeformableWall)
        progress, contact, worst, end, fault = 0, 0, 0.0, "full", ""
        worst_body = engine.catheter.body_points(0, engine.config.body_spacing)
        for _ in range(steps):
            a, progress = _aim(engine, LATERAL_DIRECTIONS[k % 6], depth, progress)
            _, _, _, info = engine.step(a[None])
            if bool(info["simulation_fault"][0]):  # (the engine resets the wall then)
                end = "simulation fault"
                fault = str(info["simulation_fault_message"][0])
                break
            contact += bool(info["in_contact"][0])
            if wall.max_displacement > worst:
                worst = wall.max_displacement
                worst_body = engine.catheter.body_points(0, engine.config.body_spacing)
            if bool(info["exited"][0]):
                end = "exited"
                break
        indentation = max(float(rest.closest_point(q)[0]) for q in worst_body) + engine.radius
        out.append(ContactTrial(start=start, target=target, direction=k % 6,
                                steps=int(engine.steps[0]),
                                contact_steps=contact, max_displacement_mm=worst * 1e3,
                                indentation_mm=indentation * 1e3, end=end, fault=fault))
    return out

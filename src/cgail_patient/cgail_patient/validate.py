"""Is a prepared anatomy usable? Checks with one clear line each, and the figures behind them.

:func:`validate_anatomy` runs every check on an :class:`~cgail_sim.anatomy.Anatomy`
(normally the one read back from the prepared directory with ``load_anatomy_mesh``):

============================  =======================================================  =========
check                         compared with                                            fails as
============================  =======================================================  =========
mesh                          watertight, consistently oriented, Euler characteristic  error
                              2 (one closed genus-0 surface)
vertex count                  <= 4,000 (the deformable wall's >= 500 steps/s budget)   warning
face quality                  smallest angle; share of wall faces under 15 deg          warning
landmarks                     ostia 5-30 mm above the annulus, left of right, 8-60 mm  error
                              apart; exit >= 100 mm from the annulus
centrelines                   the simulator's Voronoi centrelines reach both ostia     error
lumen radius                  narrowest inscribed radius along the centrelines vs the  error /
                              catheter radius (3.5 mm; warning under radius + 1.5 mm)  warning
tightest bend                 centreline bend radius vs the catheter's smallest bend   warning
                              radius L / theta_max (31.8 mm)
starts and introducers        every start and its introducer (straight, or along the   error
                              centreline where a straight one would touch the wall)
                              keep the catheter radius from the wall
targets                       the scenario set finds its 5 targets near the ostia      error
deformable wall               two heartbeats with the catheter in the introducer: no   error
                              particle further than ``wall_bound_mm`` from rest, all
                              finite (a wall that would blow up is refused, never
                              reported later as a "collision")
expert static,                the scripted expert reaches every standard target        error /
expert dynamic                (target set 0) in whole episodes of the real env:        warning
                              rigid wall; beating wall pushed by the catheter body
                              with the target moving with it
============================  =======================================================  =========

**The expert check** (``expert=True``; ``prepare_anatomy`` runs it unless
``--no-expert-check``) is the proof that the anatomy is usable: the checks above are geometry,
this one drives the catheter. Target ``k`` of set 0 (:data:`EXPERT_TARGET_SET`, the rig's and
the demonstrations' targets) is driven to from start ``k % 3`` by the scripted expert
(:class:`~cgail_learning.expert.ScriptedExpert`, no score jitter: a deterministic
function of the anatomy), once in the static env and once in the dynamic one (heartbeat,
deformable wall pushed by the catheter body, the target riding on its wall particle), each a
full episode of :class:`~cgail_sim.env.CatheterNavEnv` ending in success, collision,
exit, simulation fault or the 2,000-step timeout. So every target and every start is driven in
both modes. A target missed from its start is tried from the other starts: reached from one of
them it is a warning (the failed start is named), reached from none it is an error, and so is
a simulation fault from any start (a wall that cannot take the catheter). The error names the
target, its position from the annulus centre, the mode, each start tried and its outcome
("collision 31 mm from the target at step 212 ..., 180 mm along the centreline, where it
bends with a 14 mm radius in a lumen of 10 mm radius", "exited through the descending cut at
step 40", "simulation fault at step 443 ..."); where every miss is a collision in a bend
tighter than the catheter's smallest bend radius (L / theta_max), it says so: the lumen is too
narrow there for the catheter to cut the corner. Every episode is in ``Validation.expert_trials``
(outcome, steps, final and closest distance, largest wall displacement, tip-contact steps).
Cost on ``default``: 10 episodes of ~500 steps, about 5 s static and 10 s dynamic on one
loaded core (``figures["expert_s"]``).

:func:`expert_success` is the same drive as a measurement: the scripted expert's or the
centerline follower's success on other target sets (unseen by every training), static and
dynamic, through :func:`cgail_learning.evaluate.run_trials`.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import time
from typing import Any

import numpy as np

from cgail_sim.anatomy import Anatomy, AnatomyError
from cgail_sim.ftl_model import CatheterConfig
from cgail_sim.validate import (
    bend_radii,
    centerline_place,
    Check,
    ExpertTrial,
    geometric_checks,
    MAX_VERTICES,
    Validation,
    WALL_BOUND_MM,
)

# Check, ExpertTrial, Validation, bend_radii and centerline_place are the simulator's geometric
# checks (cgail_sim.validate), part of this module's results: importable from here too.
__all__ = ["EXPERT_TARGET_SET", "MAX_VERTICES", "WALL_BOUND_MM", "Check", "ExpertTrial",
           "SuccessTable", "Validation", "bend_radii", "centerline_place", "expert_success",
           "run_expert_trial", "validate_anatomy"]

#: Target set of the expert check: the standard one (``EnvConfig.scenario_seed`` 0), which the
#: rig, the demonstrations and the presets use.
EXPERT_TARGET_SET = 0
#: Episode outcomes of the expert check.
OUTCOMES = ("success", "collision", "exited", "timeout", "simulation fault")


def _exit_where(anatomy: Anatomy, previous: np.ndarray, tip: np.ndarray) -> str:
    """Which cut the last step ``previous -> tip`` left the lumen through
    (:func:`cgail_sim.exits.crossed_disc` on :attr:`Anatomy.exit_discs`: row 0 is the
    descending cut), else out of the anatomy's bounds (the env's other exit)."""
    from cgail_sim.exits import crossed_disc

    discs = anatomy.exit_discs
    (x0, y0, z0), (x1, y1, z1) = np.asarray(previous, float), np.asarray(tip, float)
    k = int(crossed_disc(x0, y0, z0, x1, y1, z1, discs))
    if k < 0:
        return "out of the anatomy's bounds"
    if k == 0:
        return "through the descending cut"
    x, y, z = discs[k, :3] * 1e3
    return f"through the cut at ({x:.0f}, {y:.0f}, {z:.0f}) mm (a branch end)"


def _fault_of(info: dict[str, Any]) -> str | None:
    """The simulation fault an env step reports in its info, if any (its text, or a
    placeholder when the env gives only the flag)."""
    for key in ("simulation_fault", "fault"):
        value = info.get(key)
        if isinstance(value, str) and value:
            return value
        if value is not None and not isinstance(value, str) and bool(value):
            text = info.get("fault_message") or info.get("simulation_fault_message")
            return str(text) if text else "the simulator stopped the episode"
    return None


def run_expert_trial(env: Any, expert: Any, start: int, target: int) -> ExpertTrial:
    """One full expert episode from ``start`` to ``target`` of ``env``'s target set.

    Args:
        env: a :class:`~cgail_sim.env.CatheterNavEnv`.
        expert: a :class:`~cgail_learning.expert.ScriptedExpert` of ``env``.
        start: start index.
        target: target index.

    Returns:
        The episode's outcome and figures; a simulation fault (a wall that blows up) ends it
        as ``simulation fault``, never raised.
    """
    from cgail_sim.wall import WallError

    eng = env.unwrapped.engine
    anatomy = eng.world.anatomy
    env.reset(seed=target, options={"start": start, "target": target})
    expert.reset(None)
    rest = np.asarray(eng.scenarios.targets[target].position)
    rel = (rest - np.asarray(anatomy.annulus_center)) * 1e3
    height = float(rel @ np.asarray(anatomy.root_axis))
    max_wall = 0.0
    contact = 0
    fault: str | None = None
    info: dict[str, Any] = {}
    bend_mm = math.inf
    while True:
        previous = np.array(eng.catheter.tip_position[0])  # (the exit's step starts here)
        try:
            _, _, terminated, truncated, info = env.step(expert.act())
        except WallError as err:
            fault = str(err)
        wall = eng.walls[0]
        max_wall = max(max_wall, float(getattr(wall, "max_displacement", 0.0)))
        if fault is None:
            fault = _fault_of(info)
        if fault is not None:
            break
        contact += bool(info["in_contact"])
        if terminated or truncated:
            break
    steps = int(eng.steps[0])
    tip = np.asarray(eng.catheter.tip_position[0])
    final = float(np.linalg.norm(np.asarray(eng.target[0]) - tip)) * 1e3
    closest = float(eng.min_distance[0]) * 1e3
    if fault is not None:
        outcome = "simulation fault"
        detail = f"simulation fault at step {steps} ({fault})"
    elif info["success"]:
        outcome, detail = "success", ""
    elif info["collision"]:
        outcome = "collision"
        detail = (f"collision {final:.0f} mm from the target at step {steps} "
                  f"({float(info['collision_force']):.1f} N, "
                  f"{float(info['penetration']) * 1e3:.1f} mm into the wall), ")
        place, bend_mm = centerline_place(eng.world.centerlines[eng.branch[0]], tip)
        detail += place
    elif info["exited"]:
        outcome = "exited"
        detail = (f"exited {_exit_where(anatomy, previous, tip)} at step {steps}, "
                  f"{final:.0f} mm from the target")
    else:
        outcome = "timeout"
        detail = (f"timeout after {steps} steps, closest {closest:.0f} mm from the target "
                  f"(final {final:.0f} mm)")
    return ExpertTrial(mode=env.unwrapped.config.mode, target=target,
                       target_mm=(float(rel[0]), float(rel[1]), float(rel[2])),
                       height_mm=height, start=start, outcome=outcome, steps=steps,
                       final_distance_mm=final, closest_mm=closest,
                       max_wall_mm=max_wall * 1e3, contact_steps=contact, detail=detail,
                       collision_bend_mm=bend_mm)


def _expert_check(anatomy: Anatomy, v: Validation, mode: str) -> None:
    """The ``expert <mode>`` row (module doc)."""
    from cgail_learning.expert import ScriptedExpert
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    name = f"expert {mode}"
    limit = f"every target of set {EXPERT_TARGET_SET} reached"
    t0 = time.perf_counter()
    try:
        env = CatheterNavEnv(EnvConfig(mode=mode, anatomy=anatomy,
                                       scenario_seed=EXPERT_TARGET_SET))
    except (AnatomyError, ValueError) as err:
        v.add(name, "error", "not run", limit, f"the {mode} env does not build: {err}")
        return
    expert = ScriptedExpert(env)
    n_s, n_t = len(env.scenarios.starts), len(env.scenarios.targets)
    failed: list[tuple[ExpertTrial, list[ExpertTrial]]] = []
    retried: list[str] = []
    reached = 0
    steps = 0
    for k in range(n_t):
        tried: list[ExpertTrial] = []
        for s in [k % n_s, *(j for j in range(n_s) if j != k % n_s)]:
            trial = run_expert_trial(env, expert, s, k)
            tried.append(trial)
            v.expert_trials.append(trial)
            steps += trial.steps
            if trial.outcome in ("success", "simulation fault"):
                break
        last = tried[-1]
        misses = [t for t in tried if t.outcome != "success"]
        if last.outcome == "success":
            reached += 1
            if misses:
                retried.append(f"{last.where} reached from start {last.start} only ("
                               + "; ".join(f"from start {t.start}: {t.detail}" for t in misses)
                               + ")")
        else:
            failed.append((last, misses))
            if last.outcome == "simulation fault":
                break  # (the wall cannot take the catheter here: no more minutes on it)
    elapsed = time.perf_counter() - t0
    v.figures[f"expert_{mode}_s"] = elapsed
    v.figures["expert_s"] = v.figures.get("expert_s", 0.0) + elapsed
    v.figures[f"expert_{mode}_steps"] = steps
    trials = [t for t in v.expert_trials if t.mode == mode]
    walls = max((t.max_wall_mm for t in trials), default=0.0)
    value = (f"{reached}/{n_t} targets reached ({len(trials)} episode"
             f"{'s' * (len(trials) != 1)}, {steps} steps, "
             f"{elapsed:.1f} s" + (f"; wall <= {walls:.1f} mm" if mode == "dynamic" else "")
             + ")")
    if failed:
        first, misses = failed[0]
        text = (f"{first.where} not reached in {mode} mode: "
                + "; ".join(f"from start {t.start}: {t.detail}" for t in misses))
        if len(failed) > 1:
            text += "; also " + ", ".join(
                f"target {t.target} ({'; '.join(f'start {m.start}: {m.outcome}' for m in ms)})"
                for t, ms in failed[1:])
        if first.outcome == "simulation fault" and reached + len(failed) < n_t:
            text += f"; targets {', '.join(str(j) for j in range(first.target + 1, n_t))} " \
                    "not driven after the fault"
        v.add(name, "error", value, limit,
              f"expected the scripted expert to reach every standard target, found {text}: "
              "the anatomy is not usable for this task" + _diagnosis(failed, env)
              + " (the report's expert table says more)")
    elif retried:
        v.add(name, "warning", value, limit, f"in {mode} mode " + "; ".join(retried))
    else:
        v.add(name, "ok", value, limit)


def _diagnosis(failed: list[tuple[ExpertTrial, list[ExpertTrial]]], env: Any) -> str:
    """Why the expert fails, where every miss is a collision in a bend tighter than the
    catheter's smallest bend radius (L / theta_max): ``''`` otherwise."""
    cat = env.unwrapped.engine.config.catheter
    r_bend = cat.segment_length / cat.theta_max * 1e3
    bends = []
    for _, misses in failed:
        for t in misses:
            if t.outcome != "collision" or not t.collision_bend_mm < r_bend:
                return ""
            bends.append(t.collision_bend_mm)
    if not bends:
        return ""
    lo, hi = f"{min(bends):.0f}", f"{max(bends):.0f}"
    return (f": every miss is a collision where the centreline bends with a "
            f"{lo if lo == hi else f'{lo}-{hi}'} mm radius, against the catheter's smallest bend "
            f"radius of {r_bend:.1f} mm (L / theta_max), and the lumen there is too narrow for "
            "the catheter to cut that corner without touching the wall")


def _check_modes(name: str, modes: Any) -> tuple[str, ...]:
    modes = tuple(modes)
    bad = [m for m in modes if m not in ("static", "dynamic")]
    if bad or not modes:
        raise ValueError(f"{name}: expected modes among 'static' and 'dynamic', found "
                         f"{list(modes)}")
    return modes


@dataclass
class SuccessTable:
    """Success of one method on target sets of an anatomy (:func:`expert_success`)."""

    method: str
    trials: dict[str, dict[int, list[Any]]]
    """mode -> target set -> the trials (:class:`cgail_learning.evaluate.Trial`)."""

    def rate(self, mode: str, target_set: int | None = None) -> float:
        """Share of successful trials in ``mode``, over every set or in ``target_set``."""
        by_set = self.trials[mode]
        runs = [t for k, ts in by_set.items() if target_set in (None, k) for t in ts]
        return float(np.mean([t.success for t in runs])) if runs else float("nan")

    def markdown(self) -> str:
        """A markdown table: one row per mode, one column per target set, and all sets."""
        sets = sorted({k for by_set in self.trials.values() for k in by_set})
        lines = [f"| {self.method} | " + " | ".join(f"set {k}" for k in sets) + " | all |",
                 "|---|" + "---|" * (len(sets) + 1)]
        for mode, by_set in self.trials.items():
            cells = [f"{100 * self.rate(mode, k):.0f}% ({len(by_set[k])})" for k in sets]
            n = sum(len(ts) for ts in by_set.values())
            lines.append(f"| {mode} | " + " | ".join(cells)
                         + f" | {100 * self.rate(mode):.0f}% ({n}) |")
        return "\n".join(lines)


def expert_success(anatomy: Any, *, sets: tuple[int, ...] = (1, 2, 3),
                   modes: tuple[str, ...] = ("static", "dynamic"), method: str = "expert",
                   trials: int = 15, seed: int = 10_000, tracker: bool = True) -> SuccessTable:
    """The scripted expert's or the centerline follower's success on target sets ``sets``
    (not set 0, which the demonstrations and the expert check use: targets no run trained on),
    in each mode, through ``evaluate``'s trials
    (:func:`cgail_learning.evaluate.run_trials`: trial ``k`` from start ``k % 3`` to
    target ``(k // 3) % 5`` with seed ``seed + k``, so 15 trials cover every pair once).

    Args:
        anatomy: a built-in name, a prepared directory, a mesh file or an
            :class:`~cgail_sim.anatomy.Anatomy`.
        sets: the target sets (``EnvConfig.scenario_seed``).
        modes: ``static`` and/or ``dynamic``.
        method: ``expert`` (the scripted expert, which reads the simulator's state; seeded
            score jitter per trial, as in ``evaluate``) or ``follower`` (the centerline
            follower, :class:`~cgail_learning.evaluate.CenterlineFollower`).
        trials: trials per set and mode.
        seed: base seed of the trials.
        tracker: the follower perceives the tip through the simulated EM tracker
            (``evaluate``'s and ``plan_patient``'s default, :class:`~cgail_learning.
            evaluate.TrackingNoise`); False: the true tip.

    Raises:
        ValueError: an unknown method or mode, fewer than one trial.
        AnatomyError: an anatomy that does not load or admits no scenario set.
    """
    from cgail_learning.evaluate import CenterlineFollower, run_trials, TrackingNoise
    from cgail_learning.expert import ScriptedExpert
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    if method not in ("expert", "follower"):
        raise ValueError(f"method: expected 'expert' or 'follower', found {method!r}")
    if trials < 1:
        raise ValueError(f"trials: expected >= 1, found {trials}")
    modes = _check_modes("modes", modes)
    out: dict[str, dict[int, list[Any]]] = {}
    for mode in modes:
        for k in sets:
            env = CatheterNavEnv(EnvConfig(mode=mode, anatomy=anatomy, scenario_seed=int(k)))
            tracked = method == "follower"
            agent = CenterlineFollower(env) if tracked else ScriptedExpert(env)
            noise = TrackingNoise() if tracker and tracked else None
            out.setdefault(mode, {})[int(k)] = run_trials(env, agent, trials, seed,
                                                           noise=noise, tracked=tracked)
    return SuccessTable(method, out)


def validate_anatomy(anatomy: Anatomy, *, catheter: CatheterConfig | None = None,
                     wall: bool = True, wall_bound_mm: float = WALL_BOUND_MM,
                     beats: float = 2.0, expert: bool = False,
                     expert_modes: tuple[str, ...] = ("static", "dynamic")) -> Validation:
    """Run every check (module doc) on ``anatomy``.

    Args:
        anatomy: the lumen to check (phantom frame).
        catheter: the catheter (default: the paper's, 7 mm, L 50 mm, theta_max 90 deg).
        wall: run the deformable-wall check.
        wall_bound_mm: largest accepted particle displacement, mm.
        beats: heartbeats the wall check runs.
        expert: run the expert check (the scripted expert to every standard target, whole
            episodes; ~15 s), the proof that the anatomy is usable (``prepare_anatomy`` runs
            it; off by default for the cheap geometric screening of population samples).
        expert_modes: the modes of the expert check (``static``, ``dynamic``).

    Returns:
        The checks and their figures; later checks that depend on a failed one are skipped
        and say so.
    """
    cat = catheter or CatheterConfig()
    _check_modes("expert_modes", expert_modes)
    v = Validation()
    t0 = time.perf_counter()
    if not geometric_checks(anatomy, cat, v, wall=wall, wall_bound_mm=wall_bound_mm,
                            beats=beats):
        return v
    for mode in expert_modes if expert else ():
        if not v.errors:  # (a refused lumen: no minutes of timeouts on top)
            _expert_check(anatomy, v, mode)
        else:
            v.add(f"expert {mode}", "error", "not run",
                  f"every target of set {EXPERT_TARGET_SET} reached",
                  "not run: fix the errors above first")
    v.figures["validation_s"] = time.perf_counter() - t0
    return v

"""Is a prepared anatomy usable? Checks with one clear line each, and the figures behind them.

:func:`validate_anatomy` runs every check on an :class:`~cgail_planner.sim.anatomy.Anatomy`
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
(:class:`~cgail_planner.learning.expert.ScriptedExpert`, no score jitter: a deterministic
function of the anatomy), once in the static env and once in the dynamic one (heartbeat,
deformable wall pushed by the catheter body, the target riding on its wall particle), each a
full episode of :class:`~cgail_planner.sim.env.CatheterNavEnv` ending in success, collision,
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
dynamic, through :func:`cgail_planner.learning.evaluate.run_trials`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import time
from typing import Any

import numpy as np

from cgail_planner.sim.anatomy import Anatomy, AnatomyError
from cgail_planner.sim.ftl_model import CatheterConfig

__all__ = ["EXPERT_TARGET_SET", "Check", "ExpertTrial", "SuccessTable", "Validation",
           "bend_radii", "expert_success", "run_expert_trial", "validate_anatomy"]

#: Vertex count above which the deformable wall falls below ~500 steps/s.
MAX_VERTICES = 4000
#: Largest wall-particle displacement from rest accepted in the deformable-wall check, mm
#: (the heartbeat moves the annulus by up to ~11 mm; the catheter indents the wall by a few).
WALL_BOUND_MM = 25.0
#: Target set of the expert check: the standard one (``EnvConfig.scenario_seed`` 0), which the
#: rig, the demonstrations and the presets use.
EXPERT_TARGET_SET = 0
#: Episode outcomes of the expert check.
OUTCOMES = ("success", "collision", "exited", "timeout", "simulation fault")


@dataclass(frozen=True)
class Check:
    """One line of the report's check table."""

    name: str
    status: str
    """``ok``, ``warning`` or ``error``."""
    value: str
    """The measured figure, with its unit."""
    limit: str
    """What it is compared with."""
    message: str
    """One line: what is wrong and what to do (empty when ok)."""


@dataclass(frozen=True)
class ExpertTrial:
    """One episode of the expert check."""

    mode: str
    """``static`` or ``dynamic``."""
    target: int
    """Index in target set :data:`EXPERT_TARGET_SET`."""
    target_mm: tuple[float, float, float]
    """The target's rest position from the annulus centre, mm (phantom axes: x patient left,
    y posterior, z cranial)."""
    height_mm: float
    """The target's height above the annulus plane (along the root axis), mm."""
    start: int
    outcome: str
    """One of :data:`OUTCOMES`."""
    steps: int
    final_distance_mm: float
    """Tip-target distance at the last step, mm."""
    closest_mm: float
    """Smallest tip-target distance of the episode (T_a), mm."""
    max_wall_mm: float
    """Largest wall-particle displacement from rest over the episode, mm (0 in static mode)."""
    contact_steps: int
    """Steps with the tip touching the wall (minor contacts included)."""
    detail: str
    """Why it failed, one phrase (empty on success)."""
    collision_bend_mm: float = math.inf
    """A collision's place: the centreline's tightest bend radius within 10 mm of the tip,
    mm (inf: no collision, or straight there)."""

    @property
    def where(self) -> str:
        """The target, as the report and the error name it."""
        x, y, z = self.target_mm
        return (f"target {self.target} (({x:.1f}, {y:.1f}, {z:.1f}) mm from the annulus "
                f"centre, {self.height_mm:.1f} mm above its plane)")


@dataclass
class Validation:
    """All checks of one anatomy, and the data behind them (for the report and render)."""

    checks: list[Check] = field(default_factory=list)
    centerlines: dict[str, Any] | None = None
    scenarios: Any = None
    figures: dict[str, Any] = field(default_factory=dict)
    """Numbers for the report: radius profile, bends, wall displacement, speeds ..."""
    expert_trials: list[ExpertTrial] = field(default_factory=list)
    """Every episode of the expert check, in the order run (module doc)."""

    @property
    def errors(self) -> list[Check]:
        return [c for c in self.checks if c.status == "error"]

    @property
    def warnings(self) -> list[Check]:
        return [c for c in self.checks if c.status == "warning"]

    def add(self, name: str, status: str, value: str, limit: str, message: str = "") -> None:
        self.checks.append(Check(name, status, value, limit, message))


def bend_radii(points: np.ndarray, half: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """(arc length, bend radius) along a polyline (m): the circumradius of the points ``half``
    arc length before and after each point (inf where straight)."""
    pts = np.asarray(points, dtype=float)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s = arc[(arc >= half) & (arc <= arc[-1] - half)]

    def at(t: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(t, arc, pts[:, k]) for k in range(3)], axis=1)

    a, b, c = at(s - half), at(s), at(s + half)
    ab = np.linalg.norm(b - a, axis=1)
    bc = np.linalg.norm(c - b, axis=1)
    ca = np.linalg.norm(a - c, axis=1)
    cross = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(cross > 1e-15, ab * bc * ca / (2.0 * cross), np.inf)
    return s, r


def _centerline_place(centerline: Any, point: np.ndarray) -> tuple[str, float]:
    """Where ``point`` lies along a centreline, as an error names it (the arc length of its
    nearest centreline point, the centreline's tightest bend radius within 10 mm of it,
    :func:`bend_radii`, and the lumen's inscribed radius there), and that bend radius, mm."""
    pts = np.asarray(centerline.points, dtype=float)
    i = int(np.argmin(np.linalg.norm(pts - point, axis=1)))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s, rb = bend_radii(pts)
    near = np.abs(s - arc[i]) <= 0.010
    bend = float(rb[near].min()) if near.any() else math.inf
    text = f"{arc[i] * 1e3:.0f} mm along the centreline"
    if math.isfinite(bend):
        text += f", where it bends with a {bend * 1e3:.0f} mm radius"
    lumen = float(np.asarray(centerline.radii)[i]) * 1e3
    return text + f" in a lumen of {lumen:.0f} mm radius", bend * 1e3


def _mesh_checks(anatomy: Anatomy, v: Validation) -> bool:
    mesh = anatomy.mesh
    euler = int(mesh.euler_number)
    ok = bool(mesh.is_watertight and mesh.is_winding_consistent and euler == 2)
    v.add("mesh", "ok" if ok else "error",
          f"watertight {mesh.is_watertight}, Euler {euler}", "closed, oriented, Euler 2",
          "" if ok else "expected one closed, consistently oriented genus-0 surface, found "
          f"watertight={mesh.is_watertight}, winding consistent={mesh.is_winding_consistent}, "
          f"Euler characteristic {euler}")
    n = len(anatomy.vertices)
    v.figures["vertices"] = n
    v.add("vertex count", "ok" if n <= MAX_VERTICES else "warning", f"{n}",
          f"<= {MAX_VERTICES}",
          "" if n <= MAX_VERTICES else f"expected <= {MAX_VERTICES} vertices for a deformable "
          f"wall at >= 500 steps/s, found {n}: prepare with a lower --target-vertices")
    tri = anatomy.vertices[anatomy.faces[anatomy.wall_face_mask]]
    angles = []
    for k in range(3):
        e1 = tri[:, (k + 1) % 3] - tri[:, k]
        e2 = tri[:, (k + 2) % 3] - tri[:, k]
        cos = (e1 * e2).sum(axis=1) / np.maximum(
            np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    min_angle = np.min(angles, axis=0)
    low = float(np.mean(min_angle < 15.0))
    v.figures["min_angle_deg"] = float(min_angle.min())
    v.figures["share_under_15deg"] = low
    v.add("face quality", "ok" if low <= 0.05 else "warning",
          f"smallest angle {min_angle.min():.1f} deg; {low:.1%} of wall faces under 15 deg",
          "<= 5 % under 15 deg",
          "" if low <= 0.05 else f"expected <= 5 % of wall faces with an angle under 15 deg, "
          f"found {low:.1%}: slivers slow the wall solver and can make it stiff")
    return ok


def _landmark_checks(anatomy: Anatomy, v: Validation) -> bool:
    ax = anatomy.root_axis
    heights = {s: float((anatomy.ostia[s] - anatomy.annulus_center) @ ax) * 1e3
               for s in ("left", "right")}
    v.figures["ostium_heights_mm"] = heights
    bad = [f"{s} {h:.1f} mm" for s, h in heights.items() if not 5.0 <= h <= 30.0]
    sep = float(np.linalg.norm(anatomy.ostia["left"] - anatomy.ostia["right"])) * 1e3
    problems = []
    if bad:
        problems.append(f"ostia 5-30 mm above the annulus, found {', '.join(bad)}")
    if not 8.0 <= sep <= 60.0:
        problems.append(f"ostia 8-60 mm apart, found {sep:.1f} mm")
    ok = not problems
    v.add("landmarks", "ok" if ok else "error",
          f"ostia {heights['left']:.1f} / {heights['right']:.1f} mm above the annulus, "
          f"{sep:.1f} mm apart",
          "ostia 5-30 mm high, 8-60 mm apart",
          "" if ok else "expected " + "; ".join(problems))
    side = float((anatomy.ostia["left"] - anatomy.ostia["right"])[0]) * 1e3
    if side < 0:
        v.add("ostium sides", "warning", f"left ostium {-side:.1f} mm right of the right one",
              "left ostium to the patient's left",
              "expected the left ostium to the patient's left (+x) of the right one, found it "
              f"{-side:.1f} mm to the right: swapped ostia or a flipped x axis?")
    return ok


def _lumen_checks(anatomy: Anatomy, cat: CatheterConfig, v: Validation) -> None:
    assert v.centerlines is not None
    r_cat = cat.radius * 1e3
    worst: tuple[float, str, float] = (math.inf, "", 0.0)
    profile = {}
    for b, cl in v.centerlines.items():
        pts = np.asarray(cl.points)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0),
                                                              axis=1))]) * 1e3
        # The last 10 mm run into the ostium on the wall: not a lumen to pass.
        sel = arc <= arc[-1] - 10.0
        r = np.asarray(cl.radii)[sel] * 1e3
        profile[b] = {"arc_mm": arc[sel].tolist(), "radius_mm": r.tolist(),
                      "min": float(r.min()), "median": float(np.median(r))}
        i = int(np.argmin(r))
        if r[i] < worst[0]:
            worst = (float(r[i]), b, float(arc[sel][i]))
    v.figures["radius_profile"] = profile
    rmin, branch, where = worst
    med = float(np.median(np.concatenate([np.asarray(p["radius_mm"]) for p in profile.values()])))
    value = (f"min {rmin:.1f} mm ({branch} centreline, {where:.0f} mm from the start); "
             f"median {med:.1f} mm")
    limit = f"> {r_cat:.1f} mm (catheter radius); warn < {r_cat + 1.5:.1f} mm"
    if rmin <= r_cat:
        v.add("lumen radius", "error", value, limit,
              f"expected a lumen wider than the catheter (radius {r_cat:.1f} mm), found an "
              f"inscribed radius of {rmin:.1f} mm {where:.0f} mm along the {branch} centreline")
    elif rmin < r_cat + 1.5:
        v.add("lumen radius", "warning", value, limit,
              f"the narrowest point ({rmin:.1f} mm radius, {where:.0f} mm along the {branch} "
              f"centreline) leaves less than 1.5 mm around the catheter")
    else:
        v.add("lumen radius", "ok", value, limit)
    r_bend = cat.segment_length / cat.theta_max * 1e3
    tight: tuple[float, str, float] = (math.inf, "", 0.0)
    for b, cl in v.centerlines.items():
        s, rb = bend_radii(np.asarray(cl.points))
        s_mm = s * 1e3
        sel = s_mm <= s_mm[-1] - 15.0   # not the final turn into the ostium
        if sel.any():
            i = int(np.argmin(rb[sel]))
            if rb[sel][i] * 1e3 < tight[0]:
                tight = (float(rb[sel][i]) * 1e3, b, float(s_mm[sel][i]))
    v.figures["tightest_bend_mm"] = tight[0]
    value = f"{tight[0]:.1f} mm ({tight[1]} centreline, {tight[2]:.0f} mm from the start)"
    limit = f">= {r_bend:.1f} mm (L / theta_max)"
    if tight[0] < r_bend:
        v.add("tightest bend", "warning", value, limit,
              f"the centreline bends with a {tight[0]:.1f} mm radius, tighter than the catheter's "
              f"smallest bend radius {r_bend:.1f} mm: the catheter must cut this corner")
    else:
        v.add("tightest bend", "ok", value, limit)


def _start_checks(anatomy: Anatomy, cat: CatheterConfig, v: Validation) -> bool:
    from cgail_planner.sim.scenarios import tube_clearance

    r_cat = cat.radius
    worst = math.inf
    where = ""
    for k, st in enumerate(v.scenarios.starts):
        p = np.asarray(st.position)
        # the introducer as the catheter's body lies in it: straight, or along the
        # centerline where a straight one would touch the wall (StartConfig.introducer)
        nodes = np.vstack([np.asarray(st.introducer, dtype=np.float64).reshape(-1, 3), p])
        clear, at = tube_clearance(anatomy, nodes)
        if clear < worst:
            worst = float(clear)
            where = f"start {k}, {float(np.linalg.norm(at - p)) * 1e3:.0f} mm behind the tip"
    v.figures["introducer_clearance_mm"] = worst * 1e3
    value = f"{worst * 1e3:.1f} mm ({where})"
    limit = f">= {r_cat * 1e3:.1f} mm (catheter radius)"
    if worst < r_cat:
        v.add("starts and introducers", "error", value, limit,
              f"expected every start and its introducer {r_cat * 1e3:.1f} mm from the "
              f"wall, found {worst * 1e3:.1f} mm at {where}: the descending aorta bends too "
              "much there; give --exit-point higher up the descending aorta")
        return False
    v.add("starts and introducers", "ok", value, limit)
    return True


def _wall_check(anatomy: Anatomy, cat: CatheterConfig, v: Validation,
                bound_mm: float, beats: float) -> None:
    from cgail_planner.sim.env import DYNAMIC_PBD_CONFIG
    from cgail_planner.sim.wall import DeformableWall

    wall = DeformableWall(anatomy, DYNAMIC_PBD_CONFIG)
    st = v.scenarios.starts[0]
    tail = np.asarray(st.introducer_tail)
    p = np.asarray(st.position)
    n_body = max(2, int(np.linalg.norm(p - tail) / 0.005) + 1)
    body = np.ascontiguousarray(tail + np.linspace(0.0, 1.0, n_body)[:, None] * (p - tail))
    rest = np.asarray(anatomy.vertices)
    period = float(wall.heartbeat.config.period)
    dt = 0.1
    steps = math.ceil(beats * period / dt)
    worst = 0.0
    when = 0.0
    for k in range(1, steps + 1):
        wall.step(k * dt, dt, body, cat.radius)
        x = np.asarray(wall.vertices)
        if not np.isfinite(x).all():
            worst, when = math.inf, k * dt
            break
        d = float(np.linalg.norm(x - rest, axis=1).max())
        if d > worst:
            worst, when = d, k * dt
    v.figures["wall_max_displacement_mm"] = worst * 1e3
    value = f"{worst * 1e3:.1f} mm (t = {when:.1f} s)"
    limit = f"<= {bound_mm:.0f} mm, finite"
    if not worst * 1e3 <= bound_mm:
        v.add("deformable wall", "error", value, limit,
              f"expected the beating wall within {bound_mm:.0f} mm of rest, found a particle "
              f"{worst * 1e3:.0f} mm away at t = {when:.1f} s: this lumen cannot be simulated "
              "in dynamic mode (check the face quality and the introducer)")
    else:
        v.add("deformable wall", "ok", value, limit)


def _exit_where(anatomy: Anatomy, previous: np.ndarray, tip: np.ndarray) -> str:
    """Which cut the last step ``previous -> tip`` left the lumen through
    (:func:`cgail_planner.sim.exits.crossed_disc` on :attr:`Anatomy.exit_discs`: row 0 is the
    descending cut), else out of the anatomy's bounds (the env's other exit)."""
    from cgail_planner.sim.exits import crossed_disc

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
        env: a :class:`~cgail_planner.sim.env.CatheterNavEnv`.
        expert: a :class:`~cgail_planner.learning.expert.ScriptedExpert` of ``env``.
        start: start index.
        target: target index.

    Returns:
        The episode's outcome and figures; a simulation fault (a wall that blows up) ends it
        as ``simulation fault``, never raised.
    """
    from cgail_planner.sim.wall import WallError

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
        place, bend_mm = _centerline_place(eng.world.centerlines[eng.branch[0]], tip)
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
    from cgail_planner.learning.expert import ScriptedExpert
    from cgail_planner.sim.config import EnvConfig
    from cgail_planner.sim.env import CatheterNavEnv

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
    """mode -> target set -> the trials (:class:`cgail_planner.learning.evaluate.Trial`)."""

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
    (:func:`cgail_planner.learning.evaluate.run_trials`: trial ``k`` from start ``k % 3`` to
    target ``(k // 3) % 5`` with seed ``seed + k``, so 15 trials cover every pair once).

    Args:
        anatomy: a built-in name, a prepared directory, a mesh file or an
            :class:`~cgail_planner.sim.anatomy.Anatomy`.
        sets: the target sets (``EnvConfig.scenario_seed``).
        modes: ``static`` and/or ``dynamic``.
        method: ``expert`` (the scripted expert, which reads the simulator's state; seeded
            score jitter per trial, as in ``evaluate``) or ``follower`` (the centerline
            follower, :class:`~cgail_planner.learning.evaluate.CenterlineFollower`).
        trials: trials per set and mode.
        seed: base seed of the trials.
        tracker: the follower perceives the tip through the simulated EM tracker
            (``evaluate``'s and ``plan_patient``'s default, :class:`~cgail_planner.learning.
            evaluate.TrackingNoise`); False: the true tip.

    Raises:
        ValueError: an unknown method or mode, fewer than one trial.
        AnatomyError: an anatomy that does not load or admits no scenario set.
    """
    from cgail_planner.learning.evaluate import CenterlineFollower, run_trials, TrackingNoise
    from cgail_planner.learning.expert import ScriptedExpert
    from cgail_planner.sim.config import EnvConfig
    from cgail_planner.sim.env import CatheterNavEnv

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
    from cgail_planner.sim.centerline import compute_centerlines
    from cgail_planner.sim.scenarios import build_scenarios

    cat = catheter or CatheterConfig()
    _check_modes("expert_modes", expert_modes)
    v = Validation()
    t0 = time.perf_counter()
    if not _mesh_checks(anatomy, v):
        return v
    landmarks_ok = _landmark_checks(anatomy, v)
    try:
        v.centerlines = compute_centerlines(anatomy)
    except AnatomyError as err:
        v.add("centrelines", "error", "none", "both ostia reached", str(err))
        return v
    lengths = {b: c.length * 1e3 for b, c in v.centerlines.items()}
    v.figures["centerline_length_mm"] = lengths
    short = min(lengths.values())
    v.add("centrelines", "ok" if short >= 150.0 else "error",
          f"left {lengths['left']:.0f} mm, right {lengths['right']:.0f} mm",
          "both ostia reached, >= 150 mm",
          "" if short >= 150.0 else f"expected centrelines >= 150 mm from the start to the "
          f"ostia (descending aorta, arch, ascending aorta), found {short:.0f} mm: misplaced "
          "exit or ostia?")
    _lumen_checks(anatomy, cat, v)
    try:
        v.scenarios = build_scenarios(anatomy, v.centerlines)
    except ValueError as err:
        v.add("scenarios", "error", "none", "3 starts, 5 targets", str(err))
        return v
    v.add("targets", "ok", f"{len(v.scenarios.targets)} targets, {len(v.scenarios.starts)} "
          "starts", "5 targets, 3 starts")
    starts_ok = _start_checks(anatomy, cat, v)
    if wall and starts_ok and landmarks_ok:
        _wall_check(anatomy, cat, v, wall_bound_mm, beats)
    elif wall:
        v.add("deformable wall", "error", "not run", f"<= {wall_bound_mm:.0f} mm",
              "not run: fix the errors above first")
    for mode in expert_modes if expert else ():
        if not v.errors:  # (a refused lumen: no minutes of timeouts on top)
            _expert_check(anatomy, v, mode)
        else:
            v.add(f"expert {mode}", "error", "not run",
                  f"every target of set {EXPERT_TARGET_SET} reached",
                  "not run: fix the errors above first")
    v.figures["validation_s"] = time.perf_counter() - t0
    return v

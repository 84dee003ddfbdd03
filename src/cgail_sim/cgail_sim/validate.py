"""The geometric checks of an anatomy: is its lumen usable by the catheter in the simulator?

:func:`validate_geometry` runs them all on an :class:`~cgail_sim.anatomy.Anatomy`, one clear
line each (:class:`Check`), with the figures behind them (:class:`Validation`): mesh, vertex
count, face quality, landmarks, centrelines, lumen radius, tightest bend, starts and
introducers, targets and a short run of the deformable wall (the table of
:mod:`cgail_patient.validate`). A population sample is screened with them
(:mod:`cgail_sim.population`); a prepared patient anatomy gets them and, on top, the scripted
expert's drive to every standard target (:func:`cgail_patient.validate.validate_anatomy`),
which needs the learning package and so lives there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import time
from typing import Any

import numpy as np

from cgail_sim.anatomy import Anatomy, AnatomyError
from cgail_sim.ftl_model import CatheterConfig

__all__ = ["MAX_VERTICES", "WALL_BOUND_MM", "Check", "ExpertTrial", "Validation", "bend_radii",
           "centerline_place", "geometric_checks", "validate_geometry"]

#: Vertex count above which the deformable wall falls below ~500 steps/s.
MAX_VERTICES = 4000
#: Largest wall-particle displacement from rest accepted in the deformable-wall check, mm
#: (the heartbeat moves the annulus by up to ~11 mm; the catheter indents the wall by a few).
WALL_BOUND_MM = 25.0


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


def centerline_place(centerline: Any, point: np.ndarray) -> tuple[str, float]:
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
    from cgail_sim.scenarios import tube_clearance

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
    from cgail_sim.pbd import DYNAMIC_PBD_CONFIG
    from cgail_sim.wall import DeformableWall

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


def geometric_checks(anatomy: Anatomy, cat: CatheterConfig, v: Validation, *, wall: bool,
                     wall_bound_mm: float, beats: float) -> bool:
    """Run the geometric checks (module doc) on ``anatomy``, adding them to ``v``.

    Returns:
        False when a failed check stopped the others (mesh, centrelines or scenarios), True
        when every check ran (each may still have failed).
    """
    from cgail_sim.centerline import compute_centerlines
    from cgail_sim.scenarios import build_scenarios

    if not _mesh_checks(anatomy, v):
        return False
    landmarks_ok = _landmark_checks(anatomy, v)
    try:
        v.centerlines = compute_centerlines(anatomy)
    except AnatomyError as err:
        v.add("centrelines", "error", "none", "both ostia reached", str(err))
        return False
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
        return False
    v.add("targets", "ok", f"{len(v.scenarios.targets)} targets, {len(v.scenarios.starts)} "
          "starts", "5 targets, 3 starts")
    starts_ok = _start_checks(anatomy, cat, v)
    if wall and starts_ok and landmarks_ok:
        _wall_check(anatomy, cat, v, wall_bound_mm, beats)
    elif wall:
        v.add("deformable wall", "error", "not run", f"<= {wall_bound_mm:.0f} mm",
              "not run: fix the errors above first")
    return True


def validate_geometry(anatomy: Anatomy, *, catheter: CatheterConfig | None = None,
                      wall: bool = True, wall_bound_mm: float = WALL_BOUND_MM,
                      beats: float = 2.0) -> Validation:
    """Run every geometric check (module doc) on ``anatomy``.

    Args:
        anatomy: the lumen to check (phantom frame).
        catheter: the catheter (default: the paper's, 7 mm, L 50 mm, theta_max 90 deg).
        wall: run the deformable-wall check.
        wall_bound_mm: largest accepted particle displacement, mm.
        beats: heartbeats the wall check runs.

    Returns:
        The checks and their figures; later checks that depend on a failed one are skipped
        and say so.
    """
    v = Validation()
    t0 = time.perf_counter()
    if geometric_checks(anatomy, catheter or CatheterConfig(), v, wall=wall,
                        wall_bound_mm=wall_bound_mm, beats=beats):
        v.figures["validation_s"] = time.perf_counter() - t0
    return v

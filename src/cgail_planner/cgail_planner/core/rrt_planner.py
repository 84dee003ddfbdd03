"""A classical curvature-constrained planner: bi-directional RRT on OMPL's 3-D Vana-Owen curves.

numpy and OMPL's Python bindings (``ompl`` 2.0.1 on PyPI); no rclpy and no torch. Used by
:class:`cgail_planner.core.planner.Planner` as ``planner_type='rrt'``, the classical peer of the
learned planner (Fauser et al.'s curvature-constrained bi-RRT for catheters).

**Catheter.** The tip moves forward along a curve whose curvature never exceeds
``1 / r_min`` with ``r_min = L / theta_max`` (:class:`cgail_sim.ftl_model.CatheterConfig`:
a full bend ``theta_max`` over the steerable segment ``L``; 50 mm / 90 deg = 31.8 mm).

**Curves (OMPL).** Every edge of the trees is a Vana-Owen curve of
:class:`ompl.base.VanaOwenStateSpace` with turning radius ``r_min``: a state is a position and
a heading (yaw, pitch); the curve couples a horizontal Dubins curve of radius ``r_h`` with a
vertical one of radius ``r_v``, ``1/r_v^2 = 1/r_min^2 - 1/r_h^2``. Its 3-D curvature is
``sqrt(1/r_v^2 + cos^4(pitch)/r_h^2) <= 1/r_min``; OMPL's sampling of the curves bends them up
to ~2% more, so it is asked for :data:`RADIUS_FACTOR` ``* r_min`` (the sampled path's curvature
is tested against ``1 / r_min``). The pitch is
bounded (:data:`MAX_PITCH`, the curves are singular at +-90 deg), so the planner plans in a frame
whose "horizontal" plane is the best-fit plane of the goal's Voronoi centerline (the aortic arch's
plane): along the lumen the heading stays near that plane (built-in anatomies: within 30 deg).

**Why not OMPL's RRT-Connect.** ``ompl.geometric.RRTConnect`` on this space was tried first:
it samples states uniformly in the bounding box with uniform headings, and the 2.0.1 bindings do
not expose ``StateSpace.setStateSamplerAllocator``, so the sampler cannot be told about the
lumen. In the aorta (a ~25 mm tube in a ~150 mm box) almost no uniform sample can be reached by
a curvature-bounded curve that stays in the tube: 5 s per query and no solution for any of the
15 default scenarios (measured on the 2-core VM). OMPL also seeds its samplers from a
process-wide generator and warns, when re-seeded after first use, that sampling will then not
be deterministic, so repeated plans in one process could not be tied to a seed.
So the tree search here is a small bi-directional RRT of our own (RRT-Connect's two trees,
joined by one curve), and OMPL provides what is hard to get right: the curvature-bounded
3-D steering curves (``getPath``, ``interpolate``, ``distance``)
and the motion checker that walks them (:class:`ompl.base.VanaOwenMotionValidator`).

**Search** (bi-directional, as Fauser et al.). The start tree grows forward from the tip pose,
the goal tree backward from goal states: the goal position with headings drawn around the
centerline's direction there (positions within ``goal_tolerance / 2`` of the goal only when the
goal itself lacks clearance). Samples lie in the lumen around the goal branch's Voronoi
centerline (a centerline point between the start and the goal, a lateral offset within the
local lumen radius less the clearance, the local centerline direction tilted by up to 35 deg).
An extension follows the Vana-Owen curve from the nearest node (by curve length among the
nearest few by distance) for at most ``range``; after every new node the other tree tries to
join it directly with one curve. The first joined path is shortcut greedily (each node joined to
the furthest later node one valid curve reaches). Every random draw comes from one
``numpy.random.Generator(seed)`` and the OMPL calls are deterministic, so a seed gives the same
path.

**Budget.** The search stops at whichever comes first: ``max_iterations`` iterations (each one
a tree extension or a goal state added) or the wall-clock ``time_limit_s``. The iteration
budget is the deterministic bound: with a generous time limit the result (a path or
:class:`NoPathError`) is a function of the seed and the configuration only, whatever the load
of the host. (Not to the bit across CPUs: numpy's SIMD kernels (AVX-512, AVX2, SSE) round the
anatomy built from its parameters differently in the last bits, and a long search amplifies
that; the success counts differ by a few plans of 15, see the tests.) The time limit is the
real-time safety bound of the planner node; a plan it cuts short depends on the machine's speed
(its error says which limit ran out).

**Validity.** A state is valid when the tip lies outside the exit slab of every open end
(:func:`cgail_sim.exits.in_exit_slab`, ``2 * resolution`` deep: no motion leaves
through a cut's disc), inside the anatomy's bounding region
(:func:`cgail_sim.scenarios.episode_bounds`) and at least ``catheter radius +
clearance_margin + resolution / 2`` from the wall (the wall's own distance query,
:meth:`cgail_sim.wall.StaticWall.distance`). Motions are checked every ``resolution`` of
arc length (OMPL's validity-checking resolution): the distance to the wall is 1-Lipschitz along
the curve, so between two checked states it is at least the checked value less
``resolution / 2``, and the whole curve clears the wall by ``radius + clearance_margin``. Start
and goal states are also checked inside the lumen (``contains``); a curve cannot leave the lumen
between checked states since it would have to cross the wall or a cut's disc (and so a slab).

**Output.** The joined curves sampled every ``resolution`` (:attr:`RrtPath.points`, start first,
the goal state last); :class:`~cgail_planner.core.planner.Planner` resamples them at its
``path_spacing``. No spline fit: the curves are already smooth (continuous heading), and a fit
could bend them beyond ``1 / r_min``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import itertools
import math
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cgail_planner.core.errors import InvalidInputError, NoPathError
from cgail_sim.exits import in_exit_slab
from cgail_sim.ftl_model import CatheterConfig

FloatArray = NDArray[np.float64]

#: The Vana-Owen turning radius asked of OMPL, in units of ``r_min``. Its curves meet
#: ``1 / rho`` in theory, but ``interpolate`` samples the horizontal and the vertical curve at the
#: same fraction of their lengths, so the sampled points bend up to ~2% more (measured on the
#: built-in anatomies); 5% more radius keeps the sampled path within ``1 / r_min``.
RADIUS_FACTOR = 1.05
#: Largest |pitch| of a state, rad: headings within 80 deg of the planning plane (the Vana-Owen
#: curves are singular at 90 deg).
MAX_PITCH = math.radians(80.0)
#: Largest tilt of a sampled heading from the local centerline direction, rad.
SAMPLE_TILT = math.radians(35.0)
#: Nearest nodes (by distance) whose curve lengths are compared when extending a tree.
NEAREST_CANDIDATES = 4
#: Nodes of the other tree a new node tries to join directly (nearest by distance).
JOIN_CANDIDATES = 6
#: Probability that an iteration adds a goal state to the goal tree rather than extending.
GOAL_SAMPLE_RATE = 0.05
#: Default search budget of one plan, iterations (:attr:`RrtConfig.max_iterations`). Measured
#: with the budget alone (60 s limit; 15 start x target pairs x seeds 0-2,
#: docs/reports/rrt.md): 1000 iterations plan 39/45 (default) and 37/45 (elongated), what the
#: former 1 s wall-clock limit gave, and a search that uses all of them takes ~0.6-0.9 s of one
#: core (the median plan 50-130 ms); 2000 would add 2 elongated plans for twice the time of a
#: failed search.
MAX_ITERATIONS_DEFAULT = 1000
#: Install command named when the OMPL bindings are missing.
INSTALL_HINT = "scripts/ws pip install ompl==2.0.1"


@dataclass(frozen=True)
class RrtConfig:
    """Settings of the curvature-constrained RRT (the planner node's ``rrt_*`` parameters)."""

    max_iterations: int = MAX_ITERATIONS_DEFAULT
    """Search iterations of one plan (tree extensions and goal states added), the
    deterministic budget: the result depends on it, the seed and the rest of the configuration,
    never on the host; [1, 1000000]."""
    time_limit_s: float = 1.0
    """Wall-time bound of the search, s; (0, 60]. The real-time safety bound: a plan it cuts
    before ``max_iterations`` depends on the machine's speed and load. Use a generous limit
    (e.g. 30 s) where results must be reproducible."""
    seed: int = 0
    """Seed of every random draw of a plan (the same seed gives the same path); [0, 2^31 - 1]."""
    clearance_margin: float = 0.0005
    """Clearance from the wall beyond the catheter radius along the whole path, m; [0, 5 mm]."""
    range: float = 0.02
    """Longest curve one extension adds to a tree, m; [2 mm, 0.2 m]."""
    resolution: float = 0.0005
    """Arc-length spacing of the validity checks along a curve (and of the output), m;
    [0.1 mm, 2 mm]. The checked clearance is raised by half of it (module docstring)."""

    def __post_init__(self) -> None:
        for name, low, high, low_open in (("time_limit_s", 0.0, 60.0, True),
                                          ("clearance_margin", 0.0, 0.005, False),
                                          ("range", 0.002, 0.2, False),
                                          ("resolution", 1e-4, 0.002, False)):
            value = getattr(self, name)
            ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
                  and math.isfinite(value) and (value > low if low_open else value >= low)
                  and value <= high)
            if not ok:
                raise ValueError(f"{name} must be in {'(' if low_open else '['}{low}, {high}], "
                                 f"found {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) \
                or not 0 <= self.seed <= 2**31 - 1:
            raise ValueError(f"seed must be an int in [0, 2147483647], found {self.seed!r}")
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) \
                or not 1 <= self.max_iterations <= 1_000_000:
            raise ValueError(f"max_iterations must be an int in [1, 1000000], "
                             f"found {self.max_iterations!r}")


@dataclass(frozen=True)
class Lumen:
    """What the RRT needs of the anatomy (built by :meth:`Planner` from its model world)."""

    distance: Callable[[FloatArray, float], FloatArray]
    """``(points (P, 3), max_dist) -> (P,)`` unsigned distance to the wall, inf beyond
    ``max_dist`` (the wall's own query)."""
    contains: Callable[[FloatArray], NDArray[np.bool_]]
    """Lumen test of (N, 3) points."""
    centerlines: dict[str, FloatArray]
    """Branch name -> (N, 3) Voronoi centerline from the descending aorta to the ostium, m."""
    ostia: dict[str, FloatArray]
    """Branch name -> (3,) coronary ostium, m."""
    exit_discs: FloatArray
    """(D, 7) the open cuts (:attr:`cgail_sim.anatomy.Anatomy.exit_discs`)."""
    bbox_low: FloatArray
    """(3,) lower corner of the region the tip may visit, m."""
    bbox_high: FloatArray
    """(3,) upper corner, m."""


@dataclass(frozen=True)
class RrtPath:
    """A path found by :class:`RrtPlanner`."""

    points: FloatArray
    """(M, 3) positions along the joined curves every ``resolution``, start first, m."""
    knots: FloatArray
    """(K, 3) the tree states the curves join (after shortcutting), m."""
    headings: FloatArray
    """(K, 3) unit headings at the knots."""
    iterations: int
    """Search iterations until the trees joined (at most ``max_iterations``)."""
    nodes: int
    """Nodes in both trees when they joined."""
    elapsed_s: float
    """Wall time of the plan, s."""


def _import_ompl() -> tuple[Any, Any]:
    try:
        from ompl import base as ob
        from ompl import util as ou
    except ImportError as exc:  # pragma: no cover - the requirement pins it
        raise ImportError(f"planner_type 'rrt' needs OMPL's Python bindings ({exc}); install "
                          f"them with: {INSTALL_HINT}") from None
    ou.setLogLevel(ou.LOG_ERROR)
    return ob, ou


class _Frame:
    """The planning frame: origin and rows ``(e1, e2, n)``; ``n`` the normal of the best-fit
    plane of a centerline (its smallest principal axis)."""

    def __init__(self, line: FloatArray) -> None:
        self.origin = line.mean(axis=0)
        _, _, vt = np.linalg.svd(line - self.origin)
        if float(np.linalg.det(vt)) < 0.0:
            vt[2] = -vt[2]
        self.rot = vt

    def to_local(self, p: FloatArray) -> FloatArray:
        return (np.asarray(p) - self.origin) @ self.rot.T

    def to_world(self, x: FloatArray) -> FloatArray:
        return np.asarray(x) @ self.rot + self.origin


class RrtPlanner:
    """Bi-directional curvature-constrained RRT in the lumen (module docstring).

    Args:
        config: search settings.
        catheter: the catheter model (``r_min = segment_length / theta_max``, radius).
        lumen: the anatomy's geometry queries.

    Raises:
        ImportError: OMPL's bindings are missing (the message gives the install command).
    """

    def __init__(self, config: RrtConfig, catheter: CatheterConfig, lumen: Lumen) -> None:
        self.config = config
        self.catheter = catheter
        self.lumen = lumen
        self.r_min = catheter.segment_length / catheter.theta_max
        #: Distance to the wall a checked state needs, m.
        self.required = catheter.radius + config.clearance_margin + 0.5 * config.resolution
        self._ob, _ = _import_ompl()
        self._frames: dict[str, _Frame] = {}
        # local lumen radius along each centerline (distance of its points to the wall)
        self._radii = {b: np.minimum(np.asarray(lumen.distance(np.ascontiguousarray(line), 0.05)),
                                     0.05)
                       for b, line in lumen.centerlines.items()}

    # ------------------------------------------------------------------ geometry
    def branch_for(self, goal: FloatArray) -> str:
        """The branch whose coronary ostium is nearest ``goal``."""
        ostia = self.lumen.ostia
        return min(ostia, key=lambda b: float(np.linalg.norm(goal - ostia[b])))

    def clearance(self, points: FloatArray) -> FloatArray:
        """(P,) distance of each point to the wall, m (capped at 50 mm)."""
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        return np.minimum(np.asarray(self.lumen.distance(pts, 0.05)), 0.05)

    def _space(self, frame: _Frame) -> tuple[Any, Any, Callable[[Any], bool]]:
        """A Vana-Owen space in ``frame`` with its space information and validity check."""
        ob = self._ob
        lum = self.lumen
        space = ob.VanaOwenStateSpace(RADIUS_FACTOR * self.r_min, MAX_PITCH)
        corners = np.array([[x, y, z] for x in (lum.bbox_low[0], lum.bbox_high[0])
                            for y in (lum.bbox_low[1], lum.bbox_high[1])
                            for z in (lum.bbox_low[2], lum.bbox_high[2])])
        local = frame.to_local(corners)
        bounds = ob.RealVectorBounds(3)
        for k in range(3):
            bounds.setLow(k, float(local[:, k].min()))
            bounds.setHigh(k, float(local[:, k].max()))
        space.setBounds(bounds)
        si = ob.SpaceInformation(space)
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = frame.rot.tolist()
        ox, oy, oz = frame.origin.tolist()
        discs = np.ascontiguousarray(lum.exit_discs, dtype=np.float64)
        slab = 2.0 * self.config.resolution
        lx, ly, lz = lum.bbox_low.tolist()
        hx, hy, hz = lum.bbox_high.tolist()
        need = self.required
        distance = lum.distance
        query = np.empty((1, 3))

        def valid(state: Any) -> bool:
            a, b, c = state[0], state[1], state[2]
            x = ox + a * r00 + b * r10 + c * r20
            y = oy + a * r01 + b * r11 + c * r21
            z = oz + a * r02 + b * r12 + c * r22
            if in_exit_slab(x, y, z, discs, slab) >= 0 \
                    or not (lx <= x <= hx and ly <= y <= hy and lz <= z <= hz):
                return False
            query[0, 0], query[0, 1], query[0, 2] = x, y, z
            return bool(distance(query, need)[0] >= need)

        si.setStateValidityChecker(valid)
        si.setMotionValidator(ob.VanaOwenMotionValidator(si))
        si.setStateValidityCheckingResolution(self.config.resolution
                                              / space.getMaximumExtent())
        si.setup()
        return space, si, valid

    # ------------------------------------------------------------------ planning
    def plan(self, position: FloatArray, rotation: FloatArray, goal: FloatArray,
             goal_tolerance: float) -> RrtPath:
        """A curvature-bounded path from the tip pose ``[rotation | position]`` to ``goal``.

        Args:
            position: (3,) tip position, m.
            rotation: (3, 3) tip rotation (heading ``rotation[:, 1]``).
            goal: (3,) goal position, m (heading free).
            goal_tolerance: the path ends within this of the goal (half of it at most), m.

        Raises:
            InvalidInputError: the start pose lacks clearance or leaves the planning frame's
                pitch range.
            NoPathError: the trees did not join within ``max_iterations`` iterations or
                ``time_limit_s`` (one line naming the limit that ran out; :attr:`~cgail_planner.
                core.errors.NoPathError.reason` ``max_iterations`` or ``time_limit``, ``step``
                the iterations used).
        """
        t0 = time.perf_counter()
        cfg = self.config
        deadline = t0 + cfg.time_limit_s
        rng = np.random.default_rng(cfg.seed)
        p0 = np.asarray(position, dtype=np.float64)
        h0 = np.asarray(rotation, dtype=np.float64)[:, 1]
        g = np.asarray(goal, dtype=np.float64)
        branch = self.branch_for(g)
        frame = self._frames.get(branch)
        if frame is None:
            frame = self._frames[branch] = _Frame(self.lumen.centerlines[branch])
        space, si, valid = self._space(frame)
        search = _Search(self, frame, space, si, valid, rng, branch)
        start = search.state(p0, h0)
        clear0 = float(self.clearance(p0)[0])
        if not (bool(self.lumen.contains(p0[None])[0]) and valid(start)):
            raise InvalidInputError(
                f"rrt start: expected the tip at least {self.required * 1e3:.2f} mm from the "
                f"wall inside the lumen, found {clear0 * 1e3:.2f} mm")
        pitch = math.asin(max(-1.0, min(1.0, float(frame.rot[2] @ h0))))
        if abs(pitch) > MAX_PITCH:
            raise InvalidInputError(
                f"rrt start: expected a heading within {math.degrees(MAX_PITCH):.0f} deg of the "
                f"planning plane, found {math.degrees(pitch):.0f} deg")
        joined = search.run(start, p0, g, goal_tolerance, deadline, cfg.max_iterations)
        if joined is None:
            if search.iterations >= cfg.max_iterations:
                limit, what = "max_iterations", f"max_iterations {cfg.max_iterations}"
            else:
                limit, what = "time_limit", f"time_limit_s {cfg.time_limit_s:g} s"
            raise NoPathError(
                f"rrt found no path within {what} ({search.iterations} iterations, "
                f"{search.size} nodes, seed {cfg.seed})", None, limit, search.iterations)
        states = search.shortcut(joined)
        points = search.dense(states)
        knots = np.array([search.position(s) for s in states])
        headings = np.array([search.heading(s) for s in states])
        return RrtPath(points=points, knots=knots, headings=headings,
                       iterations=search.iterations, nodes=search.size,
                       elapsed_s=time.perf_counter() - t0)


class _Tree:
    """Nodes (OMPL states), their positions and parents."""

    def __init__(self) -> None:
        self.states: list[Any] = []
        self.parent: list[int] = []
        self._pos = np.empty((64, 3))

    def add(self, state: Any, position: FloatArray, parent: int) -> int:
        n = len(self.states)
        if n == len(self._pos):
            self._pos = np.vstack([self._pos, np.empty_like(self._pos)])
        self._pos[n] = position
        self.states.append(state)
        self.parent.append(parent)
        return n

    @property
    def positions(self) -> FloatArray:
        return self._pos[:len(self.states)]

    def nearest(self, p: FloatArray, k: int) -> NDArray[np.int64]:
        d2 = np.einsum("ij,ij->i", self.positions - p, self.positions - p)
        k = min(k, len(d2))
        idx = np.argpartition(d2, k - 1)[:k] if k < len(d2) else np.arange(len(d2))
        return idx[np.argsort(d2[idx], kind="stable")]

    def branch(self, i: int) -> list[Any]:
        """States from the root to node ``i``."""
        out = []
        while i >= 0:
            out.append(self.states[i])
            i = self.parent[i]
        return out[::-1]


class _Search:
    """One plan's bi-directional search (state of :meth:`RrtPlanner.plan`)."""

    def __init__(self, planner: RrtPlanner, frame: _Frame, space: Any, si: Any,
                 valid: Callable[[Any], bool], rng: np.random.Generator, branch: str) -> None:
        self.planner, self.frame, self.space, self.si = planner, frame, space, si
        self.valid, self.rng = valid, rng
        self.line = planner.lumen.centerlines[branch]
        self.radii = planner._radii[branch]
        tangents = np.gradient(self.line, axis=0)
        self.tangents = tangents / np.linalg.norm(tangents, axis=1)[:, None]
        self.iterations = 0
        self.start_tree, self.goal_tree = _Tree(), _Tree()

    @property
    def size(self) -> int:
        return len(self.start_tree.states) + len(self.goal_tree.states)

    # states <-> world
    def state(self, p: FloatArray, h: FloatArray) -> Any:
        s = self.space.allocState()
        x = self.frame.to_local(p)
        d = self.frame.rot @ (h / np.linalg.norm(h))
        s[0], s[1], s[2] = float(x[0]), float(x[1]), float(x[2])
        s.setYaw(math.atan2(float(d[1]), float(d[0])))
        s.setPitch(max(-MAX_PITCH, min(MAX_PITCH, math.asin(max(-1.0, min(1.0, float(d[2])))))))
        return s

    def position(self, s: Any) -> FloatArray:
        return self.frame.to_world(np.array([s[0], s[1], s[2]]))

    def heading(self, s: Any) -> FloatArray:
        yaw, pitch = s.getYaw(), s.getPitch()
        d = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw),
                      math.sin(pitch)])
        return d @ self.frame.rot

    # sampling
    def _index(self, p: FloatArray) -> int:
        return int(np.argmin(np.linalg.norm(self.line - p, axis=1)))

    def _tilted(self, t: FloatArray) -> FloatArray:
        """``t`` tilted by a random angle up to :data:`SAMPLE_TILT` in a random direction."""
        u = self.rng.normal(size=3)
        u -= (u @ t) * t
        u /= max(float(np.linalg.norm(u)), 1e-12)
        a = SAMPLE_TILT * math.sqrt(float(self.rng.uniform()))
        return math.cos(a) * t + math.sin(a) * u

    def sample(self) -> Any:
        """A random state in the lumen around the centerline between the start and the goal."""
        i = int(self.rng.integers(self.lo, self.hi + 1))
        t = self.tangents[i]
        u = self.rng.normal(size=3)
        u -= (u @ t) * t
        u /= max(float(np.linalg.norm(u)), 1e-12)
        room = max(float(self.radii[i]) - self.planner.required, 0.0)
        p = self.line[i] + room * math.sqrt(float(self.rng.uniform())) * u
        return self.state(p, self._tilted(t))

    def goal_state(self) -> tuple[Any, FloatArray] | None:
        """A valid goal state: the goal (or a point within half the tolerance) with a heading
        tilted from the centerline's direction there."""
        for _ in range(20):
            p = self.goal
            if not self.goal_clear:
                u = self.rng.normal(size=3)
                u /= np.linalg.norm(u)
                p = self.goal + 0.5 * self.tolerance * float(self.rng.uniform()) ** (1 / 3) * u
                if not bool(self.planner.lumen.contains(p[None])[0]):
                    continue
            s = self.state(p, self._tilted(self.tangents[self.goal_index]))
            if self.valid(s):
                return s, p
        return None

    # search
    def run(self, start: Any, p0: FloatArray, goal: FloatArray, tolerance: float,
            deadline: float, max_iterations: int) -> list[Any] | None:
        """Grow both trees until they join (the states from the start to a goal state), for
        at most ``max_iterations`` iterations and until ``deadline`` (``perf_counter``)."""
        self.goal, self.tolerance = goal, tolerance
        i0, self.goal_index = self._index(p0), self._index(goal)
        self.lo, self.hi = min(i0, self.goal_index), max(i0, self.goal_index)
        self.hi = min(self.hi + 3, len(self.line) - 1)
        self.goal_clear = bool(self.planner.lumen.contains(goal[None])[0]) and \
            float(self.planner.clearance(goal)[0]) >= self.planner.required
        self.start_tree.add(start, p0, -1)
        rng = self.rng
        forward = True
        while self.iterations < max_iterations and time.perf_counter() < deadline:
            self.iterations += 1
            if not self.goal_tree.states or rng.uniform() < GOAL_SAMPLE_RATE:
                found = self.goal_state()
                if found is not None:
                    j = self.goal_tree.add(found[0], found[1], -1)
                    path = self._join(self.goal_tree, j, forward=False)
                    if path is not None:
                        return path
                continue
            tree = self.start_tree if forward else self.goal_tree
            new = self._extend(tree, self.sample(), forward)
            if new is not None:
                path = self._join(tree, new, forward)
                if path is not None:
                    return path
            forward = not forward
        return None

    def _extend(self, tree: _Tree, target: Any, forward: bool) -> int | None:
        """Grow ``tree`` towards ``target`` along a curve of at most ``range``: the new node,
        or None when that curve is blocked. The start tree grows forward (curves from its
        nodes), the goal tree backward (curves into its nodes)."""
        space, si = self.space, self.si
        p = self.position(target)
        best, best_len = -1, math.inf
        for i in tree.nearest(p, NEAREST_CANDIDATES):
            a, b = (tree.states[i], target) if forward else (target, tree.states[i])
            length = space.distance(a, b)
            if length < best_len:
                best, best_len = int(i), length
        if best < 0 or not math.isfinite(best_len):
            return None
        node = tree.states[best]
        step = self.planner.config.range
        new = space.allocState()
        if best_len <= step:
            space.copyState(new, target)
        elif forward:
            space.interpolate(node, target, step / best_len, new)
        else:
            space.interpolate(target, node, 1.0 - step / best_len, new)
        ok = si.checkMotion(node, new) if forward else si.checkMotion(new, node)
        if not ok:
            return None
        return tree.add(new, self.position(new), best)

    def _join(self, tree: _Tree, i: int, forward: bool) -> list[Any] | None:
        """Join node ``i`` of ``tree`` to one of the :data:`JOIN_CANDIDATES` nearest nodes of
        the other tree with one curve; the start-to-goal states when it works.

        (A stepwise connect, as in RRT-Connect, stalls here: a Vana-Owen curve is found by a
        local search over radii, so the curve from a point part-way along it is not always
        shorter than the rest of it.)
        """
        other = self.goal_tree if forward else self.start_tree
        if not other.states:
            return None
        s = tree.states[i]
        for j in other.nearest(tree.positions[i], JOIN_CANDIDATES):
            t = other.states[int(j)]
            ok = self.si.checkMotion(s, t) if forward else self.si.checkMotion(t, s)
            if ok:
                a, b = (tree.branch(i), other.branch(int(j))) if forward \
                    else (other.branch(int(j)), tree.branch(i))
                return a + b[::-1]
        return None

    def shortcut(self, states: list[Any]) -> list[Any]:
        """Greedy shortcutting: from each kept state, the furthest later state one valid curve
        reaches (deterministic; at most K^2 / 2 curve checks for K states)."""
        out = [states[0]]
        i = 0
        while i < len(states) - 1:
            j = i + 1
            for k in range(len(states) - 1, i + 1, -1):
                if self.si.checkMotion(states[i], states[k]):
                    j = k
                    break
            out.append(states[j])
            i = j
        return out

    def dense(self, states: list[Any]) -> FloatArray:
        """Positions along the curves joining ``states`` every ``resolution``."""
        space = self.space
        res = self.planner.config.resolution
        tmp = space.allocState()
        pts = [self.position(states[0])]
        for a, b in itertools.pairwise(states):
            n = max(1, math.ceil(space.distance(a, b) / res))
            for k in range(1, n + 1):
                space.interpolate(a, b, k / n, tmp)
                pts.append(self.position(tmp))
        return np.array(pts)

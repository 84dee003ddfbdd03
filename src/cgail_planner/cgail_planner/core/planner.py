"""Whole-path planning: roll a policy out in the simulator model, or follow the centerline.

numpy and numba (the BVH of :mod:`cgail_planner.sim.wall`, an injected policy callable); no
rclpy and no torch. Used by :mod:`cgail_planner.nodes.planner_node` with
:class:`cgail_planner.learning.onnx_policy.OnnxPolicy`.

**Speed.** When the policy is a numba :class:`~cgail_planner.core.mlp.MlpProgram` (an
``OnnxPolicy`` on its ``mlp`` backend) and the wall a simulator wall, the whole rollout is one
numba call (:mod:`cgail_planner.core.rollout_kernel`, ~20 us per step, mostly the 25-ray cast)
that gives the same path as the Python loop :meth:`Planner.rollout_reference` (~85 us per step
with onnxruntime), which remains the rollout for any other policy or wall. The kernel is loaded
(compiled, without a numba cache) when the planner is built, not in the first plan.

**C-GAIL planner** (``planner_type='cgail'``): from the current tip pose ``[R | p]`` the policy
is rolled out in the model of the anatomy, exactly with the environment's observation
(:data:`cgail_planner.sim.env.OBS_LAYOUT`: position relative to the anatomy's bounding-box centre
over ``position_scale``, the tip axes, ``u`` and ``v`` towards the goal over ``d_max``, 25 ray
hits over ``ray_length``) and its follow-the-leader kinematics (:mod:`cgail_planner.sim.catheter`:
``R <- R Rx(alpha) Rz(gamma)``, ``p <- p + dl y_A`` with ``|alpha|, |gamma| <= theta_max dl / L``,
``dl <= v_max dt``). The rollout succeeds when the tip comes within ``goal_tolerance`` of the
goal (the goal is then appended as the last point); it fails on a wall contact (a ray shorter than
the catheter radius: the tip sphere touches the wall), on leaving the anatomy's bounding box, or
after ``max_rollout_steps``. In dynamic mode the rays are cast against the wall's current
(deformed) shape, frozen for the rollout. Retraction (``dl < 0``) slides back along the rolled-out
body, as in the simulator.

**Centerline planner** (``planner_type='centerline'``, the traditional baseline): the Voronoi
centerline of the branch whose coronary ostium is nearest the goal, from the tip's projection on
it to the centerline point nearest the goal (cut at the target), then the goal itself, starting at
the tip.

Both raw paths are B-spline fitted and resampled at ``path_spacing``
(:func:`cgail_planner.core.path_fit.fit_path`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import math
import time
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from cgail_planner.core.mlp import MlpProgram
from cgail_planner.core.path_fit import fit_path, PathFitConfig, PathFitError

FloatArray = NDArray[np.float64]

PLANNER_TYPES = ("cgail", "centerline")
MODES = ("static", "dynamic")


class PlannerError(ValueError):
    """Planning refused or failed; the message says what was wrong and what was expected."""


class InvalidInputError(PlannerError):
    """A pose or goal is unusable (NaN/inf, not a rotation, goal outside the lumen)."""


class NoPathError(PlannerError):
    """The planner ran but found no path to the goal (rollout collided, exited or timed out).

    Args:
        message: what happened.
        points: (K, 3) the tip positions rolled out before the failure, m (None when the
            failure is not a rollout's); kept as :attr:`points` for diagnostics.
    """

    def __init__(self, message: str, points: FloatArray | None = None) -> None:
        super().__init__(message)
        self.points = points


class RayWall(Protocol):
    """What the rollout needs from a wall (:class:`cgail_planner.sim.wall.StaticWall`)."""

    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                ) -> np.ndarray:
        """(R,) hit distances along unit directions, ``max_dist`` when nothing is hit."""


Policy = Callable[[NDArray[np.float32]], NDArray[np.float32]]


@dataclass(frozen=True)
class PlannerConfig:
    """Planner settings (the node's parameters of the same names)."""

    planner_type: str = "cgail"
    """``cgail`` (ONNX policy rollout) or ``centerline`` (the traditional baseline)."""
    goal_tolerance: float = 0.010
    """The rollout reached the goal within this distance, m (paper epsilon 10 mm); (0, 0.05]."""
    max_rollout_steps: int = 1500
    """Steps of the policy rollout before giving up (0.5 mm each at full insertion); [1, 1e5]."""
    path_spacing: float = 0.001
    """Arc-length spacing of the published (B-spline fitted, resampled) path, m; [0.1 mm, 1 cm]."""
    fit_stride: int = 4
    """Every ``fit_stride``-th rollout point is a B-spline knot (ends always kept); [1, 50]."""
    theta_max: float = math.pi / 2.0
    """Maximal bending angle of the rollout kinematics, rad (paper 90 deg); (0, pi]."""
    segment_length: float = 0.050
    """Steerable segment length L, m (paper 50 mm); [1 mm, 0.5 m]."""
    max_insertion_speed: float = 0.005
    """Insertion speed of the rollout at full action, m/s (paper 5 mm/s); (0, 0.1]."""
    dt: float = 0.1
    """Rollout time step, s (the environment's; 0.5 mm per step); [1 ms, 2 s]."""
    outer_diameter: float = 0.007
    """Catheter outer diameter, m (7 mm): a ray shorter than its radius is a contact; (0, 0.02]."""
    ray_length: float = 0.040
    """Observation ray length, m (the environment's 40 mm); [5 mm, 0.2 m]."""
    position_scale: float = 0.15
    """Observed position scale, m (the environment's 0.15 m); [1 cm, 10 m]."""

    def __post_init__(self) -> None:
        if self.planner_type not in PLANNER_TYPES:
            raise ValueError(f"planner_type must be one of {PLANNER_TYPES}, found "
                             f"{self.planner_type!r}")
        for name, low, high in (("goal_tolerance", 0.0, 0.05), ("theta_max", 0.0, math.pi),
                                ("max_insertion_speed", 0.0, 0.1),
                                ("outer_diameter", 0.0, 0.02)):
            _check(name, getattr(self, name), low, high, low_open=True)
        for name, low, high in (("path_spacing", 1e-4, 0.01), ("segment_length", 1e-3, 0.5),
                                ("dt", 1e-3, 2.0), ("ray_length", 0.005, 0.2),
                                ("position_scale", 0.01, 10.0)):
            _check(name, getattr(self, name), low, high)
        for name, ilow, ihigh in (("max_rollout_steps", 1, 100_000), ("fit_stride", 1, 50)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) \
                    or not ilow <= value <= ihigh:
                raise ValueError(f"{name} must be an int in [{ilow}, {ihigh}], found {value!r}")


def _check(name: str, value: float, low: float, high: float, low_open: bool = False) -> None:
    ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
          and math.isfinite(value) and (value > low if low_open else value >= low)
          and value <= high)
    if not ok:
        raise ValueError(f"{name} must be in {'(' if low_open else '['}{low}, {high}], found "
                         f"{value!r}")


@dataclass(frozen=True)
class PlanResult:
    """A planned path."""

    path: FloatArray
    """(M, 3) B-spline fitted path resampled every ``path_spacing``, tip first, goal last, m."""
    raw: FloatArray
    """(K, 3) the raw rollout (or centerline) points the spline was fitted to, m."""
    planner_type: str
    """Which planner made it."""
    steps: int
    """Rollout steps (0 for the centerline)."""
    elapsed_s: float
    """Wall time spent planning, s."""


@dataclass(frozen=True)
class ModelWorld:
    """The model of the anatomy the planner plans in (from :func:`sim.scenarios.load_world`)."""

    origin: FloatArray
    """(3,) observation origin: the anatomy's bounding-box centre, m."""
    d_max: float
    """Distance normaliser of ``u`` and ``v``, m."""
    bbox_low: FloatArray
    """(3,) lower corner of the region a rollout may visit, m."""
    bbox_high: FloatArray
    """(3,) upper corner, m."""
    centerlines: dict[str, FloatArray]
    """Branch name -> (N, 3) Voronoi centerline from the descending aorta to the ostium, m."""
    ostia: dict[str, FloatArray]
    """Branch name -> (3,) coronary ostium position, m."""
    contains: Callable[[FloatArray], NDArray[np.bool_]]
    """Lumen test of (N, 3) points."""


def model_world_from_sim(world: object) -> ModelWorld:
    """Build a :class:`ModelWorld` from a :class:`cgail_planner.sim.scenarios.World`."""
    anatomy = world.anatomy  # type: ignore[attr-defined]
    sc = world.scenarios  # type: ignore[attr-defined]
    verts = np.asarray(anatomy.vertices, dtype=np.float64)
    return ModelWorld(
        origin=np.asarray(sc.origin, dtype=np.float64), d_max=float(sc.d_max),
        bbox_low=verts.min(axis=0) - 0.01, bbox_high=verts.max(axis=0) + 0.01,
        centerlines={b: np.asarray(c.points, dtype=np.float64)
                     for b, c in world.centerlines.items()},  # type: ignore[attr-defined]
        ostia={b: np.asarray(p, dtype=np.float64) for b, p in anatomy.ostia.items()},
        contains=anatomy.contains)


def validate_pose(position: FloatArray, rotation: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Check a tip pose: finite position, a proper rotation matrix (tolerance 1e-3).

    Raises:
        InvalidInputError: naming what is wrong.
    """
    p = np.asarray(position, dtype=np.float64)
    r = np.asarray(rotation, dtype=np.float64)
    if p.shape != (3,) or r.shape != (3, 3):
        raise InvalidInputError(f"tip pose must be a (3,) position and a (3, 3) rotation, found "
                                f"{p.shape} and {r.shape}")
    if not (np.isfinite(p).all() and np.isfinite(r).all()):
        raise InvalidInputError(f"tip pose must be finite, found position {p.tolist()} "
                                "or a rotation with NaN/inf")
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > 1e-3 or np.linalg.det(r) < 0.0:
        raise InvalidInputError(f"tip orientation must be a rotation (unit quaternion), found "
                                f"orthogonality error {err:.3g}")
    return p, r


def rotation_from_quaternion(x: float, y: float, z: float, w: float) -> FloatArray:
    """Rotation matrix of a unit quaternion ``(x, y, z, w)``.

    Raises:
        InvalidInputError: NaN/inf or a norm not within 1e-3 of 1.
    """
    q = np.array([x, y, z, w], dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not math.isfinite(n) or abs(n - 1.0) > 1e-3:
        raise InvalidInputError(f"orientation must be a unit quaternion, found {q.tolist()} "
                                f"(norm {n:.4g})")
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quaternion_from_rotation(r: FloatArray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix (Shepperd's method)."""
    m = np.asarray(r, dtype=np.float64)
    tr = float(m[0, 0] + m[1, 1] + m[2, 2])
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)
    n = math.sqrt(sum(v * v for v in q))
    return (float(q[0] / n), float(q[1] / n), float(q[2] / n), float(q[3] / n))


def _wall_bvh(wall: object) -> tuple[np.ndarray, ...] | None:
    """The arrays the numba ray kernel needs, for a simulator wall, else None.

    A :class:`cgail_planner.sim.wall.StaticWall` (or :class:`~cgail_planner.sim.wall.
    DeformableWall`) casts its rays on a :class:`cgail_planner.sim.raycast.WallBVH`; the wall is
    brought up to date first by a one-ray cast (a deformable wall refits its tree lazily), then
    the tree is read as ``WallBVH.raycast`` passes it to its kernel: ``(vertices, faces, order,
    node_min, node_max, left, right, start, count)``.
    """
    from cgail_planner.sim.raycast import WallBVH
    from cgail_planner.sim.wall import StaticWall

    if not isinstance(wall, StaticWall):
        return None
    bvh = wall.bvh
    if not isinstance(bvh, WallBVH):
        return None
    wall.raycast(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]), 1e-3)
    nmin, nmax, left, right, start, count, order, _fitted, _n_nodes = bvh.tree
    return (bvh.vertices, bvh.faces, order, nmin, nmax, left, right, start, count)


def pose_observation(p: FloatArray, r: FloatArray, goal: FloatArray, hits: FloatArray,
                     origin: FloatArray, d_max: float, position_scale: float,
                     ray_length: float) -> NDArray[np.float32]:
    """The environment's observation (:data:`cgail_planner.sim.env.OBS_LAYOUT`) of one tip
    pose ``[r | p]`` towards ``goal``, with the ray hit distances ``hits`` (m) cast from it.

    The single-pose form of :meth:`cgail_planner.sim.env.NavEngine.observe`, shared by the
    planner and the evaluation's simulated tracker.
    """
    obs = np.empty(16 + len(hits), dtype=np.float32)
    obs[0:3] = (p - origin) / position_scale
    obs[3:12] = r.T.reshape(9)
    vec = (goal - p) / d_max
    obs[12] = math.sqrt(float(vec @ vec))
    obs[13:16] = vec
    obs[16:] = hits
    obs[16:] *= 1.0 / ray_length
    np.clip(obs[16:], 0.0, 1.0, out=obs[16:])
    return obs


def _bend_rotation(alpha: float, gamma: float) -> FloatArray:
    ca, sa, cg, sg = math.cos(alpha), math.sin(alpha), math.cos(gamma), math.sin(gamma)
    return np.array([[cg, -sg, 0.0], [ca * sg, ca * cg, -sa], [sa * sg, sa * cg, ca]])


class Planner:
    """Plans whole paths from a tip pose to a goal (module docstring).

    Args:
        config: planner settings.
        world: the anatomy model.
        wall: ray-cast wall (static, or the deformable wall whose current shape is used).
        policy: ``obs (41,) float32 -> action (3,)`` in [-1, 1]; required for ``cgail``.
        ray_directions: (R, 3) ray set in the tip frame (:data:`cgail_planner.sim.env.
            RAY_DIRECTIONS`).
        obs_dim: the policy's observation size (checked against ``16 + R``).

    Raises:
        ValueError: ``cgail`` without a policy, or an observation size mismatch.
    """

    def __init__(self, config: PlannerConfig, world: ModelWorld, wall: RayWall,
                 policy: Policy | None, ray_directions: FloatArray,
                 obs_dim: int | None = None) -> None:
        self.config = config
        self.world = world
        self.wall = wall
        self.policy = policy
        self.rays = np.ascontiguousarray(ray_directions, dtype=np.float64)
        self.obs_dim = 16 + len(self.rays)
        if config.planner_type == "cgail" and policy is None:
            raise ValueError("planner_type 'cgail' needs a policy, found None")
        if obs_dim is not None and obs_dim != self.obs_dim:
            raise ValueError(f"policy observation size must be {self.obs_dim} (16 + "
                             f"{len(self.rays)} rays), found {obs_dim}")
        self._fit = PathFitConfig(spacing=config.path_spacing)
        program = policy if isinstance(policy, MlpProgram) else getattr(policy, "mlp", None)
        self._program: MlpProgram | None = None
        if isinstance(program, MlpProgram) and program.in_dim == self.obs_dim \
                and program.out_dim == 3:
            self._program = program
            bvh = _wall_bvh(wall)
            if bvh is not None:
                # load (or, without a numba cache, compile: seconds) the kernel now rather
                # than in the first plan: a one-step rollout from the observation origin
                origin = np.asarray(world.origin, dtype=np.float64)
                self._run_kernel(program, bvh, origin, np.eye(3), origin + 1.0, 1)

    # ------------------------------------------------------------------ validation
    def validate_goal(self, goal: FloatArray) -> FloatArray:
        """Check that the goal is finite and inside the lumen.

        Raises:
            InvalidInputError: naming the goal and the reason.
        """
        g = np.asarray(goal, dtype=np.float64)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise InvalidInputError(f"goal must be a finite (3,) position, found {g.tolist()}")
        if not bool(np.asarray(self.world.contains(g[None]))[0]):
            raise InvalidInputError(
                f"goal must lie inside the lumen of the anatomy, found "
                f"({g[0]:.4f}, {g[1]:.4f}, {g[2]:.4f}) m outside it")
        return g

    # ------------------------------------------------------------------ planning
    def plan(self, position: FloatArray, rotation: FloatArray, goal: FloatArray) -> PlanResult:
        """Plan from the tip pose ``[rotation | position]`` to ``goal``.

        Raises:
            InvalidInputError: bad pose or goal.
            NoPathError: no path found.
        """
        t0 = time.perf_counter()
        p, r = validate_pose(position, rotation)
        g = self.validate_goal(goal)
        if self.config.planner_type == "cgail":
            raw, steps = self.rollout(p, r, g)
        else:
            raw, steps = self.centerline_path(p, g), 0
        knots = raw[:: self.config.fit_stride]
        if not np.array_equal(knots[-1], raw[-1]):
            knots = np.vstack([knots, raw[-1:]])
        try:
            path = fit_path(knots, self._fit)
        except PathFitError as exc:
            raise NoPathError(f"{self.config.planner_type} path cannot be fitted: {exc}") \
                from None
        return PlanResult(path=path, raw=raw, planner_type=self.config.planner_type,
                          steps=steps, elapsed_s=time.perf_counter() - t0)

    def observation(self, p: FloatArray, r: FloatArray, goal: FloatArray,
                    hits: FloatArray) -> NDArray[np.float32]:
        """The environment's observation of tip pose ``[r | p]`` (layout in the module doc)."""
        cfg = self.config
        return pose_observation(p, r, goal, hits, self.world.origin, self.world.d_max,
                                cfg.position_scale, cfg.ray_length)

    @property
    def uses_kernel(self) -> bool:
        """True when :meth:`rollout` runs as one numba call (:mod:`.rollout_kernel`): the policy
        is an :class:`~cgail_planner.core.mlp.MlpProgram` (or has one as ``.mlp``, as
        :class:`~cgail_planner.learning.onnx_policy.OnnxPolicy` has) with this planner's
        observation size and 3 actions, and the wall is a simulator wall with a numba BVH."""
        return self._program is not None and _wall_bvh(self.wall) is not None

    def rollout(self, p0: FloatArray, r0: FloatArray, goal: FloatArray
                ) -> tuple[FloatArray, int]:
        """Roll the policy out from ``[r0 | p0]`` towards ``goal``.

        Runs :func:`cgail_planner.core.rollout_kernel.rollout_kernel` when
        :attr:`uses_kernel`, else :meth:`rollout_reference`; both give the same path.

        Returns:
            ``(points, steps)``: the tip positions from ``p0`` to ``goal`` (appended).

        Raises:
            NoPathError: contact, exit or step limit before reaching the goal.
        """
        program = self._program
        bvh = _wall_bvh(self.wall) if program is not None else None
        if program is None or bvh is None:
            return self.rollout_reference(p0, r0, goal)
        from cgail_planner.core import rollout_kernel as rk

        cfg = self.config
        goal = np.ascontiguousarray(goal, dtype=np.float64)
        status, steps, points, action = self._run_kernel(program, bvh, p0, r0, goal,
                                                         cfg.max_rollout_steps)
        p = points[-1]
        if status == rk.REACHED:
            return np.vstack([points, goal]), int(steps)
        if status == rk.TOUCHED_WALL:
            raise NoPathError(
                f"cgail rollout touched the wall after {steps} steps at "
                f"({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m, "
                f"{float(np.linalg.norm(goal - p)) * 1e3:.1f} mm from the goal", points)
        if status == rk.BAD_ACTION:
            raise NoPathError(f"policy must return 3 finite actions, found "
                              f"{action.tolist()}", points)
        if status == rk.LEFT_ANATOMY:
            raise NoPathError(f"cgail rollout left the anatomy after {steps} steps", points)
        dist = float(np.linalg.norm(goal - p))
        raise NoPathError(f"cgail rollout did not reach the goal within "
                          f"{cfg.max_rollout_steps} steps (ended {dist * 1e3:.1f} mm from it)",
                          points)

    def _run_kernel(self, program: MlpProgram, bvh: tuple[np.ndarray, ...], p0: FloatArray,
                    r0: FloatArray, goal: FloatArray, max_steps: int
                    ) -> tuple[int, int, FloatArray, FloatArray]:
        """One call of the rollout kernel: ``(status, steps, points, last action)``."""
        from cgail_planner.core import rollout_kernel as rk

        cfg = self.config
        positions = np.empty((max_steps + 1, 3))
        rotations = np.empty((max_steps + 1, 3, 3))
        action = np.zeros(3)
        kernel: Callable[..., tuple[int, int, int]] = rk.rollout_kernel
        # every scalar as a Python float/int: one compiled signature whatever the config types
        status, steps, n = kernel(
            np.ascontiguousarray(p0, dtype=np.float64), np.ascontiguousarray(r0, np.float64),
            np.ascontiguousarray(goal, dtype=np.float64), self.rays,
            np.ascontiguousarray(self.world.origin, dtype=np.float64),
            1.0 / float(cfg.position_scale), 1.0 / float(self.world.d_max),
            1.0 / float(cfg.ray_length), float(cfg.ray_length), 0.5 * float(cfg.outer_diameter),
            float(cfg.max_insertion_speed) * float(cfg.dt),
            float(cfg.theta_max) / float(cfg.segment_length), float(cfg.goal_tolerance) ** 2,
            np.ascontiguousarray(self.world.bbox_low, dtype=np.float64),
            np.ascontiguousarray(self.world.bbox_high, dtype=np.float64), int(max_steps), *bvh,
            program.ops, program.consts, program.widths, program.scratch(), program.out_reg,
            positions, rotations, action)
        return int(status), int(steps), positions[:n].copy(), action

    def rollout_reference(self, p0: FloatArray, r0: FloatArray, goal: FloatArray
                          ) -> tuple[FloatArray, int]:
        """:meth:`rollout` as a Python loop calling ``wall.raycast`` and ``policy`` per step.

        The specification of the numba kernel, and the rollout for any policy callable and
        any :class:`RayWall`. Same returns and errors as :meth:`rollout`.
        """
        cfg = self.config
        assert self.policy is not None
        radius = 0.5 * cfg.outer_diameter
        step_len = cfg.max_insertion_speed * cfg.dt
        per_len = cfg.theta_max / cfg.segment_length
        n = len(self.rays)
        positions = [p0.copy()]
        rotations = [r0.copy()]
        p, r = p0.copy(), r0.copy()
        tol2 = cfg.goal_tolerance ** 2
        origins = np.empty((n, 3))
        low = self.world.bbox_low.tolist()
        high = self.world.bbox_high.tolist()
        # the observation is filled in place (same layout as :meth:`observation`)
        obs = np.empty(self.obs_dim, dtype=np.float32)
        inv_scale = 1.0 / cfg.position_scale
        inv_dmax = 1.0 / self.world.d_max
        inv_ray = 1.0 / cfg.ray_length
        origin = self.world.origin
        gx, gy, gz = (float(v) for v in goal)
        for step in range(1, cfg.max_rollout_steps + 1):
            origins[:] = p
            hits = np.asarray(self.wall.raycast(origins, self.rays @ r.T, cfg.ray_length),
                              dtype=np.float64)
            if step > 1 and float(hits.min()) < radius:
                raise NoPathError(
                    f"cgail rollout touched the wall after {step - 1} steps at "
                    f"({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m, "
                    f"{float(np.linalg.norm(goal - p)) * 1e3:.1f} mm from the goal",
                    np.array(positions))
            x, y, z = p.tolist()
            obs[0:3] = (p - origin) * inv_scale
            obs[3:12] = r.T.reshape(9)
            vx, vy, vz = (gx - x) * inv_dmax, (gy - y) * inv_dmax, (gz - z) * inv_dmax
            obs[12] = math.sqrt(vx * vx + vy * vy + vz * vz)
            obs[13], obs[14], obs[15] = vx, vy, vz
            np.clip(hits * inv_ray, 0.0, 1.0, out=hits)
            obs[16:] = hits
            out = np.asarray(self.policy(obs)).reshape(-1).tolist()
            if len(out) != 3 or not all(math.isfinite(v) for v in out):
                raise NoPathError(f"policy must return 3 finite actions, found {out}",
                                  np.array(positions))
            a0, a1, a2 = (min(max(v, -1.0), 1.0) for v in out)
            dl = a2 * step_len
            if dl > 0.0:
                limit = per_len * dl
                r = r @ _bend_rotation(a0 * limit, a1 * limit)
                p = p + dl * r[:, 1]
                positions.append(p)
                rotations.append(r)
            elif dl < 0.0 and len(positions) > 1:
                back = -dl
                while back > 0.0 and len(positions) > 1:
                    seg = float(np.linalg.norm(positions[-1] - positions[-2]))
                    if seg <= back + 1e-12:
                        positions.pop()
                        rotations.pop()
                        back -= seg
                    else:
                        frac = back / seg
                        positions[-1] = positions[-1] + frac * (positions[-2] - positions[-1])
                        back = 0.0
                p, r = positions[-1].copy(), rotations[-1].copy()
            x, y, z = p.tolist()
            if (gx - x) ** 2 + (gy - y) ** 2 + (gz - z) ** 2 < tol2:
                return np.vstack([*positions, goal]), step
            if not (low[0] <= x <= high[0] and low[1] <= y <= high[1]
                    and low[2] <= z <= high[2]):
                raise NoPathError(f"cgail rollout left the anatomy after {step} steps",
                                  np.array(positions))
        dist = float(np.linalg.norm(goal - p))
        raise NoPathError(f"cgail rollout did not reach the goal within "
                          f"{cfg.max_rollout_steps} steps (ended {dist * 1e3:.1f} mm from it)",
                          np.array(positions))

    def branch_for(self, goal: FloatArray) -> str:
        """The branch whose coronary ostium is nearest ``goal``."""
        ostia = self.world.ostia
        return min(ostia, key=lambda b: float(np.linalg.norm(goal - ostia[b])))

    def centerline_path(self, p: FloatArray, goal: FloatArray) -> FloatArray:
        """The centerline baseline's raw path: tip, centerline to the goal's ostium, goal."""
        line = self.world.centerlines[self.branch_for(goal)]
        seg = np.diff(line, axis=0)
        l2 = np.einsum("ij,ij->i", seg, seg)
        t = np.clip(np.einsum("ij,ij->i", p - line[:-1], seg) / np.where(l2 > 0, l2, 1.0), 0, 1)
        start_seg = int(np.argmin(np.linalg.norm(line[:-1] + t[:, None] * seg - p, axis=1)))
        end = int(np.argmin(np.linalg.norm(line - goal, axis=1)))
        if end <= start_seg:
            return np.vstack([p, goal])
        return np.vstack([p, line[start_seg + 1:end + 1], goal])


@dataclass(frozen=True)
class ReplanConfig:
    """When the node re-plans during the intervention (dynamic mode)."""

    corridor_radius: float = 0.008
    """The tip has left the path when its distance to the path exceeds this, m; (0, 0.1]."""
    target_move_threshold: float = 0.003
    """A goal that moved more than this from the planned one is a new goal, m; (0, 0.1]."""
    min_interval_s: float = 1.0
    """Shortest time between two re-plans, s; [0, 60]."""

    def __post_init__(self) -> None:
        _check("corridor_radius", self.corridor_radius, 0.0, 0.1, low_open=True)
        _check("target_move_threshold", self.target_move_threshold, 0.0, 0.1, low_open=True)
        _check("min_interval_s", self.min_interval_s, 0.0, 60.0)


def replan_reason(config: ReplanConfig, *, cross_track: float, planned_goal: FloatArray,
                  goal: FloatArray, since_last_plan_s: float) -> str | None:
    """Why the path should be re-planned now, or None.

    Args:
        config: thresholds.
        cross_track: distance of the tip to the current path, m.
        planned_goal: (3,) goal the current path was planned to, m.
        goal: (3,) latest goal, m.
        since_last_plan_s: time since the last plan, s.
    """
    if since_last_plan_s < config.min_interval_s:
        return None
    moved = float(np.linalg.norm(np.asarray(goal) - np.asarray(planned_goal)))
    if moved > config.target_move_threshold:
        return f"target moved {moved * 1e3:.1f} mm"
    if cross_track > config.corridor_radius:
        return f"tip left the corridor ({cross_track * 1e3:.1f} mm from the path)"
    return None

"""Whole-path planning: roll a policy out in the model of the anatomy, or follow the centerline.

numpy and numba (the BVH of :mod:`cgail_sim.wall`, an injected policy callable); no
rclpy and no torch. Used by :mod:`cgail_planner.nodes.planner_node` with
:class:`cgail_planner.core.onnx_policy.OnnxPolicy`.

**C-GAIL planner** (``planner_type='cgail'``): from the current tip pose ``[R | p]`` the policy
is rolled out exactly as the simulator runs an episode, with the catheter model of
:mod:`cgail_sim.ftl_model`: its observation (:func:`~cgail_sim.ftl_model.
observe_pose`), its action scaling and follow-the-leader step, and its retraction rule (the body
behind the tip pose is the introducer an episode's start pose gets,
:meth:`cgail_sim.scenarios.World.introducer`: straight back to the exit plane when that
lies inside the lumen, else along the centerline; straight where neither does).
After every step the rollout ends as an
episode does, by the same priority: a **collision** (the tip sphere penetrates the wall:
``wall.tip_contact(...).penetration > 0``; the frozen model wall exerts no force), an **exit**
(the step crossed the disc of an open end, :mod:`cgail_sim.exits`, or the tip left the
anatomy's bounding box grown by 10 mm; for a ``paper_code`` policy only leaving the authors'
exit box, its training env's rule: :func:`cgail_sim.scenarios.world_exits`), or **success**
(the tip within ``goal_tolerance`` of the goal, which is then appended as the last point);
else it fails after ``max_rollout_steps``. So a policy rolled out from an episode's start
pose gives the episode's tip path and ending (``test_model_parity.py``).
In dynamic mode the wall is the deformable wall's current (deformed) shape, frozen for the
rollout.

**Speed.** When the policy is a numba :class:`~cgail_planner.core.mlp.MlpProgram` (an
``OnnxPolicy`` on its ``mlp`` backend) and the wall a simulator wall, the whole rollout is one
numba call (:mod:`cgail_planner.core.rollout_kernel`, ~20 us per step, mostly the 25-ray cast)
that gives the same path as the Python loop :meth:`Planner.rollout_reference`, which remains the
rollout for any other policy or wall. The kernel is loaded (compiled, without a numba cache) when
the planner is built, not in the first plan.

**Centerline planner** (``planner_type='centerline'``, the traditional baseline): the Voronoi
centerline of the branch whose coronary ostium is nearest the goal, from the tip's projection on
it to the centerline point nearest the goal (cut at the target), then the goal itself, starting at
the tip.

Both raw paths are B-spline fitted and resampled at ``path_spacing``
(:func:`cgail_planner.core.path_fit.fit_path`).

**RRT planner** (``planner_type='rrt'``, the classical peer): a curvature-constrained
bi-directional RRT on OMPL's Vana-Owen curves with the catheter's smallest bend radius
``L / theta_max`` and the wall clearance ``radius + clearance_margin``
(:mod:`cgail_planner.core.rrt_planner`, settings :class:`~cgail_planner.core.rrt_planner.
RrtConfig`). Its path ends at the goal (or, when the goal lacks that clearance, within
``goal_tolerance / 2`` of it) and is resampled at ``path_spacing`` without a spline fit (a fit
could bend it beyond the catheter's curvature).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
import math
import time
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cgail_planner.core.errors import ContractError, InvalidInputError, NoPathError
from cgail_planner.core.mlp import MlpProgram
from cgail_planner.core.path_fit import (
    fit_path,
    PathFitConfig,
    PathFitError,
    resample_by_arc_length,
)
from cgail_planner.core.rotations import validate_pose
from cgail_planner.core.rrt_planner import Lumen, RrtConfig, RrtPlanner
from cgail_sim.exits import crossed_disc
from cgail_sim.ftl_model import (
    advance_pose,
    CatheterConfig,
    command_nb,
    describe_anatomy,
    introducer_tail,
    ObservationConfig,
    ObservationSpec,
    observe_pose,
    PolicyContract,
    PROBE_OFFSETS,
    PROBE_RANGE,
    RAY_DIRECTIONS,
    retract_chain,
    seed_body,
    sensor_points,
)

FloatArray = NDArray[np.float64]

PLANNER_TYPES = ("cgail", "centerline", "rrt")
MODES = ("static", "dynamic")
#: Largest distance between a policy's observation origin and the anatomy's bounding-box
#: centre accepted as the same anatomy, m (built meshes differ by micrometres across CPUs).
ORIGIN_TOLERANCE = 1e-3


class RayWall(Protocol):
    """What the rollout needs from a wall (:class:`cgail_sim.wall.StaticWall`)."""

    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                ) -> np.ndarray:
        """(R,) hit distances along unit directions, ``max_dist`` when nothing is hit."""

    def distance(self, points: np.ndarray, max_dist: float) -> np.ndarray:
        """(P,) distance of each point to the nearest wall point, inf beyond ``max_dist``
        (the ``paper_code`` observation's probes)."""

    def tip_contact(self, tip: np.ndarray, radius: float, dt: float) -> Any:
        """The tip sphere vs the wall: an object with ``penetration`` (m, > 0 when the sphere
        crosses the wall) and ``clearance`` (m, exact distance to contact, inf if unknown)."""


Policy = Callable[[NDArray[np.float32]], NDArray[np.float32]]


@dataclass(frozen=True)
class PlannerConfig:
    """Planner settings (the node's parameters of the same names) and the catheter model."""

    planner_type: str = "cgail"
    """``cgail`` (ONNX policy rollout), ``centerline`` (the traditional baseline) or ``rrt``
    (the curvature-constrained RRT, :mod:`cgail_planner.core.rrt_planner`)."""
    goal_tolerance: float = 0.010
    """The rollout reached the goal within this distance, m (paper epsilon 10 mm); (0, 0.05]."""
    max_rollout_steps: int = 1500
    """Steps of the policy rollout before giving up (0.5 mm each at full insertion); [1, 1e5]."""
    path_spacing: float = 0.001
    """Arc-length spacing of the published (B-spline fitted, resampled) path, m; [0.1 mm, 1 cm]."""
    fit_stride: int = 4
    """Every ``fit_stride``-th rollout point is a B-spline knot (ends always kept); [1, 50]."""
    catheter: CatheterConfig = field(default_factory=CatheterConfig)
    """The catheter model of the rollout (a policy's: its contract's)."""
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    """Position scale and ray length of the rollout's observation (a policy's: its contract's)."""
    rrt: RrtConfig = field(default_factory=RrtConfig)
    """Settings of the ``rrt`` planner (iteration budget, time limit, seed, clearance margin,
    range)."""

    def __post_init__(self) -> None:
        if self.planner_type not in PLANNER_TYPES:
            raise ValueError(f"planner_type must be one of {PLANNER_TYPES}, found "
                             f"{self.planner_type!r}")
        _check("goal_tolerance", self.goal_tolerance, 0.0, 0.05, low_open=True)
        _check("path_spacing", self.path_spacing, 1e-4, 0.01)
        for name, ilow, ihigh in (("max_rollout_steps", 1, 100_000), ("fit_stride", 1, 50)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) \
                    or not ilow <= value <= ihigh:
                raise ValueError(f"{name} must be an int in [{ilow}, {ihigh}], found {value!r}")
        if not isinstance(self.catheter, CatheterConfig):
            raise ValueError(f"catheter must be a CatheterConfig, found "
                             f"{type(self.catheter).__name__}")
        if not isinstance(self.observation, ObservationConfig):
            raise ValueError(f"observation must be an ObservationConfig, found "
                             f"{type(self.observation).__name__}")
        if not isinstance(self.rrt, RrtConfig):
            raise ValueError(f"rrt must be an RrtConfig, found {type(self.rrt).__name__}")

    def with_contract(self, contract: PolicyContract) -> PlannerConfig:
        """These settings with the catheter model and observation of a policy's contract."""
        return replace(self, catheter=contract.catheter,
                       observation=contract.observation.config)


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
    """(K, 3) the raw rollout (or centerline) points the spline was fitted to, m; for the RRT
    its curves sampled every ``RrtConfig.resolution``."""
    planner_type: str
    """Which planner made it."""
    steps: int
    """Rollout steps (0 for the centerline and the RRT)."""
    elapsed_s: float
    """Wall time spent planning, s."""
    iterations: int = 0
    """RRT search iterations used (at most ``RrtConfig.max_iterations``; 0 for the others)."""


@dataclass(frozen=True)
class ModelWorld:
    """The model of the anatomy the planner plans in (from :func:`model_world_from_sim`)."""

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
    exit_point: FloatArray
    """(3,) centre of the open descending end, m (where the introducer comes in)."""
    exit_normal: FloatArray
    """(3,) unit normal of the descending end's plane, out of the lumen."""
    exit_discs: FloatArray
    """(D, 7) the open cuts a rollout can leave through (:attr:`cgail_sim.anatomy.
    Anatomy.exit_discs`, :mod:`cgail_sim.exits`)."""
    introducer: Callable[[FloatArray, FloatArray], FloatArray] | None = None
    """``(position, rotation) -> (K, 3)`` introducer nodes behind a tip pose (proximal end
    first, :func:`cgail_sim.ftl_model.seed_body`); None: straight to
    :func:`~cgail_sim.ftl_model.introducer_tail`."""


def _sim_introducer(world: Any) -> Callable[[FloatArray, FloatArray], FloatArray]:
    """The simulator's introducer behind a tip pose, or the straight one where it has none."""
    from cgail_sim.scenarios import ScenarioError

    anatomy = world.anatomy

    def introducer(p: FloatArray, r: FloatArray) -> FloatArray:
        try:
            return np.asarray(world.introducer(p, r), dtype=np.float64)
        except ScenarioError:
            return introducer_tail(anatomy.exit_point, anatomy.exit_normal, p, r)[None]

    return introducer


def model_world_from_sim(world: Any, observation: ObservationSpec | None = None,
                         exit_rule: str = "discs") -> ModelWorld:
    """Build a :class:`ModelWorld` from a :class:`cgail_sim.scenarios.World`.

    Args:
        world: the simulator's world (anatomy, centerlines, scenarios).
        observation: a policy's observation spec (its contract's): its ``origin`` and ``d_max``
            replace the world's own.
        exit_rule: how a rollout leaves the anatomy (:data:`cgail_sim.scenarios.EXIT_RULES`,
            :func:`cgail_sim.scenarios.world_exits`), the rule the policy was trained with:
            ``box`` for a ``paper_code`` policy (:func:`exit_rule_of`).

    Raises:
        ContractError: the spec's origin is more than :data:`ORIGIN_TOLERANCE` from this
            anatomy's bounding-box centre (the policy was trained on another anatomy).
    """
    from cgail_sim.scenarios import world_exits

    anatomy = world.anatomy
    sc = world.scenarios
    origin = np.asarray(sc.origin, dtype=np.float64)
    d_max = float(sc.d_max)
    if observation is not None:
        moved = float(np.linalg.norm(observation.origin - origin))
        if moved > ORIGIN_TOLERANCE:
            raise ContractError(
                f"observation origin: expected this anatomy's bounding-box centre "
                f"{origin.round(4).tolist()} m, found the policy's "
                f"{observation.origin.round(4).tolist()} m ({moved * 1e3:.1f} mm apart)")
        origin, d_max = observation.origin.copy(), observation.d_max
    discs, low, high = world_exits(anatomy, sc.waypoints, exit_rule)
    return ModelWorld(
        origin=origin, d_max=d_max, bbox_low=low, bbox_high=high,
        centerlines={b: np.asarray(c.points, dtype=np.float64)
                     for b, c in world.centerlines.items()},
        ostia={b: np.asarray(p, dtype=np.float64) for b, p in anatomy.ostia.items()},
        contains=anatomy.contains,
        exit_point=np.asarray(anatomy.exit_point, dtype=np.float64),
        exit_normal=np.asarray(anatomy.exit_normal, dtype=np.float64),
        exit_discs=discs, introducer=_sim_introducer(world))


def exit_rule_of(contract: PolicyContract) -> str:
    """The exit rule a policy was trained with: its env option set's
    (:data:`cgail_sim.config.OPTION_SETS`; ``box`` for ``paper_code``), ``discs`` for a
    ``custom`` configuration, which the contract does not describe further."""
    from cgail_sim.config import OPTION_SETS

    return str(OPTION_SETS.get(contract.env_options, {}).get("exit_rule", "discs"))


def _lumen(world: ModelWorld, wall: RayWall) -> Lumen:
    """The geometry queries the RRT needs: the wall's distance (its unchecked form when it has
    one) and the model world's lumen test, centerlines, ostia, exit discs and bounds."""
    distance = getattr(wall, "distance_unchecked", None) or wall.distance
    return Lumen(distance=distance, contains=world.contains, centerlines=world.centerlines,
                 ostia=world.ostia, exit_discs=world.exit_discs,
                 bbox_low=world.bbox_low, bbox_high=world.bbox_high)


def _wall_arrays(wall: object) -> Any | None:
    """The BVH arrays of a simulator wall (:attr:`cgail_sim.raycast.WallBVH.
    query_arrays`) brought up to date, or None for any other wall.

    A deformable wall refits its tree lazily, so a one-ray cast comes first.
    """
    from cgail_sim.raycast import WallBVH
    from cgail_sim.wall import StaticWall

    if not isinstance(wall, StaticWall) or not isinstance(wall.bvh, WallBVH):
        return None
    wall.raycast(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]), 1e-3)
    return wall.bvh.query_arrays


def world_observation_spec(scenarios: Any, contract: PolicyContract) -> ObservationSpec:
    """The observation spec of the anatomy ``scenarios`` for a policy of ``contract``: that
    anatomy's ``origin``, and the ``d_max`` of the targets the policy was trained on (fixed
    targets or the sphere, from its ``env_options``), with the policy's sensors."""
    from cgail_sim.config import EnvConfig

    try:
        targets = EnvConfig.from_options(contract.env_options).targets
    except ValueError:  # a 'custom' option set: the fixed targets' bound
        targets = "fixed"
    return ObservationSpec.for_world(scenarios, contract.observation.config,
                                     d_max=scenarios.d_max_for(targets))


def reconcile_contract(contract: PolicyContract, *, anatomy: str, mode: str,
                       theta_max: float | None, segment_length: float | None, override: bool,
                       world_spec: ObservationSpec | None = None, anatomy_hash: str = ""
                       ) -> tuple[PolicyContract, list[str]]:
    """The contract a planner runs with, given settings that may repeat some of its entries.

    A setting of None takes the contract's value. A setting that disagrees with the contract
    raises :class:`ContractError` (one line: the name, the policy's value, the setting's value),
    unless ``override`` is set: then the setting wins and a warning is returned. ``mode`` only
    informs: a policy trained in the rigid (static) world may run in the beating one.

    Args:
        contract: the policy's contract.
        anatomy: the anatomy the planner plans in: a built-in name, or a path anatomy's label.
        mode: ``static`` or ``dynamic``: the world the planner plans in.
        theta_max: the maximal bending angle setting, rad, or None.
        segment_length: the steerable segment length setting, m, or None.
        override: let disagreeing settings win (with a warning).
        world_spec: this anatomy's own observation spec (origin, d_max, for the policy's
            targets: :func:`world_observation_spec`), used in place of the policy's when an
            overridden anatomy disagrees, and always for a population policy
            (``contract.anatomies == 'population'``), which runs in any anatomy.
        anatomy_hash: the content hash of a path anatomy, ``""`` for a built-in one
            (:func:`cgail_sim.anatomy_spec.anatomy_identity`). What identifies the anatomy
            is compared: the hashes when either side has one (a path anatomy: its label may
            differ), else the built-in names.

    Returns:
        ``(contract, notes)``: the contract to run with and the lines to log (warnings for
        overrides, a note when the mode differs).
    """
    notes: list[str] = []
    cat = contract.catheter
    changes: dict[str, float] = {}
    for name, value, want in (("theta_max", theta_max, cat.theta_max),
                              ("segment_length", segment_length, cat.segment_length)):
        if value is None or math.isclose(value, want, rel_tol=1e-9, abs_tol=1e-12):
            continue
        if not override:
            raise ContractError(f"{name}: expected the policy's {want:.6g}, found parameter "
                                f"{value:.6g} (set override_policy_contract to run anyway)")
        changes[name] = value
        notes.append(f"override_policy_contract: {name} {value:.6g} instead of the policy's "
                     f"{want:.6g}")
    observation = contract.observation
    same = (anatomy_hash == contract.anatomy_hash if anatomy_hash or contract.anatomy_hash
            else anatomy == contract.anatomy)
    if contract.anatomies == "population":  # a generalist: any anatomy, in its own frame
        if world_spec is None:
            raise ContractError("anatomy: a population policy is observed in the frame of the "
                                "anatomy it runs in: expected that anatomy's observation spec "
                                "(world_spec), found none")
        observation = ObservationSpec(origin=world_spec.origin, d_max=world_spec.d_max,
                                      config=observation.config,
                                      ray_directions=observation.ray_directions,
                                      probe_offsets=observation.probe_offsets)
        notes.append(f"population policy (trained across the anatomy population) runs in "
                     f"{describe_anatomy(anatomy, anatomy_hash)}, observed in its frame "
                     f"(origin {np.round(world_spec.origin * 1e3, 1).tolist()} mm, d_max "
                     f"{world_spec.d_max * 1e3:.1f} mm)")
    elif not same:
        ours, theirs = describe_anatomy(anatomy, anatomy_hash), contract.describe_anatomy()
        if not (anatomy_hash or contract.anatomy_hash):  # two built-in names: just the names
            ours, theirs = repr(anatomy), repr(contract.anatomy)
        if not override:
            raise ContractError(f"anatomy: expected the policy's {theirs}, found parameter "
                                f"{ours} (set override_policy_contract to run anyway)")
        notes.append(f"override_policy_contract: anatomy {ours} instead of the policy's "
                     f"{theirs} (observed in this anatomy's frame)")
        if world_spec is not None:
            observation = ObservationSpec(origin=world_spec.origin, d_max=world_spec.d_max,
                                          config=observation.config,
                                          ray_directions=observation.ray_directions,
                                          probe_offsets=observation.probe_offsets)
    if mode != contract.mode:
        notes.append(f"policy trained in the {contract.mode} world runs in the {mode} world")
    if not changes and observation is contract.observation:
        return contract, notes
    return PolicyContract(catheter=CatheterConfig(**{**asdict(cat), **changes}),
                          observation=observation, anatomy=anatomy, mode=contract.mode,
                          training=contract.training, anatomy_hash=anatomy_hash,
                          env_options=contract.env_options, anatomies=contract.anatomies), notes


class Planner:
    """Plans whole paths from a tip pose to a goal (module docstring).

    Args:
        config: planner settings and the catheter model.
        world: the anatomy model (observation origin and ``d_max``, exit discs, bounds).
        wall: ray-cast and contact wall (static, or the deformable wall whose current shape is
            used).
        policy: ``obs (dim,) float32 -> action (3,)`` in [-1, 1]; required for ``cgail``.
        ray_directions: (R, 3) ray set in the tip frame (default
            :data:`~cgail_sim.ftl_model.RAY_DIRECTIONS`; a policy's: its contract's).
        obs_dim: the policy's observation size (checked against the spec's: ``16 + R``, or
            ``11 + P`` for the ``paper_code`` observation of ``config.observation.kind``).
        probe_offsets: (P, 3) ``paper_code`` probe points in the tip frame (default
            :data:`~cgail_sim.ftl_model.PROBE_OFFSETS`; a policy's: its contract's).

    Raises:
        ValueError: ``cgail`` without a policy, or an observation size mismatch.
    """

    def __init__(self, config: PlannerConfig, world: ModelWorld, wall: RayWall,
                 policy: Policy | None, ray_directions: FloatArray | None = None,
                 obs_dim: int | None = None, probe_offsets: FloatArray | None = None) -> None:
        self.config = config
        self.world = world
        self.wall = wall
        self.policy = policy
        self.spec = ObservationSpec(
            origin=world.origin, d_max=world.d_max, config=config.observation,
            ray_directions=RAY_DIRECTIONS if ray_directions is None else ray_directions,
            probe_offsets=PROBE_OFFSETS if probe_offsets is None else probe_offsets)
        self.rays = self.spec.ray_directions
        self.obs_dim = self.spec.dim
        if config.planner_type == "cgail" and policy is None:
            raise ValueError("planner_type 'cgail' needs a policy, found None")
        if obs_dim is not None and obs_dim != self.obs_dim:
            raise ValueError(f"policy observation size must be {self.obs_dim} ({self.spec.kind} "
                             f"observation, {self.spec.n_rays} sensors), found {obs_dim}")
        self._fit = PathFitConfig(spacing=config.path_spacing)
        self.rrt: RrtPlanner | None = None
        if config.planner_type == "rrt":
            self.rrt = RrtPlanner(config.rrt, config.catheter, _lumen(world, wall))
        program = policy if isinstance(policy, MlpProgram) else getattr(policy, "mlp", None)
        self._program: MlpProgram | None = None
        if isinstance(program, MlpProgram) and program.in_dim == self.obs_dim \
                and program.out_dim == 3:
            self._program = program
            arrays = _wall_arrays(wall)
            if arrays is not None:
                # load (or, without a numba cache, compile: seconds) the kernel now rather
                # than in the first plan: a one-step rollout from the observation origin
                origin = np.asarray(world.origin, dtype=np.float64)
                self._run_kernel(program, arrays, origin, np.eye(3), origin + 1.0, 1)

    @classmethod
    def from_contract(cls, contract: PolicyContract, world: Any, wall: RayWall, policy: Policy,
                      settings: PlannerConfig | None = None) -> Planner:
        """A C-GAIL planner built from its policy's contract.

        Args:
            contract: the policy's contract (catheter model, observation spec).
            world: the simulator's world of the contract's anatomy.
            wall: the wall to plan in.
            policy: the policy.
            settings: the planner settings (default ``PlannerConfig()``); their catheter model
                and observation are replaced by the contract's.

        Raises:
            ContractError: the world is not the contract's anatomy (observation origin).
        """
        config = (settings or PlannerConfig()).with_contract(contract)
        model = model_world_from_sim(world, contract.observation, exit_rule_of(contract))
        return cls(config, model, wall, policy, contract.observation.ray_directions,
                   obs_dim=contract.observation.dim,
                   probe_offsets=contract.observation.probe_offsets)

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
            InvalidInputError: bad pose or goal (for the RRT also a start without clearance).
            NoPathError: no path found (for the RRT: none within its iteration budget or time
                limit).
        """
        t0 = time.perf_counter()
        p, r = validate_pose(position, rotation)
        g = self.validate_goal(goal)
        if self.rrt is not None:
            found = self.rrt.plan(p, r, g, self.config.goal_tolerance)
            return PlanResult(path=resample_by_arc_length(found.points, self.config.path_spacing),
                              raw=found.points, planner_type="rrt", steps=0,
                              elapsed_s=time.perf_counter() - t0, iterations=found.iterations)
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
        """The environment's observation of tip pose ``[r | p]`` (:func:`observe_pose`)."""
        return observe_pose(self.spec, p, r, goal, hits)

    def readings(self, p: FloatArray, r: FloatArray) -> FloatArray:
        """(S,) sensor readings of tip pose ``[r | p]`` in the wall: ray hit distances, or the
        ``paper_code`` probes' nearest-wall distances (inf beyond
        :data:`~cgail_sim.ftl_model.PROBE_RANGE`), m."""
        spec = self.spec
        pts = sensor_points(spec, p[None], r[None])[0]
        if spec.kind == "paper_code":
            return np.asarray(self.wall.distance(pts, PROBE_RANGE), dtype=np.float64)
        origins = np.repeat(np.asarray(p, dtype=np.float64)[None], len(pts), axis=0)
        return np.asarray(self.wall.raycast(origins, pts, spec.ray_length), dtype=np.float64)

    @property
    def uses_kernel(self) -> bool:
        """True when :meth:`rollout` runs as one numba call (:mod:`.rollout_kernel`): the policy
        is an :class:`~cgail_planner.core.mlp.MlpProgram` (or has one as ``.mlp``, as
        :class:`~cgail_planner.core.onnx_policy.OnnxPolicy` has) with this planner's
        observation size and 3 actions, and the wall is a simulator wall with a numba BVH."""
        return self._program is not None and _wall_arrays(self.wall) is not None

    def _seed(self, p0: FloatArray, r0: FloatArray, steps: int
              ) -> tuple[FloatArray, FloatArray, FloatArray, int]:
        """A body seeded with the introducer behind ``[r0 | p0]``, room for ``steps`` more
        nodes: ``(positions, rotations, arc, n0)`` with ``n0`` seeded nodes, the last the
        start pose."""
        w = self.world
        intro = (w.introducer(p0, r0) if w.introducer is not None
                 else introducer_tail(w.exit_point, w.exit_normal, p0, r0))
        capacity = steps + np.asarray(intro).reshape(-1, 3).shape[0] + 1
        positions = np.empty((capacity, 3))
        rotations = np.empty((capacity, 3, 3))
        arc = np.empty(capacity)
        n0 = seed_body(positions, rotations, arc, intro, p0, r0)
        return positions, rotations, arc, n0

    def rollout(self, p0: FloatArray, r0: FloatArray, goal: FloatArray
                ) -> tuple[FloatArray, int]:
        """Roll the policy out from ``[r0 | p0]`` towards ``goal``.

        Runs :func:`cgail_planner.core.rollout_kernel.rollout_kernel` when
        :attr:`uses_kernel`, else :meth:`rollout_reference`; both give the same path.

        Returns:
            ``(points, steps)``: the body from ``p0`` (or, after a retraction behind ``p0``,
            from the tip) to the final tip, then ``goal``.

        Raises:
            NoPathError: collision, exit or step limit before reaching the goal.
        """
        program = self._program
        arrays = _wall_arrays(self.wall) if program is not None else None
        if program is None or arrays is None:
            return self.rollout_reference(p0, r0, goal)
        from cgail_planner.core import rollout_kernel as rk

        cfg = self.config
        goal = np.ascontiguousarray(goal, dtype=np.float64)
        status, steps, points, action = self._run_kernel(program, arrays, p0, r0, goal,
                                                         cfg.max_rollout_steps)
        if status == rk.REACHED:
            return np.vstack([points, goal]), int(steps)
        if status == rk.BAD_ACTION:
            raise NoPathError(f"policy must return 3 finite actions, found "
                              f"{action.tolist()}", points, "bad_action", int(steps))
        raise self._failure({rk.COLLIDED: "collided", rk.LEFT_ANATOMY: "left",
                             rk.STEP_LIMIT: "limit"}[status], int(steps), points, goal)

    def _failure(self, kind: str, step: int, points: FloatArray, goal: FloatArray
                 ) -> NoPathError:
        """The error of a rollout that ended without reaching the goal."""
        p = points[-1]
        if kind == "collided":
            text = (f"cgail rollout touched the wall at step {step} at "
                    f"({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m, "
                    f"{float(np.linalg.norm(goal - p)) * 1e3:.1f} mm from the goal")
        elif kind == "left":
            text = f"cgail rollout left the anatomy at step {step}"
        else:
            text = (f"cgail rollout did not reach the goal within "
                    f"{self.config.max_rollout_steps} steps (ended "
                    f"{float(np.linalg.norm(goal - p)) * 1e3:.1f} mm from it)")
        return NoPathError(text, points, kind, step)

    def _run_kernel(self, program: MlpProgram, arrays: Any, p0: FloatArray, r0: FloatArray,
                    goal: FloatArray, max_steps: int
                    ) -> tuple[int, int, FloatArray, FloatArray]:
        """One call of the rollout kernel: ``(status, steps, points, last action)``."""
        from cgail_planner.core import rollout_kernel as rk

        cfg, cat, spec, w = self.config, self.config.catheter, self.spec, self.world
        p0 = np.ascontiguousarray(p0, dtype=np.float64)
        r0 = np.ascontiguousarray(r0, dtype=np.float64)
        positions, rotations, arc, n0 = self._seed(p0, r0, max_steps)
        action = np.zeros(3)
        kernel: Callable[..., tuple[int, int, int]] = rk.rollout_kernel
        # every scalar as a Python float/int: one compiled signature whatever the config types
        status, steps, n = kernel(
            positions, rotations, arc, n0, np.ascontiguousarray(goal, dtype=np.float64),
            spec.ray_directions, spec.probe_offsets, spec.kind == "paper_code", spec.origin,
            float(spec.position_scale), float(spec.d_max),
            float(spec.ray_length), float(cat.theta_max), float(cat.segment_length),
            float(cat.max_step_insertion), bool(cat.forward_only), float(cat.radius),
            float(cat.dt),
            float(self.wall_tolerance), float(cfg.goal_tolerance),
            np.ascontiguousarray(w.exit_discs, dtype=np.float64),
            np.ascontiguousarray(w.bbox_low, dtype=np.float64),
            np.ascontiguousarray(w.bbox_high, dtype=np.float64), int(max_steps), arrays,
            program.ops, program.consts, program.widths, program.scratch(), program.out_reg,
            action)
        return int(status), int(steps), _points(positions, int(n), n0), action

    @property
    def wall_tolerance(self) -> float:
        """The wall's penetration tolerance, m (0 for a wall that does not say)."""
        return float(getattr(self.wall, "penetration_tolerance", 0.0))

    def rollout_reference(self, p0: FloatArray, r0: FloatArray, goal: FloatArray
                          ) -> tuple[FloatArray, int]:
        """:meth:`rollout` as a Python loop calling ``wall.raycast``, ``wall.tip_contact`` and
        ``policy`` per step, and the single-pose forms of :mod:`cgail_sim.ftl_model`.

        The specification of the numba kernel, and the rollout for any policy callable and
        any :class:`RayWall`. Same returns and errors as :meth:`rollout`.
        """
        cfg, cat, spec, w = self.config, self.config.catheter, self.spec, self.world
        assert self.policy is not None
        p = np.array(p0, dtype=np.float64)
        r = np.array(r0, dtype=np.float64)
        goal = np.asarray(goal, dtype=np.float64)
        positions, rotations, arc, n0 = self._seed(p, r, cfg.max_rollout_steps)
        n = n0
        discs = np.ascontiguousarray(w.exit_discs, dtype=np.float64)
        low, high = w.bbox_low.tolist(), w.bbox_high.tolist()
        gx, gy, gz = goal.tolist()
        clearance = -math.inf  # a lower bound of the exact clearance (as the env's broad phase)
        for step in range(1, cfg.max_rollout_steps + 1):
            hits = self.readings(p, r)
            out = np.asarray(self.policy(observe_pose(spec, p, r, goal, hits)))
            out = out.astype(np.float32).reshape(-1)
            if out.shape != (3,) or not np.isfinite(out).all():
                raise NoPathError(f"policy must return 3 finite actions, found {out.tolist()}",
                                  _points(positions, n, n0), "bad_action", step)
            a0, a1, a2 = out.tolist()
            x0, y0, z0 = p.tolist()
            alpha, gamma, dl = command_nb(a0, a1, a2, cat.theta_max, cat.segment_length,
                                          cat.max_step_insertion, cat.forward_only)
            travelled = 0.0
            if dl > 0.0:
                p, r = advance_pose(p, r, alpha, gamma, dl)
                positions[n] = p
                rotations[n] = r
                arc[n] = arc[n - 1] + dl
                n += 1
                travelled = dl
            elif dl < 0.0:
                n, travelled = retract_chain(positions, arc, n, -dl)
                p, r = positions[n - 1].copy(), rotations[n - 1].copy()
            # the episode's ending, in its order: collision, exit, success
            clearance -= travelled
            if clearance <= 1e-9:
                contact = self.wall.tip_contact(p, cat.radius, cat.dt)
                if contact.penetration > 0.0:
                    raise self._failure("collided", step, _points(positions, n, n0), goal)
                clearance = contact.clearance if math.isfinite(contact.clearance) else -math.inf
            x, y, z = p.tolist()
            if crossed_disc(x0, y0, z0, x, y, z, discs) >= 0 \
                    or not (low[0] <= x <= high[0] and low[1] <= y <= high[1]
                            and low[2] <= z <= high[2]):
                raise self._failure("left", step, _points(positions, n, n0), goal)
            if math.sqrt((gx - x) ** 2 + (gy - y) ** 2 + (gz - z) ** 2) < cfg.goal_tolerance:
                return np.vstack([_points(positions, n, n0), goal]), step
        raise self._failure("limit", cfg.max_rollout_steps, _points(positions, n, n0), goal)

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


def _points(positions: FloatArray, n: int, n0: int) -> FloatArray:
    """The planned body of a rollout: nodes ``n0 - 1 .. n - 1`` (from the start pose on; the
    nodes before it are the introducer), or from the tip when it retracted into the
    introducer."""
    return positions[min(n0, n) - 1:n].copy()

"""Gymnasium environment: steer a follow-the-leader catheter to a coronary ostium.

:class:`NavEngine` holds the batched simulation (N environments, numpy-vectorised catheter,
observations and reward, one batched raycast per step in static mode);
:class:`CatheterNavEnv` is the single gymnasium environment (an engine with N = 1) and
:class:`cgail_sim.vec_env.CatheterNavVecEnv` the batched one (same engine, N > 1).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, cast

import gymnasium as gym
from gymnasium import spaces
import numpy as np
from numpy.typing import NDArray

from cgail_sim.anatomy_spec import anatomy_label, AnatomySpec
from cgail_sim.config import EnvConfig
from cgail_sim.exits import crossed_discs
from cgail_sim.ftl_model import (
    action_to_command,
    bend_limit,
    CatheterBatch,
    OBS_DIM,
    OBS_LAYOUT,
    ObservationSpec,
    observe_batch,
    PROBE_RANGE,
    RAY_DIRECTIONS,
    sensor_points,
    steer_towards,
)
from cgail_sim.heartbeat import HeartbeatConfig
from cgail_sim.pbd import DYNAMIC_PBD_CONFIG, PBDConfig
from cgail_sim.reward import (
    bending_event,
    compute_reward,
    non_minor_collision,
    reached_target,
    StepEvents,
    update_waypoints,
)
from cgail_sim.scenarios import (
    target_sampler,
    TargetConfig,
    World,
    world_exits,
)
from cgail_sim.wall import DeformableWall, StaticWall, WallError
from cgail_sim.worlds import load_world

FloatArray = NDArray[np.float64]
_LOG = logging.getLogger(__name__)


#: Bound of the unbounded-looking entries (positions, u, v) of the observation space.
OBS_BOUND = 5.0
#: ``paper_code`` observation: bound of the position (mm) and of the distance / 50 mm. The
#: episode ends at the exit box, at most 125 mm beyond the centreline, so a tip stays well
#: within 1 m of the anatomy's centre and 2 m of the target.
PAPER_CODE_POSITION_BOUND_MM = 1000.0
PAPER_CODE_DISTANCE_BOUND = 40.0


def observation_spec(config: EnvConfig) -> ObservationSpec:
    """The observation spec of an env configuration (its anatomy's origin and d_max)."""
    sc = load_world(config.anatomy, config.n_waypoints, config.scenario_seed).scenarios
    return ObservationSpec.for_world(sc, config.observation, d_max=sc.d_max_for(config.targets))


def obs_layout_dict(config: EnvConfig | None = None) -> dict[str, Any]:
    """JSON-able description of the observation (layout and ray set).

    Args:
        config: when given, the whole :class:`~cgail_sim.ftl_model.ObservationSpec` of
            that configuration (``origin``, ``position_scale``, ``d_max``, ``ray_length``: the
            numbers needed to rebuild observations outside the simulator) and its ``anatomy``
            (:func:`~cgail_sim.anatomy_spec.anatomy_label`).
    """
    if config is not None:
        return {**observation_spec(config).to_dict(), "anatomy": anatomy_label(config.anatomy)}
    return {
        "dim": OBS_DIM,
        "fields": [f._asdict() for f in OBS_LAYOUT],
        "ray_directions_tip_frame": RAY_DIRECTIONS.tolist(),
    }


def _observation_space(spec: ObservationSpec | None = None) -> spaces.Box:
    # Bounds hold by construction: the tip never gets further than the anatomy's bounding box
    # + 10 mm (the episode ends there) and the target stays within a few mm of its rest point.
    if spec is not None and spec.kind == "paper_code":
        low = np.full(spec.dim, -1.0, dtype=np.float32)  # (quaternion, direction)
        high = np.full(spec.dim, 1.0, dtype=np.float32)
        low[0:3], high[0:3] = -PAPER_CODE_POSITION_BOUND_MM, PAPER_CODE_POSITION_BOUND_MM
        low[10], high[10] = 0.0, PAPER_CODE_DISTANCE_BOUND
        low[11:] = 0.0  # probes: mm below 0.8, or 1
        return spaces.Box(low, high, dtype=np.float32)
    low = np.full(OBS_DIM, -OBS_BOUND, dtype=np.float32)
    high = np.full(OBS_DIM, OBS_BOUND, dtype=np.float32)
    low[3:12], high[3:12] = -1.0, 1.0
    low[12] = 0.0
    low[16:], high[16:] = 0.0, 1.0
    return spaces.Box(low, high, dtype=np.float32)


def _make_wall(world: World, mode: str, pbd_config: PBDConfig | None = None,
               heartbeat: HeartbeatConfig | None = None) -> StaticWall | DeformableWall:
    if mode == "static":
        return StaticWall(world.anatomy)
    return DeformableWall(world.anatomy,
                          pbd_config if pbd_config is not None else DYNAMIC_PBD_CONFIG,
                          heartbeat)


def _checked_pose(pose: Any) -> tuple[FloatArray, FloatArray]:
    """``(position (3,), rotation (3, 3))`` as float arrays, checked finite and a rotation."""
    try:
        p = np.array(pose[0], dtype=np.float64)
        r = np.array(pose[1], dtype=np.float64)
    except (TypeError, ValueError, IndexError, KeyError):
        raise ValueError(f"start_pose must be (position, rotation), found {pose!r}") from None
    if p.shape != (3,) or r.shape != (3, 3) or not (np.isfinite(p).all()
                                                     and np.isfinite(r).all()):
        raise ValueError(f"start_pose must be a finite (3,) position and (3, 3) rotation, "
                         f"found shapes {p.shape} and {r.shape}")
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > 1e-6 or np.linalg.det(r) < 0.0:
        raise ValueError(f"start_pose rotation must be a rotation matrix, found orthogonality "
                         f"error {err:.3g} and determinant {np.linalg.det(r):.3g}")
    return p, r


def _check_pbd_config(pbd_config: Any) -> PBDConfig | None:
    if pbd_config is not None and not isinstance(pbd_config, PBDConfig):
        raise ValueError(f"pbd_config must be a PBDConfig or None, found "
                         f"{type(pbd_config).__name__}")
    return pbd_config


def validate_actions(actions: Any, n_envs: int, single: bool = False) -> FloatArray:
    """Check normalised actions; returns an (N, 3) float64 array.

    Args:
        actions: (N, 3) actions, or (3,) when ``single``.
        n_envs: batch size N.
        single: expect one (3,) action (the single env).

    Raises:
        ValueError: wrong shape, non-numeric, NaN or inf entries.
    """
    expected = (3,) if single else (n_envs, 3)
    try:
        a = np.asarray(actions, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"action must be numeric with shape {expected}, found "
                         f"{type(actions).__name__}") from exc
    if a.shape != expected:
        raise ValueError(f"action must have shape {expected}, found {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action must be finite (no NaN/inf), found {a.tolist()}")
    return a.reshape(n_envs, 3)


class NavEngine:
    """N catheter navigation episodes stepped together (see :class:`CatheterNavEnv`).

    Args:
        config: environment configuration.
        n_envs: batch size N.
        pbd_config: wall solver of the dynamic mode (default :data:`DYNAMIC_PBD_CONFIG`, the
            calibrated wall with 5 accelerated sweeps per step); ignored in static mode.
    """

    def __init__(self, config: EnvConfig, n_envs: int,
                 pbd_config: PBDConfig | None = None) -> None:
        self.config = config
        self.n_envs = n_envs
        self.pbd_config = _check_pbd_config(pbd_config)
        self.world = load_world(config.anatomy, config.n_waypoints, config.scenario_seed)
        sc = self.world.scenarios
        self.scenarios = sc
        anatomy = self.world.anatomy
        if config.mode == "static":
            wall = _make_wall(self.world, "static")
            self.walls = [wall] * n_envs
            self._shared_wall = True
        else:
            self.walls = [_make_wall(self.world, "dynamic", self.pbd_config, config.heartbeat)
                          for _ in range(n_envs)]
            self._shared_wall = False
        cat = config.catheter
        self.catheter = CatheterBatch(n_envs, cat, capacity=config.max_steps + 8)
        self.radius = cat.radius
        #: the open cuts the tip can leave through (:mod:`cgail_sim.exits`)
        self.exit_discs, self.bbox_low, self.bbox_high = world_exits(
            anatomy, sc.waypoints, config.exit_rule)
        #: the episode target's wall vertex, rest offset and branch, per environment
        self._target_vertex = np.zeros(n_envs, dtype=np.int64)
        self._target_offset = np.zeros((n_envs, 3))
        self.branch = ["left"] * n_envs
        self._branch_waypoints = {b: w for b, w in sc.waypoints.items()}
        n_wp = next(iter(sc.waypoints.values())).shape[0]
        self.start_id = np.zeros(n_envs, dtype=np.int64)
        self.target_id = np.zeros(n_envs, dtype=np.int64)
        self.target = np.zeros((n_envs, 3))
        self.waypoints = np.zeros((n_envs, n_wp, 3))
        self.reached = np.zeros((n_envs, n_wp), dtype=bool)
        self.steps = np.zeros(n_envs, dtype=np.int64)
        self.time = np.zeros(n_envs)
        self.min_distance = np.zeros(n_envs)
        self.spec = ObservationSpec.for_world(sc, config.observation,
                                              d_max=sc.d_max_for(config.targets))
        #: (N, S) sensor readings of the last step (:func:`~cgail_sim.ftl_model.
        #: observe_batch`): ray hit distances, or ``paper_code`` probe wall distances, m.
        self.hits = np.full((n_envs, self.spec.n_rays), self.spec.no_reading)
        self.contact_force = np.zeros(n_envs)
        self.penetration = np.zeros(n_envs)
        self.in_contact = np.zeros(n_envs, dtype=bool)
        self._clearance_lb = np.full(n_envs, -np.inf)

    # ------------------------------------------------------------------ episodes
    def draw_target(self, rng: np.random.Generator) -> TargetConfig:
        """A target drawn with ``rng`` in the anatomy's 30 mm sphere (``EnvConfig.targets ==
        "sphere"``; :class:`~cgail_sim.scenarios.TargetSampler`)."""
        return target_sampler(self.world.anatomy).sample(rng, 1)[0]

    def reset_env(self, i: int, start_id: int, target_id: int,
                  start_pose: tuple[FloatArray, FloatArray] | None = None,
                  target: TargetConfig | None = None) -> None:
        """Start episode ``i`` from start ``start_id`` towards target ``target_id``, or towards
        ``target`` (a drawn one, :meth:`draw_target`; ``target_id`` is then -1).

        ``start_pose`` ``(position (3,), rotation (3, 3))`` puts the tip there instead of at
        the start's pose, with the introducer behind it
        (:meth:`~cgail_sim.scenarios.World.introducer`): a demonstration replayed from
        the pose it was recorded from (:mod:`cgail_learning.demo_bags`).
        """
        sc = self.scenarios
        if not 0 <= start_id < len(sc.starts):
            raise ValueError(f"start must be in [0, {len(sc.starts) - 1}], found {start_id}")
        if target is None and not 0 <= target_id < len(sc.targets):
            raise ValueError(f"target must be in [0, {len(sc.targets) - 1}], found {target_id}")
        if target is not None and not isinstance(target, TargetConfig):
            raise ValueError(f"target must be a TargetConfig or None, found "
                             f"{type(target).__name__}")
        start = sc.starts[start_id]
        if start_pose is None:
            self.catheter.reset_env(i, start.position, start.rotation, start.introducer)
        else:
            p, r = _checked_pose(start_pose)
            self.catheter.reset_env(i, p, r, self.world.introducer(p, r))
        if not self._shared_wall:
            self.walls[i].reset()
        self.start_id[i] = start_id
        tc = sc.targets[target_id] if target is None else target
        self.target_id[i] = target_id if target is None else -1
        self.target[i] = tc.position
        self._target_vertex[i] = tc.vertex
        self._target_offset[i] = tc.offset
        self.branch[i] = tc.branch
        self.waypoints[i] = self._branch_waypoints[tc.branch]
        self.reached[i] = False
        self.steps[i] = 0
        self.time[i] = 0.0
        self.contact_force[i] = 0.0
        self.penetration[i] = 0.0
        self.in_contact[i] = False
        self._clearance_lb[i] = -np.inf
        tip = self.catheter.tip_position[i]
        self.min_distance[i] = float(np.linalg.norm(self.target[i] - tip))
        # waypoints already under the start pose are marked without reward
        update_waypoints(tip[None], self.waypoints[i:i + 1], self.reached[i:i + 1],
                         self.config.reward)
        self._cast_rays(np.array([i]))

    def _cast_rays(self, idx: NDArray[np.int64]) -> None:
        """Sense (rays, or ``paper_code`` probes) from the tips of environments ``idx``."""
        self.hits[idx] = self._readings(idx, self.catheter.tip_position[idx],
                                        self.catheter.tip_rotation[idx])

    def _readings(self, idx: NDArray[np.int64], tips: FloatArray, rots: FloatArray
                  ) -> FloatArray:
        """(n, S) sensor readings of poses ``(tips, rots)`` in the walls of environments
        ``idx``: ray hit distances, or ``paper_code`` probe wall distances (m)."""
        spec = self.spec
        n_s = spec.n_rays
        pts = sensor_points(spec, tips, rots)  # (n, S, 3): ray directions or probe points
        probes = spec.kind == "paper_code"
        out = np.empty((len(idx), n_s))
        # (the walls' unchecked queries: finite and well-formed by construction)
        if probes:
            def query(wall: Any, k: slice) -> FloatArray:
                return wall.distance_unchecked(
                    np.ascontiguousarray(pts[k].reshape(-1, 3)), PROBE_RANGE)
        else:
            origins = np.repeat(tips[:, None, :], n_s, axis=1)
            length = float(self.config.ray_length)

            def query(wall: Any, k: slice) -> FloatArray:
                return wall.cast_unchecked(np.ascontiguousarray(origins[k].reshape(-1, 3)),
                                           np.ascontiguousarray(pts[k].reshape(-1, 3)), length)
        if self._shared_wall:
            out[:] = query(self.walls[0], slice(None)).reshape(len(idx), n_s)
        else:
            for k, i in enumerate(np.asarray(idx).tolist()):
                out[k] = query(self.walls[i], slice(k, k + 1))
        return out

    def readings_at(self, i: int, p: FloatArray, r: FloatArray) -> FloatArray:
        """(S,) sensor readings of environment ``i``'s wall as if its tip were at ``[r | p]``
        (what ``evaluate`` observes through a simulated tracker)."""
        return self._readings(np.array([i]), np.asarray(p, dtype=np.float64)[None],
                              np.asarray(r, dtype=np.float64)[None])[0]

    # ------------------------------------------------------------------ stepping
    def step(self, actions: FloatArray) -> tuple[FloatArray, NDArray[np.bool_],
                                                 NDArray[np.bool_], dict[str, Any]]:
        """Advance every environment by one validated (N, 3) normalised action.

        Returns:
            ``(reward, terminated, truncated, info_arrays)``; observations come from
            :meth:`observe` (call it after resetting the finished environments).
        """
        cfg = self.config
        cat = self.catheter
        alpha, gamma, dl = action_to_command(actions, cat.theta_max, cfg.segment_length,
                                             cat.config.max_step_insertion, cfg.forward_only)
        previous_tips = cat.tip_position  # (a copy) for the exit test
        al, ga, applied_dl = cat.step(alpha, gamma, dl)
        limit = bend_limit(np.where(applied_dl > 0.0, applied_dl, 0.0), cat.theta_max,
                           cfg.segment_length)
        self.steps += 1
        self.time += cfg.dt
        tips = cat.tip_position
        n = self.n_envs
        fault = np.zeros(n, dtype=bool)
        fault_message = [""] * n
        if cfg.mode == "dynamic":
            for i in range(n):
                wall = cast(DeformableWall, self.walls[i])  # (dynamic mode)
                # (unchecked step: finite times, a body from the catheter kinematics)
                try:
                    wall.step_unchecked(float(self.time[i]), float(cfg.dt),
                                        cat.body_points(i, cfg.body_spacing),
                                        float(self.radius))
                except WallError as err:  # a simulation fault ends this episode (see step)
                    fault[i], fault_message[i] = True, str(err)
                    _LOG.warning("simulation fault in %s: env %d, start %d, target %d, step "
                                 "%d: %s", anatomy_label(cfg.anatomy), i,
                                 int(self.start_id[i]), int(self.target_id[i]),
                                 int(self.steps[i]), err)
                    wall.reset()  # a sane wall for this last step's sensing
                self.target[i] = (wall.vertices[int(self._target_vertex[i])]
                                  + self._target_offset[i])
        # Static broad phase (exact, not a heuristic): the clearance to a rigid wall is
        # 1-Lipschitz in the tip position, so after the tip travelled |delta_l| it is >= the last
        # exact clearance - |delta_l|; while that bound stays > 0 the tip cannot touch the wall and
        # tip_contact would report no contact, so the closest-point query is skipped. The
        # deformable wall is queried every step (its force depends on the particles it moved).
        if self._shared_wall:
            self._clearance_lb -= np.abs(applied_dl)
            query = np.flatnonzero(self._clearance_lb <= 1e-9)
            self.contact_force[:] = 0.0
            self.penetration[:] = 0.0
            self.in_contact[:] = False
        else:
            query = np.arange(n)
        for i in query.tolist():
            c = self.walls[i].tip_contact_unchecked(tips[i], float(self.radius), float(cfg.dt))
            self.contact_force[i] = c.force
            self.penetration[i] = c.penetration
            self.in_contact[i] = c.in_contact
            # an unknown (infinite: nothing within the search radius) clearance proves nothing
            self._clearance_lb[i] = c.clearance if math.isfinite(c.clearance) else -np.inf
        self._cast_rays(np.arange(n))
        rcfg = cfg.reward
        collision = non_minor_collision(self.contact_force, self.penetration, rcfg)
        outside_box = np.any((tips < self.bbox_low) | (tips > self.bbox_high), axis=1)
        exited = crossed_discs(previous_tips, tips, self.exit_discs) | outside_box
        success = reached_target(tips, self.target, rcfg)
        if fault.any():  # a faulted step has no outcome of the task (no r_end)
            collision, exited, success = collision & ~fault, exited & ~fault, success & ~fault
        new_wp = update_waypoints(tips, self.waypoints, self.reached, rcfg)
        bending = bending_event(al, ga, limit, rcfg, actions)
        events = StepEvents(collision=collision, exited=exited, success=success,
                            new_waypoints=new_wp, bending=bending)
        terms, terminated = compute_reward(events, rcfg)
        dist = np.linalg.norm(self.target - tips, axis=1)
        np.minimum(self.min_distance, dist, out=self.min_distance)
        truncated = ((self.steps >= cfg.max_steps) | fault) & ~terminated
        info = {
            "success": events.success & ~events.collision & ~events.exited,
            "collision": collision,
            "exited": exited & ~collision,
            "collision_force": self.contact_force.copy(),
            "penetration": self.penetration.copy(),
            "in_contact": self.in_contact.copy(),
            "targeting_error": self.min_distance.copy(),
            "distance": dist,
            "timesteps": self.steps.copy(),
            "time": self.time.copy(),
            "new_waypoints": new_wp,
            "waypoints_reached": self.reached.sum(axis=1),
            "bend": np.stack([al, ga], axis=1),
            "insertion": applied_dl,
            "reward_end": terms.end,
            "reward_centerline": terms.centerline,
            "reward_bending": terms.bending,
            "simulation_fault": fault,
            "simulation_fault_message": np.array(fault_message),
        }
        return terms.total, terminated, truncated, info

    def observe(self) -> NDArray[np.float32]:
        """(N, OBS_DIM) float32 observations (:func:`~cgail_sim.ftl_model.observe_batch`,
        layout :data:`OBS_LAYOUT`)."""
        return observe_batch(self.spec, self.catheter.tip_position, self.catheter.tip_rotation,
                             self.target, self.hits)


def pursuit_actions(engine: NavEngine, lookahead: float = 0.015,
                    final_approach: float = 0.030) -> FloatArray:
    """Scripted sanity policy: pure pursuit along the target branch's centerline.

    For every environment of ``engine``: find the waypoint nearest the tip, aim at the waypoint
    ``lookahead`` (15 mm) further along the centerline, or at the target itself once the tip is
    within ``final_approach`` (30 mm) of it or the centerline is used up, and bend as far as the
    FTL limit allows towards that point (:func:`~cgail_sim.ftl_model.steer_towards`) while
    inserting at full speed. It knows nothing of walls or the heartbeat; it is a baseline and a
    smoke test, not the demonstration expert.

    Returns:
        (N, 3) normalised actions.
    """
    cat = engine.catheter
    tips = cat.tip_position
    wps = engine.waypoints
    seg = np.linalg.norm(np.diff(wps, axis=1), axis=2)
    arc = np.concatenate([np.zeros((engine.n_envs, 1)), np.cumsum(seg, axis=1)], axis=1)
    rows = np.arange(engine.n_envs)
    j = np.argmin(np.sum((wps - tips[:, None, :]) ** 2, axis=2), axis=1)
    ahead = arc >= (arc[rows, j] + lookahead)[:, None]
    last = wps.shape[1] - 1
    k = np.where(ahead.any(axis=1), np.argmax(ahead, axis=1), last)
    goal = wps[rows, k]
    near = (k == last) | (np.linalg.norm(engine.target - tips, axis=1) < final_approach)
    goal[near] = engine.target[near]
    return steer_towards(tips, cat.tip_rotation, goal, cat.config, cat.theta_max)


class CatheterNavEnv(gym.Env[NDArray[np.float32], NDArray[np.float32]]):
    """Follow-the-leader catheter navigation from the descending aorta to a coronary ostium.

    The in-silico task of the paper (section III): the catheter tip starts in the descending aorta
    (one of 3 start configurations) and must come within ``epsilon`` (10 mm) of a target near the
    coronary ostia (one of 5, attached to a wall particle) without a non-minor wall collision.
    ``mode='static'`` uses a rigid wall; ``mode='dynamic'`` a PBD wall driven by the heartbeat
    and pushed by the catheter body, with the target moving with its wall particle.

    **Action** ``Box(-1, 1, (3,), float32)``; values outside [-1, 1] are clipped, NaN/inf or a
    wrong shape raise ``ValueError``. With ``theta_max^t = theta_max * |delta_l| / L``:

    ===  =========  ====================================================================
    idx  name       mapping (see :mod:`cgail_sim.ftl_model`)
    ===  =========  ====================================================================
    0    alpha      bend about the tip x_A axis: ``a[0] * theta_max^t`` rad
    1    gamma      bend about the tip z_A axis: ``a[1] * theta_max^t`` rad
    2    delta_l    insertion along y_A: ``a[2] * v_max * dt`` m (0.5 mm at the defaults;
                    negative = retraction along the body, bends ignored)
    ===  =========  ====================================================================

    **Observation** ``Box(float32, (41,))`` (:data:`OBS_LAYOUT`; bounds +-1 for the axes, [0, 1]
    for the rays, [0, 5] for u and +-5 (:data:`OBS_BOUND`) for position and v, which hold by
    construction since the episode ends 10 mm outside the anatomy's bounding box):

    =======  ===============  ====================================================================
    slice    name             content
    =======  ===============  ====================================================================
    0:3      tip_position     ``(p_t - origin) / position_scale`` (origin: anatomy bbox centre,
                              scale 0.15 m)
    3:6      tip_x_axis       x_A (first column of the tip rotation R), in [-1, 1]
    6:9      tip_heading      y_A (insertion direction)
    9:12     tip_z_axis       z_A
    12       target_distance  ``u = ||p_g - p_t|| / d_max``
    13:16    target_vector    ``v = (p_g - p_t) / d_max`` (phantom frame)
    16:41    rays             hit distance / ray_length (40 mm) in [0, 1] along 25 fixed rays
                              in the tip frame (:data:`RAY_DIRECTIONS`): ray 0 along y_A, then
                              rings of 8 at 30, 60 and 90 deg from y_A (azimuth 0, 45, ...,
                              315 deg from x_A towards z_A); 1 = no wall within the ray length
    =======  ===============  ====================================================================

    **Reward** (paper Table I, :mod:`cgail_sim.reward`): ``r_obst = -1`` on a non-minor
    collision (force >= 0.8 N or penetration), ``r_exit = -1`` when the tip leaves through the
    disc of an open end (:mod:`cgail_sim.exits`) or the anatomy's bounding box + 10 mm,
    ``r_target = +1`` when ``||p_t - p_g|| < epsilon``; every step ``r_step = -1e-5``, ``+0.05``
    per newly reached centerline waypoint (within 6 mm, the target's branch, once per episode) and
    ``r_bending = +1e-5`` when ``max(|alpha|, |gamma|) > 0.9 theta_max^t``.

    **Option sets** (:data:`cgail_sim.config.OPTION_SETS`): the tables above are
    ``ours``, the default. ``CatheterNavEnv(EnvConfig.from_options("paper_code"))`` follows the
    authors' Unity code instead: a 27-float observation (tip position in mm, quaternion
    ``(x, y, z, w)``, unit direction to the target, distance / 50 mm, 16 probes in two rings
    reading the nearest-wall distance in mm below 0.8 mm, else 1), forward-only insertion
    (``|a[2]|``), their reward values per 0.1 s decision (``r_step = -5e-5``, ``+0.005`` per
    waypoint within 3.5 mm, ``r_bending = +5e-5`` when ``|a0|`` or ``|a1|`` > 0.5, the target
    within 6.5 mm), their exit box instead of the open-end discs, a 20,000-step limit (theirs:
    none) and their 0.74 s heartbeat pushing the root up from below (``docs/fidelity.md``).

    **Step order**: catheter kinematics -> (dynamic) wall step to ``t + dt`` with the body as
    capsules, target follows its wall particle -> tip contact -> rays -> reward. Centerline
    waypoints are those of the rest shape in both modes.

    **Termination**: success, non-minor collision or exit. **Truncation**: ``max_steps`` steps
    (2000 = 200 s by default), or a **simulation fault**: the deformable wall raised
    :class:`~cgail_sim.wall.WallError` (a particle beyond ``PBDConfig.max_displacement``
    from rest, or a non-finite position). That step ends the episode as truncated, with
    ``info["simulation_fault"]`` True and the wall's message in
    ``info["simulation_fault_message"]`` (logged as a warning with the anatomy, start, target
    and step); its reward is the step's ``r_in`` only (``r_end = 0``, no success, collision or
    exit). Table I has no entry for it: a fault is the simulator's, not an outcome of the task,
    so it is neither rewarded nor punished, and, like the step limit, it truncates rather than
    terminates (a learner bootstraps from the last state instead of taking it as terminal).
    The wall is reset to rest for that step's sensing; the tools count these episodes as the
    outcome ``simulation fault``.

    **Info** (every step): ``success`` / ``is_success`` (bool), ``collision`` (non-minor, bool),
    ``exited`` (bool), ``collision_force`` (N), ``penetration`` (m), ``in_contact`` (bool),
    ``targeting_error`` (m, minimum tip-target distance so far: the paper's T_a), ``distance``
    (m, current), ``timesteps`` (steps so far: T_s), ``time`` (s), ``new_waypoints``,
    ``waypoints_reached``, ``bend`` (applied [alpha, gamma], rad), ``insertion`` (applied m),
    ``reward_end``/``reward_centerline``/``reward_bending``, ``simulation_fault`` (bool) and
    ``simulation_fault_message`` (str, empty without a fault), ``start``, ``target`` (ids; -1
    for a target drawn per episode),
    ``target_position`` (m), ``theta_max`` (rad).

    **Rendering**: ``render_mode='rgb_array'`` draws the anatomy, centerlines, scenarios and the
    catheter body (anterior view) with ``cgail_sim.render`` (matplotlib, ~1 s a frame:
    for inspection, not for training).

    **Reset options**: ``{'start': int, 'target': int}`` picks the scenario (default: drawn from
    the env's seeded generator; with ``EnvConfig.targets == "sphere"`` a reset that names no
    target draws a new one in the 30 mm sphere from that generator, :meth:`NavEngine.
    draw_target`); ``'start_pose': (position, rotation)`` puts the tip at that pose
    instead of the start's (replaying a demonstration from the pose it was recorded from).
    ``set_theta_max(rad)`` changes theta_max (curriculum).

    **Anatomy**: ``EnvConfig.anatomy``, or the ``anatomy`` keyword (``gym.make("CatheterNav-v0",
    anatomy="runs/patients/p07")``): a built-in name, a prepared anatomy directory, a mesh file
    with its landmarks, or an :class:`~cgail_sim.anatomy.Anatomy`.

    **Wall solver** (dynamic mode): ``pbd_config``, default :data:`DYNAMIC_PBD_CONFIG` (the
    calibrated wall with 5 Chebyshev-accelerated Gauss-Seidel sweeps per step, ~35 % cheaper
    than the 10 plain sweeps of ``PBDConfig()`` and as close to a converged solve). Pass
    ``PBDConfig()`` to match a :class:`~cgail_sim.wall.DeformableWall` built with its
    defaults.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 10}  # noqa: RUF012

    def __init__(self, config: EnvConfig | None = None, render_mode: str | None = None,
                 pbd_config: PBDConfig | None = None, *,
                 anatomy: AnatomySpec | None = None) -> None:
        if config is not None and not isinstance(config, EnvConfig):
            raise ValueError(f"config must be an EnvConfig, found {type(config).__name__}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', found {render_mode!r}")
        self.config = config or EnvConfig()
        if anatomy is not None:  # gym.make("CatheterNav-v0", anatomy=...)
            self.config = dataclasses.replace(self.config, anatomy=anatomy)
        self.engine = NavEngine(self.config, 1, pbd_config)
        self.observation_space = _observation_space(  # type: ignore[assignment]
            self.engine.spec)
        self.action_space = spaces.Box(  # type: ignore[assignment]
            -1.0, 1.0, shape=(3,), dtype=np.float32)
        self.render_mode = render_mode
        self._needs_reset = True

    @property
    def scenarios(self) -> Any:
        """The scenario set (starts, targets, d_max, origin)."""
        return self.engine.scenarios

    @property
    def anatomy(self) -> Any:
        """The anatomy the env runs in."""
        return self.engine.world.anatomy

    @property
    def catheter(self) -> CatheterBatch:
        """The (single-row) catheter state."""
        return self.engine.catheter

    def set_theta_max(self, theta_max: float) -> None:
        """Set the maximal bending angle theta_max, rad, in (0, pi] (curriculum)."""
        self.engine.catheter.set_theta_max(theta_max)

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[NDArray[np.float32], dict[str, Any]]:
        """Start an episode; ``options`` may fix ``start`` and ``target`` (ids)."""
        super().reset(seed=seed)
        opts = dict(options or {})
        unknown = set(opts) - {"start", "target", "start_pose"}
        if unknown:
            raise ValueError(f"options keys must be in ['start', 'start_pose', 'target'], "
                             f"found {sorted(unknown)}")
        sc = self.engine.scenarios
        start = int(opts.get("start", self.np_random.integers(len(sc.starts))))
        if "target" not in opts and self.config.targets == "sphere":
            self.engine.reset_env(0, start, -1, opts.get("start_pose"),
                                  self.engine.draw_target(self.np_random))
        else:
            target = int(opts.get("target", self.np_random.integers(len(sc.targets))))
            self.engine.reset_env(0, start, target, opts.get("start_pose"))
        self._needs_reset = False
        return self.engine.observe()[0], self._reset_info()

    def _reset_info(self) -> dict[str, Any]:
        e = self.engine
        return {
            "start": int(e.start_id[0]), "target": int(e.target_id[0]),
            "target_position": e.target[0].copy(), "distance": float(e.min_distance[0]),
            "theta_max": e.catheter.theta_max,
        }

    def step(self, action: Any) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        """One control step (see the class docstring)."""
        if self._needs_reset:
            raise RuntimeError("call reset() before step() (and after an episode ended)")
        a = validate_actions(action, 1, single=True)
        reward, terminated, truncated, arrays = self.engine.step(a)
        info = {k: (v[0].item() if v.ndim == 1 else v[0].copy()) for k, v in arrays.items()}
        info["is_success"] = info["success"]
        info.update(self._reset_info())
        info["distance"] = float(arrays["distance"][0])
        te, tr = bool(terminated[0]), bool(truncated[0])
        self._needs_reset = te or tr
        return self.engine.observe()[0], float(reward[0]), te, tr, info

    def render(self) -> NDArray[np.uint8] | None:  # type: ignore[override]
        """An (H, W, 3) uint8 image of the current state (``render_mode='rgb_array'``)."""
        if self.render_mode != "rgb_array":
            return None
        import tempfile

        import matplotlib.image as mpimg

        from cgail_sim.render import render_anatomy

        e = self.engine
        dist = float(np.linalg.norm(e.target[0] - e.catheter.tip_position[0]))
        title = f"{self.config.mode}: step {int(e.steps[0])}, distance {dist * 1e3:.1f} mm"
        with tempfile.TemporaryDirectory() as tmp:
            path = render_anatomy(e.world.anatomy, f"{tmp}/frame.png",
                                  centerlines=e.world.centerlines, rollout=e.catheter.body(0),
                                  views=("anterior",), title=title, dpi=80)
            img = mpimg.imread(str(path))
        if img.dtype != np.uint8:
            img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        return np.ascontiguousarray(img[..., :3])


def make_dynamic_env(**kwargs: Any) -> CatheterNavEnv:
    """Entry point of ``CatheterNavDynamic-v0``: ``CatheterNavEnv`` with ``mode='dynamic'``."""
    config = kwargs.pop("config", None) or EnvConfig()
    return CatheterNavEnv(dataclasses.replace(config, mode="dynamic"), **kwargs)

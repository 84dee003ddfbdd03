"""Scripted expert: pure pursuit of the centerline, guarded by a kinematically-constrained
sampling MPC over the catheter's action space.

Every ``replan_every`` steps the expert rolls action sequences out with the catheter's own
follow-the-leader kinematics (:mod:`cgail_sim.ftl_model`: per-step bend limit
``theta_max * delta_l / L``, insertion <= v_max * dt) over a horizon of ``stage1 + stage2 +
tail`` steps (64 mm at full insertion), against the wall as it is at planning time (in dynamic
mode deformed by the heartbeat and the catheter):

1. **Pursuit first.** The pure pursuit of the centerline (the carrot ``lookahead`` waypoints past
   the furthest one the predicted tip has come nearest to, or the target once within
   ``approach_distance``: the centerline follower's rule) is predicted over the whole horizon.
   If its tip keeps off the wall all the way, its first ``replan_every`` actions are executed.
2. **Sampled alternatives** otherwise, and in the final approach: 25 constant bends (a0, a1 in
   {-1, -0.5, 0, 0.5, 1}, full insertion) held for ``stage1`` steps or for twice as long, each
   followed by the same pursuit, and the pursuit itself. **Safety first**: only the sequences
   whose tip keeps off the wall longest count (the pursuit among them is taken); among them
   the best score wins:

   * **clearance**: at every point of the first ``stage1 + stage2`` steps, the inscribed-sphere
     radius of the nearest centerline point minus the distance to it, minus the catheter
     radius, and no more than the distance to the wall itself minus the catheter radius; a
     path whose clearance drops below ``min_clearance`` is penalised in proportion to the
     violation;
   * **progress**: distance of the path's end (after ``stage1 + stage2`` steps) to the carrot at
     planning time;
   * **target** (final approach): the closest predicted approach to the target (the task's
     success test).

Why pursuit first: on real aortas (``data/anatomies/avt``) the arch is about as tight as the
catheter's smallest bend radius (L / theta_max, 31.8 mm). A scorer that pulls the path's end
onto a carrot 14 mm ahead cuts corners and wiggles between full bends in the descending aorta,
and arrives at the arch on a line from which no bend clears the outer wall; the contact is
50-60 mm ahead of the choice that made it, beyond a short horizon. The pursuit keeps the tip
near the centerline, and the long horizon sees the arch coming. The wall beyond the target
(once the predicted tip is within ``epsilon`` of it: the episode would have ended) does not
count.

Only actions inside [-1, 1]^3 are produced, so the demonstrations respect the catheter's
constraints by construction. The expert reads the simulator's state (tip pose, target,
centerline), which a policy never sees.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any

import numpy as np

from cgail_learning.pursuit import carrot as pursuit_carrot
from cgail_learning.pursuit import rollout
from cgail_sim.ftl_model import steer_towards


@dataclass(frozen=True)
class ExpertConfig:
    """Sampling MPC settings."""

    stage1: int = 8
    """Steps each constant-bend primitive is held."""
    stage2: int = 24
    """Pure-pursuit steps after the primitive (the part of the horizon that is scored)."""
    tail: int = 96
    """Further pure-pursuit steps of each sequence, checked for wall contact only (is the
    sequence's end a state the pursuit can go on from without touching the wall?)."""
    replan_every: int = 4
    """Steps executed from one plan before re-planning."""
    lookahead: int = 6
    """Waypoints between the furthest reached one and the carrot."""
    min_clearance: float = 0.002
    """Wanted wall clearance of the tip surface, m."""
    approach_distance: float = 0.035
    """Below this tip-target distance the carrot is the target, m."""
    score_noise: float = 0.0005
    """Std of the score jitter of a seeded episode, m (diversity of the demonstrations)."""

    def __post_init__(self) -> None:
        if self.tail < 0:
            raise ValueError(f'tail must be >= 0, found {self.tail}')
        for name in ('stage1', 'stage2', 'replan_every', 'lookahead'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name} must be >= 1, found {getattr(self, name)}')
        if self.replan_every > self.stage1:
            raise ValueError(f'replan_every must be <= stage1 ({self.stage1}), found '
                             f'{self.replan_every}')


_LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)
_SHIFT_NEIGHBOURS = 24
"""Wall vertices whose mean displacement moves a centerline point in dynamic mode."""
_GRID = np.array([(a, b) for a in _LEVELS for b in _LEVELS])


class ScriptedExpert:
    """Plans for one :class:`cgail_sim.env.CatheterNavEnv` episode at a time."""

    def __init__(self, env: Any, cfg: ExpertConfig | None = None) -> None:
        self.env = env.unwrapped
        self.cfg = cfg or ExpertConfig()
        self._plan: list[np.ndarray] = []
        self._progress = 0
        self._rng: np.random.Generator | None = None
        self._lookahead = self.cfg.lookahead
        self._near: np.ndarray | None = None
        self._near_key: tuple[Any, ...] | None = None
        self._history: list[np.ndarray] = []
        self._swept: Any = None

    def reset(self, seed: int | None = None) -> None:
        """Forget the plan and the progress (call after ``env.reset``).

        With a seed, the sampled alternatives' scores get N(0, ``score_noise``) jitter, so
        demonstrations of the same start and target may differ while staying reproducible. The
        lookahead is not drawn (it was, in ``lookahead +- 2``): the pursuit's line through a
        tight real arch depends on it, and on AVT D11 a lookahead of 5 or 7 instead of 6 took
        the expert's static success on target sets 1-3 from 100 % to 73 %.
        """
        self._plan = []
        self._progress = 0
        self._history = []
        self._rng = None if seed is None else np.random.default_rng(seed)
        self._lookahead = self.cfg.lookahead

    # -------------------------------------------------------------- helpers
    def _centerline(self) -> tuple[np.ndarray, np.ndarray]:
        eng = self.env.engine
        cl = eng.world.centerlines[eng.branch[0]]
        return np.asarray(cl.points), np.asarray(cl.radii)

    def _wall_shift(self, pts_cl: np.ndarray) -> np.ndarray:
        """(P, 3) mean displacement from rest of the wall vertices nearest each centerline
        point, m (the ``_SHIFT_NEIGHBOURS`` rest vertices nearest it, found once)."""
        eng = self.env.engine
        wall = eng.walls[0]
        rest = np.asarray(eng.world.anatomy.vertices)
        key = (id(rest), len(pts_cl), float(pts_cl[0, 0]), float(pts_cl[-1, 2]))
        if self._near_key != key:
            from scipy.spatial import cKDTree

            self._near = cKDTree(rest).query(pts_cl, k=_SHIFT_NEIGHBOURS)[1]
            self._near_key = key
        disp = np.asarray(wall.vertices) - rest
        return np.asarray(disp[self._near].mean(axis=1))

    def _rollout(self, p: np.ndarray, R: np.ndarray, first: np.ndarray, hold: np.ndarray,
                 pts_cl: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted tip points (K, H, 3) of K sequences over the horizon H = ``stage1 +
        stage2 + tail`` and the actions (K, stage1 + stage2, 3) of their first ``stage1 +
        stage2`` steps.

        Sequence k holds ``first[k]`` for ``hold[k]`` steps, then pursues its own carrot
        (:mod:`cgail_learning.pursuit`: the centerline follower's rule, from the
        episode's progress)."""
        eng = self.env.engine
        T = self.cfg.stage1 + self.cfg.stage2
        return rollout(p, R, first, hold, pts_cl, self._progress, self._lookahead, target,
                       self.cfg.approach_distance, eng.config.catheter, eng.catheter.theta_max,
                       T + self.cfg.tail, T)

    def _wall_clearance(self, traj: np.ndarray, target: np.ndarray) -> np.ndarray:
        """(K, H) distance of the predicted tip surface from the wall, m, capped where it no
        longer changes a plan: at ``min_clearance`` over the scored first ``stage1 + stage2``
        steps, at 0 over the tail (only a touch counts there); +inf once the tip has come
        within ``epsilon`` of the target. The cap is the BVH's search radius, so the search
        stays local (the catheter radius + 2 mm, 3.5 mm over the tail, instead of 10 mm: a
        third of a dynamic episode's time, same plans)."""
        eng = self.env.engine
        radius = eng.config.catheter.outer_diameter / 2
        T = self.cfg.stage1 + self.cfg.stage2
        head, tail = self._wall_distance([(traj[:, :T], radius + self.cfg.min_clearance),
                                          (traj[:, T:], radius)])
        live = np.concatenate([head, tail], axis=1) - radius
        done = np.cumsum(np.linalg.norm(traj - target, axis=2) < eng.config.reward.epsilon,
                         axis=1) > 0
        return np.where(done, np.inf, live)

    def _wall_distance(self, parts: list[tuple[np.ndarray, float]]) -> list[np.ndarray]:
        """Distance from the wall of each part's points (..., 3), capped at the part's reach,
        m: in dynamic mode from the nearest of the wall's shapes over the last heartbeat."""
        eng = self.env.engine
        flat = [np.ascontiguousarray(pts.reshape(-1, 3), np.float64) for pts, _ in parts]
        dist = [eng.walls[0].distance_unchecked(f, reach)
                for f, (_, reach) in zip(flat, parts, strict=True)]
        if self._history:
            # The beating wall moves up to a few mm a step (the valve plane most): the
            # clearance is from the wall as it was at every step of the last heartbeat, which
            # it will be again (the swept wall), not only from its shape now.
            if self._swept is None:
                from cgail_sim.raycast import WallBVH

                an = eng.world.anatomy
                self._swept = WallBVH(an.vertices, an.faces, an.wall_face_mask)
            for shape in self._history:
                self._swept.refit(shape)
                dist = [np.minimum(d, self._swept.distance_unchecked(f, reach))
                        for d, f, (_, reach) in zip(dist, flat, parts, strict=True)]
        return [np.minimum(d, reach).reshape(pts.shape[:-1])
                for d, (pts, reach) in zip(dist, parts, strict=True)]

    def act(self) -> np.ndarray:
        """Next normalised action for the env's current state (from the current plan while
        it lasts: the expert re-plans every ``replan_every`` steps)."""
        self._remember_wall()
        if self._plan:
            return self._plan.pop(0)
        return self._replan()

    def _remember_wall(self) -> None:
        """Keep the beating wall's shapes of the last heartbeat (one per step, dynamic mode)."""
        eng = self.env.engine
        if eng.config.mode != "dynamic":
            return
        wall = eng.walls[0]
        period = 60.0 / wall.heartbeat.config.heart_rate
        keep = math.ceil(period / eng.config.dt) + 1
        self._history.append(np.array(wall.vertices, dtype=np.float64))
        del self._history[:-keep]

    def label(self) -> np.ndarray:
        """The action the expert would take from the env's current state, planned afresh.

        For states the expert did not produce itself (DAgger, :mod:`cgail_learning.
        dagger`): the plan of an earlier state is dropped, so the answer depends only on the
        state and the progress made along the centerline this episode (and on the seed's score
        jitter, if :meth:`reset` was given one).
        """
        self._plan = []
        self._remember_wall()
        return self._replan()

    def _replan(self) -> np.ndarray:
        eng = self.env.engine
        p = eng.catheter.tip_position[0].copy()
        R = eng.catheter.tip_rotation[0].copy()
        target = eng.target[0].copy()
        pts_cl, radii = self._centerline()
        # (progress from the rest centerline; the carrot from the moved one, below)
        _, self._progress, _ = pursuit_carrot(p, pts_cl, self._progress, self._lookahead,
                                              target, self.cfg.approach_distance)
        if eng.config.mode == "dynamic":
            # The beating wall carries the root (and the target on it) several mm off the rest
            # shape the centerline was computed on: the centerline and its spheres move with
            # the mean displacement of the wall around each of their points.
            pts_cl = pts_cl + self._wall_shift(pts_cl)
        carrot, _, final = pursuit_carrot(p, pts_cl, self._progress, self._lookahead, target,
                                          self.cfg.approach_distance)
        cat_cfg = eng.config.catheter
        if not final:
            # 1. pursuit first: taken when it keeps off the wall over the whole horizon
            traj, acts = self._rollout(p, R, np.zeros((1, 3)), np.zeros(1, int), pts_cl,
                                       target)
            if (self._wall_clearance(traj, target) >= 0.0).all():
                self._plan = list(acts[0, :self.cfg.replan_every].astype(np.float32))
                return self._plan.pop(0)
        # 2. sampled alternatives: each constant bend held for stage1 steps, and for twice as
        # long (a tight arch needs the longer turn before pursuit takes over), and the pursuit
        pursuit = steer_towards(p, R, carrot, cat_cfg, eng.catheter.theta_max)
        bends = np.column_stack([_GRID, np.ones(len(_GRID))])
        first = np.concatenate([bends, bends, pursuit[None]])
        hold = np.concatenate([np.full(len(bends), self.cfg.stage1),
                               np.full(len(bends), 2 * self.cfg.stage1), [0]])
        traj, acts = self._rollout(p, R, first, hold, pts_cl, target)
        T = self.cfg.stage1 + self.cfg.stage2
        live = self._wall_clearance(traj, target)
        # safety first: how long each sequence, its tail included, keeps off the wall
        touch = live < 0.0
        survive = np.where(touch.any(axis=1), np.argmax(touch, axis=1), traj.shape[1])
        # clearance from the centerline's inscribed spheres, and no more than from the wall
        # itself (nearer than the spheres say where the wall is not round or has moved)
        head = traj[:, :T].reshape(-1, 3)
        d = np.linalg.norm(head[:, None, :] - pts_cl[None, :, :], axis=2)
        j = np.argmin(d, axis=1)
        clear = (radii[j] - d[np.arange(len(head)), j] - cat_cfg.outer_diameter / 2).reshape(
            len(traj), T)
        clear = np.minimum(clear, live[:, :T])
        violation = np.clip(self.cfg.min_clearance - clear, 0.0, None).max(axis=1)
        end_to_carrot = np.linalg.norm(traj[:, T - 1] - carrot, axis=1)
        closest_target = np.linalg.norm(traj[:, :T] - target, axis=2).min(axis=1)
        score = -end_to_carrot - 20.0 * violation
        if final:
            # a path predicted to reach the target (within 0.8 epsilon: margin for a target
            # that moves with the beating wall) gains nothing by going deeper: clearance
            # decides between such paths (a low target sits near the moving valve plane)
            eps = 0.8 * eng.config.reward.epsilon
            score = -np.maximum(closest_target - eps, 0.0) - 0.1 * closest_target \
                - 20.0 * violation
        if self._rng is not None:
            score = score + self._rng.normal(0.0, self.cfg.score_noise, score.shape)
        score = np.where(survive < survive.max(), -np.inf, score)
        best = int(np.argmax(score))
        if not final and survive[-1] == survive.max():
            best = len(first) - 1
        self._plan = list(acts[best, :self.cfg.replan_every].astype(np.float32))
        return self._plan.pop(0)


def run_expert_episode(env: Any, expert: ScriptedExpert, seed: int | None = None,
                       options: dict[str, Any] | None = None
                       ) -> tuple[list[np.ndarray], list[np.ndarray], dict[str, Any], list[Any]]:
    """One expert episode: (observations, actions, final info, per-step infos)."""
    obs, info = env.reset(seed=seed, options=options)
    expert.reset(seed)
    obs_l, act_l, infos = [], [], []
    while True:
        a = expert.act()
        obs_l.append(obs)
        act_l.append(a)
        obs, _, te, tr, info = env.step(a)
        infos.append(info)
        if te or tr:
            return obs_l, act_l, info, infos

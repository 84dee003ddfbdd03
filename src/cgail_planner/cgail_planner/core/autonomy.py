"""Autonomous navigation: controllers that drive the catheter from the tracked tip pose.

Pure numpy (and the planner core); no rclpy. Each controller maps the tip pose ``[R | p]``
(phantom frame, m) to a :class:`~cgail_planner.core.safety.Command` in the units of the rig's
command topics: insertion velocity in m/s (``catheter/insertion_command``, |v| <= 5 mm/s) and
the segment bend ``(bend_alpha, bend_gamma)`` in rad (``catheter/bend_command``, what
``pam_controller`` turns into pressures through its identified bending model). Every command
then goes through the :class:`~cgail_planner.core.safety.Supervisor`. Both controllers are
deterministic functions of their inputs.

* **path** (:class:`PathTracker`, the default): look-ahead pure pursuit on the planned path.
  The aim is the path point ``lookahead`` m of arc beyond the tip's projection
  (:class:`~cgail_planner.core.guidance.PathFollower`), and the bend is the guidance's own rule
  (:func:`~cgail_planner.core.guidance.suggested_bend`): the constant-curvature segment bend
  whose arc from the tip reaches the aim, ``|bend| = 2 L sin(theta) / d``, which is how the
  catheter model turns the tip (``bend * dl / L`` per inserted ``dl``). The insertion slows
  with the heading error (``cos theta``, floored at ``min_speed_fraction``) and near the goal.
* **policy** (:class:`PolicyController`): the ONNX C-GAIL policy on the tracked state. The
  observation is the planner's (:meth:`cgail_planner.core.planner.Planner.readings` and
  :meth:`~cgail_planner.core.planner.Planner.observation`: the one catheter model of
  :mod:`cgail_sim.ftl_model`, the policy's contract), and the action is read as the rig reads
  it (:func:`command_from_action`). The policy's contract must agree with the anatomy
  (:func:`policy_planner`), as for the planner.

Both stop at the goal by the operator's protocol (:func:`cgail_planner.core.operator.arrival`).
**Shared autonomy** (:func:`shared_command`): the person's stick deflections correct the
autonomy's command (the bend adds, the insertion overrides outside a deadzone).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cgail_planner.core.errors import ContractError, InvalidInputError
from cgail_planner.core.guidance import PathFollower, suggested_bend
from cgail_planner.core.operator import arrival
from cgail_planner.core.planner import (
    Planner,
    reconcile_contract,
    world_observation_spec,
)
from cgail_planner.core.safety import cap_bend, Command
from cgail_sim.ftl_model import CatheterConfig

FloatArray = NDArray[np.float64]

CONTROLLERS = ('path', 'policy')
AUTONOMY_MODES = ('autonomous', 'shared')


def command_from_action(action: Any, catheter: CatheterConfig) -> tuple[float, tuple[float,
                                                                                    float]]:
    """A normalised policy action ``a in [-1, 1]^3`` as rig commands.

    The catheter model steps ``delta_l = a2 v_max dt`` with step bends ``a0 theta_max |dl| /
    L`` (:func:`cgail_sim.ftl_model.action_to_command`), i.e. a segment bend ``a0 theta_max``
    held while inserting at ``a2 v_max`` (:func:`cgail_sim.ftl_model.segment_bend_step` is
    the inverse reading). Values beyond [-1, 1] are clipped; ``forward_only`` inserts ``|a2|``.

    Returns:
        ``(insertion velocity m/s, (bend_alpha, bend_gamma) rad)``.
    """
    a = np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[:3], -1.0, 1.0)
    a2 = abs(float(a[2])) if catheter.forward_only else float(a[2])
    return (a2 * catheter.max_insertion_speed,
            (float(a[0]) * catheter.theta_max, float(a[1]) * catheter.theta_max))


def action_from_command(insertion_velocity: float, bend: tuple[float, float],
                        catheter: CatheterConfig) -> FloatArray:
    """The normalised action of a rig command (:func:`command_from_action`'s inverse, saturated
    at +-1): what the simulator steps for it."""
    return np.clip(np.array([bend[0] / catheter.theta_max, bend[1] / catheter.theta_max,
                             insertion_velocity / catheter.max_insertion_speed]), -1.0, 1.0)


@dataclass(frozen=True)
class AutonomyConfig:
    """Settings of the controllers (the ``autonomy`` node's parameters of the same names)."""

    lookahead: float = 0.015
    """path: arc length from the tip's projection to the aimed path point, m (the simulator's
    pure-pursuit baseline's 15 mm); (0, 0.1]."""
    insertion_speed: float = 0.005
    """path: insertion speed on a straight stretch, m/s; (0, 0.005]."""
    min_speed_fraction: float = 0.3
    """path: floor of the ``cos(heading error)`` slow-down; (0, 1]."""
    slow_down_distance: float = 0.02
    """Both: within this distance of the goal the insertion slows linearly, m; (0, 0.2]."""
    min_insertion_fraction: float = 0.3
    """Both: the share of the insertion left at the goal; (0, 1]."""
    stop_distance: float = 0.002
    """Both: done within this distance of the goal, m; (0, 0.05]."""
    epsilon: float = 0.01
    """Both: once within this (the success radius), done when the distance grew by
    ``overshoot``, m; >= stop_distance, <= 0.1."""
    overshoot: float = 0.002
    """Both: the growth that marks the closest approach as passed, m; (0, 0.05]."""
    max_bend: float = math.pi / 2
    """path: cap of the bend magnitude, rad (the catheter model's theta_max caps it too);
    (0, pi/2]."""

    def __post_init__(self) -> None:
        for name, high in (('lookahead', 0.1), ('insertion_speed', 0.005),
                           ('min_speed_fraction', 1.0), ('slow_down_distance', 0.2),
                           ('min_insertion_fraction', 1.0), ('stop_distance', 0.05),
                           ('epsilon', 0.1), ('overshoot', 0.05), ('max_bend', math.pi / 2)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not (math.isfinite(value) and 0.0 < value <= high + 1e-12):
                raise ValueError(f'{name}: expected a number in (0, {high:g}], found {value!r}')
        if self.epsilon < self.stop_distance:
            raise ValueError(f'epsilon: expected >= stop_distance ({self.stop_distance}), '
                             f'found {self.epsilon!r}')


class Controller(Protocol):
    """What the node needs of a controller."""

    done: str | None

    def reset(self) -> None:
        """Forget the run (a new trial or a resume)."""

    def command(self, position: FloatArray, rotation: FloatArray, now: float) -> Command:
        """The command for the tip pose ``[rotation | position]`` at ``now`` (s)."""


class _Arrival:
    """The goal and the closest approach to it (:func:`~cgail_planner.core.operator.arrival`)."""

    def __init__(self, config: AutonomyConfig) -> None:
        self.config = config
        self.goal: FloatArray | None = None
        self.done: str | None = None
        self.min_distance = math.inf

    def reset(self) -> None:
        self.done = None
        self.min_distance = math.inf

    def set_goal(self, goal: FloatArray) -> None:
        g = np.asarray(goal, dtype=np.float64).reshape(-1)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise InvalidInputError(f'goal: expected a finite (3,) position, found {g.tolist()}')
        self.goal = g

    def speed_fraction(self, position: FloatArray) -> float:
        """1 far from the goal, ``min_insertion_fraction`` at it; 0 once done (and sets
        :attr:`done`)."""
        cfg = self.config
        if self.goal is None:
            raise InvalidInputError('goal: expected a goal (planner/goal or a path), found none')
        d = float(np.linalg.norm(self.goal - position))
        self.min_distance = min(self.min_distance, d)
        if self.done is None:
            self.done = arrival(d, self.min_distance, cfg.stop_distance, cfg.epsilon,
                                cfg.overshoot)
        if self.done is not None:
            return 0.0
        if d >= cfg.slow_down_distance:
            return 1.0
        frac = d / cfg.slow_down_distance
        return cfg.min_insertion_fraction + (1.0 - cfg.min_insertion_fraction) * frac


class PathTracker:
    """Look-ahead pure pursuit on the planned path (module docstring).

    Args:
        config: the controller settings.
        catheter: the catheter model (segment length L, theta_max).
    """

    def __init__(self, config: AutonomyConfig | None = None,
                 catheter: CatheterConfig | None = None) -> None:
        self.config = config or AutonomyConfig()
        self.catheter = catheter or CatheterConfig()
        self.follower: PathFollower | None = None
        self._arrival = _Arrival(self.config)
        self._goal_given = False

    @property
    def done(self) -> str | None:
        """Why the run ended at the goal, or None."""
        return self._arrival.done

    def reset(self) -> None:
        """Forget the run (the projection and the closest approach)."""
        self._arrival.reset()
        if self.follower is not None:
            self.follower.reset()

    def set_path(self, points: FloatArray) -> None:
        """Follow a new path (N, 3); its end is the goal unless one was given.

        Raises:
            ValueError: a path that is not (N >= 2, 3), finite and of positive length.
        """
        self.follower = PathFollower(points)
        if not self._goal_given:
            self._arrival.set_goal(self.follower.points[-1])

    def set_goal(self, goal: FloatArray) -> None:
        """The target (``planner/goal``): arrival and slow-down are measured to it."""
        self._arrival.set_goal(goal)
        self._goal_given = True

    def command(self, position: FloatArray, rotation: FloatArray, now: float) -> Command:
        """Bend towards the aimed path point, insert (module docstring).

        Raises:
            InvalidInputError: no path yet.
        """
        if self.follower is None:
            raise InvalidInputError('path: expected a planned path, found none')
        cfg, cat = self.config, self.catheter
        _, arc, _ = self.follower.project(position)
        aim = self.follower.point_at(arc + cfg.lookahead)
        alpha, gamma, theta = suggested_bend(position, rotation, aim, cat.segment_length,
                                             min(cfg.max_bend, cat.theta_max))
        speed = cfg.insertion_speed * max(math.cos(theta), cfg.min_speed_fraction)
        speed *= self._arrival.speed_fraction(position)
        return Command(speed, cap_bend((alpha, gamma), cfg.max_bend), now)


class PolicyController:
    """The ONNX policy on the tracked state (module docstring).

    Args:
        planner: a C-GAIL planner built from the policy's contract (:func:`policy_planner`):
            its observation, readings and policy are used, never its rollout.
        config: the arrival settings (the policy sets the speed; the slow-down near the goal
            scales it).
    """

    def __init__(self, planner: Planner, config: AutonomyConfig | None = None) -> None:
        if planner.policy is None:
            raise ValueError('planner: expected a planner with a policy, found none')
        self.planner = planner
        self.config = config or AutonomyConfig()
        self.catheter = planner.config.catheter
        self._arrival = _Arrival(self.config)

    @property
    def done(self) -> str | None:
        """Why the run ended at the goal, or None."""
        return self._arrival.done

    def reset(self) -> None:
        """Forget the closest approach."""
        self._arrival.reset()

    def set_goal(self, goal: FloatArray) -> None:
        """The target the policy observes (``planner/goal``)."""
        self._arrival.set_goal(goal)

    def command(self, position: FloatArray, rotation: FloatArray, now: float) -> Command:
        """One policy step on the tip pose.

        Raises:
            InvalidInputError: no goal yet, or a policy output that is not 3 finite values.
        """
        p = np.asarray(position, dtype=np.float64)
        r = np.asarray(rotation, dtype=np.float64)
        fraction = self._arrival.speed_fraction(p)
        goal = self._arrival.goal
        assert goal is not None and self.planner.policy is not None
        obs = self.planner.observation(p, r, goal, self.planner.readings(p, r))
        action = np.asarray(self.planner.policy(obs), dtype=np.float64).reshape(-1)
        if action.shape != (3,) or not np.isfinite(action).all():
            raise InvalidInputError(f'policy action: expected 3 finite values, found '
                                    f'{action.tolist()}')
        velocity, bend = command_from_action(action, self.catheter)
        return Command(velocity * fraction, bend, now)


def policy_planner(policy: Any, world: Any, wall: Any, *, anatomy: str, anatomy_hash: str,
                   mode: str) -> Planner:
    """The planner whose observation the policy controller uses, from the policy's contract.

    The contract is checked as the planner node checks it
    (:func:`~cgail_planner.core.planner.reconcile_contract`, no override).

    Args:
        policy: an :class:`~cgail_planner.core.onnx_policy.OnnxPolicy` (``.contract``).
        world: the simulator's world of the anatomy.
        wall: the wall the sensors read.
        anatomy: the anatomy's label (:func:`cgail_sim.anatomy_spec.anatomy_identity`).
        anatomy_hash: its content hash (``''`` for a built-in one).
        mode: ``static`` or ``dynamic``.

    Raises:
        ContractError: no contract, or one that disagrees with the anatomy.
    """
    contract = getattr(policy, 'contract', None)
    if contract is None:
        raise ContractError(f'policy: expected a catheter contract in '
                            f"{getattr(policy, 'path', 'the policy')}, found none (re-export "
                            'it with cgail export-onnx)')
    contract, _ = reconcile_contract(
        contract, anatomy=anatomy, anatomy_hash=anatomy_hash, mode=mode, theta_max=None,
        segment_length=None, override=False,
        world_spec=world_observation_spec(world.scenarios, contract))
    return Planner.from_contract(contract, world, wall, policy)


@dataclass(frozen=True)
class SharedConfig:
    """How the person's sticks correct the autonomy in shared mode."""

    scale_bend: float = 0.5
    """Bend added at full deflection of a bend stick, rad; (0, pi/2]."""
    scale_insertion: float = 0.005
    """Insertion velocity at full deflection of the insertion stick, m/s; (0, 0.005]."""
    insertion_deadzone: float = 0.1
    """Insertion deflections within this leave the autonomy's insertion; beyond it the stick's
    velocity replaces it (pull back to stop or retract); [0, 1)."""

    def __post_init__(self) -> None:
        for name, low, high, low_open in (('scale_bend', 0.0, math.pi / 2, True),
                                          ('scale_insertion', 0.0, 0.005, True),
                                          ('insertion_deadzone', 0.0, 1.0, False)):
            value = getattr(self, name)
            ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
                  and math.isfinite(value) and (value > low if low_open else value >= low)
                  and (value < high if name == 'insertion_deadzone' else value <= high + 1e-12))
            if not ok:
                raise ValueError(f"{name}: expected a number in {'(' if low_open else '['}"
                                 f"{low:g}, {high:g}{')' if name == 'insertion_deadzone' else ']'}"
                                 f', found {value!r}')


def shared_command(auto: Command, sticks: tuple[float, float, float],
                   config: SharedConfig) -> Command:
    """The autonomy's command corrected by the person's sticks.

    Args:
        auto: the controller's command.
        sticks: ``(insertion, alpha, gamma)`` deflections in [-1, 1] (clipped).
        config: the scales.

    Returns:
        The bend ``auto.bend + scale_bend * (alpha, gamma)``; the insertion ``scale_insertion *
        insertion`` when ``|insertion| > insertion_deadzone``, else the autonomy's. The
        supervisor caps the result.
    """
    s = [min(max(float(v), -1.0), 1.0) if math.isfinite(v) else 0.0 for v in sticks]
    velocity = config.scale_insertion * s[0] if abs(s[0]) > config.insertion_deadzone \
        else auto.insertion_velocity
    return Command(velocity, (auto.bend[0] + config.scale_bend * s[1],
                              auto.bend[1] + config.scale_bend * s[2]), auto.stamp)

"""Configuration of the catheter navigation environment (one frozen dataclass, validated).

**Option sets.** :data:`OPTION_SETS` names bundles of :class:`EnvConfig` values that are built
into their owners (the observation kind of :mod:`~cgail_sim.ftl_model`, its insertion
rule, the reward of :mod:`~cgail_sim.reward`, the heartbeat of
:mod:`~cgail_sim.heartbeat`):

* ``ours``: the defaults (what this project judges best; ``docs/fidelity.md``);
* ``paper_code``: the authors' Unity code and scene where ours differs: the 27-float
  observation with 16 probes in two rings, forward-only insertion, their reward values per
  decision and reach radii, their exit box (``exit_rule='box'``), a step limit that does not
  bind (:data:`PAPER_CODE_MAX_STEPS`: their ``MaxStep`` is 0, no limit) and their 0.74 s
  heartbeat pushing the root up from below;
* ``sphere_targets``: ``ours`` with a target drawn anew per episode in the 30 mm sphere
  (``targets``; the ``generalist`` preset trains in it, and its ``d_max`` is the sphere's bound,
  so ``evaluate`` rebuilds it from the policy's contract).

``EnvConfig.from_options("paper_code", mode="dynamic")`` builds one; :attr:`EnvConfig.options`
names the set a configuration follows (``custom`` when neither).
"""

from __future__ import annotations

from collections.abc import Mapping
import dataclasses
from dataclasses import dataclass, field
import math
from typing import Any

from cgail_sim.anatomy_spec import AnatomySpec, check_anatomy_spec
from cgail_sim.ftl_model import CatheterConfig, OBS_KINDS, ObservationConfig
from cgail_sim.heartbeat import HeartbeatConfig, PAPER_CODE_HEARTBEAT
from cgail_sim.reward import PAPER_CODE_REWARD, RewardConfig
from cgail_sim.scenarios import EXIT_RULES, TARGET_MODES

#: The catheter model's defaults (:mod:`cgail_sim.ftl_model`) the fields below start from.
_MODEL = CatheterConfig()
_OBS = ObservationConfig()

#: Simulation modes: ``static`` = rigid wall; ``dynamic`` = PBD wall + heartbeat + moving target.
MODES = ("static", "dynamic")
#: The ``paper_code`` step limit, env steps (2,000 s at 0.1 s): the authors' agent has
#: ``MaxStep: 0``, no limit (``shared/design/AUTHORS_SCENE.md``). Long enough never to bind
#: on an episode that keeps inserting: 5x their longest recorded episode (18,668 physics steps
#: = 3,734 decisions, ``Assets/OutPath/old1/distance.txt``), about 3x the largest mean episode
#: length of any of their runs (6,777). Only a policy that stops inserting meets it (in their
#: scene it would run for ever).
PAPER_CODE_MAX_STEPS = 20_000


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines a :class:`~cgail_sim.env.CatheterNavEnv`.

    Invalid values raise ``ValueError`` at construction, naming the field and the allowed range.
    """

    mode: str = "static"
    """``static`` (rigid wall) or ``dynamic`` (deformable wall, heartbeat, moving target)."""
    anatomy: AnatomySpec = "default"
    """The anatomy: a built-in name (``default``, ``elongated``), a prepared anatomy directory
    (``lumen.stl`` + ``lumen.yaml``), a mesh file with its ``<stem>.yaml`` landmarks, or an
    :class:`~cgail_sim.anatomy.Anatomy` (:func:`~cgail_sim.anatomy.
    resolve_anatomy`). A path is checked here and loaded when an env is built."""
    dt: float = _MODEL.dt
    """Control time step, s (0.1 s: 0.5 mm insertion per step at 5 mm/s); in [1 ms, 2 s]."""
    max_steps: int = 2000
    """Steps before truncation (2000 x 0.1 s = 200 s, past the 3-min rig limit); in [1, 1e6]."""
    theta_max: float = _MODEL.theta_max
    """Initial maximal bending angle, rad (paper: 90 deg; the curriculum lowers it); (0, pi]."""
    segment_length: float = _MODEL.segment_length
    """Steerable segment length L, m (paper: 50 mm); in [1 mm, 0.5 m]."""
    outer_diameter: float = _MODEL.outer_diameter
    """Catheter outer diameter, m (paper: 7 mm); in [0.5 mm, 20 mm]."""
    max_insertion_speed: float = _MODEL.max_insertion_speed
    """Maximal insertion speed, m/s (paper: 5 mm/s); in (0, 0.1]."""
    ray_length: float = _OBS.ray_length
    """Length of every observation ray, m (hits are normalised by it); in [5 mm, 0.2 m]."""
    position_scale: float = _OBS.position_scale
    """Tip positions are observed as ``(p - origin) / position_scale``, m; in [1 cm, 10 m]."""
    body_spacing: float = 0.005
    """Spacing of the body points handed to the deformable wall, m; in [0.5 mm, 0.1 m]."""
    scenario_seed: int = 0
    """Seed of the target sampling (the scenario set is fixed per anatomy and seed); >= 0."""
    n_waypoints: int = 100
    """Waypoints per centerline (paper: ~100); in [10, 1000]."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Reward values and thresholds (paper Table I)."""
    observation_kind: str = "ours"
    """Observation layout: ``ours`` (41 floats, rays) or ``paper_code`` (27 floats, probes;
    :mod:`cgail_sim.ftl_model`)."""
    forward_only: bool = False
    """Insertion rule: False retracts on ``a[2] < 0``; True inserts ``|a[2]|`` (the authors'
    code; :attr:`~cgail_sim.ftl_model.CatheterConfig.forward_only`)."""
    heartbeat: HeartbeatConfig = field(default_factory=HeartbeatConfig)
    """Annulus motion of the dynamic mode (:mod:`cgail_sim.heartbeat`)."""
    targets: str = "fixed"
    """Where a reset that names no target takes one from: ``fixed``, the scenario set's
    (``scenario_seed``; the paper's 5), or ``sphere``, drawn anew per episode in the 30 mm
    sphere by the scenario set's sampler (:class:`~cgail_sim.scenarios.TargetSampler`:
    inside the lumen, wall clearance, attached to a wall vertex, branch = nearer ostium). A reset
    that names a target id still takes the fixed set's. ``sphere`` also sets the observation's
    ``d_max`` to the sphere's bound (:attr:`~cgail_sim.scenarios.ScenarioSet.
    sphere_d_max`)."""

    exit_rule: str = "discs"
    """When the tip has left: ``discs`` (ours: a step through the disc of an open cut,
    :mod:`cgail_sim.exits`, or the anatomy's bounding box + 10 mm) or ``box`` (the authors'
    scene: only leaving the exit box of :func:`~cgail_sim.scenarios.paper_code_exit_box`,
    60-125 mm beyond the centreline; a tip out of an open end travels on until then)."""

    def __post_init__(self) -> None:
        """Validate every field.

        Raises:
            ValueError: a field out of its range, naming it; an anatomy that is not a name or a
                path to an anatomy (:class:`~cgail_sim.anatomy.AnatomyError`, naming
                the path and what was wrong).
        """
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, found {self.mode!r}")
        check_anatomy_spec(self.anatomy)  # (an AnatomyError is a ValueError)
        if not isinstance(self.max_steps, int) or not 1 <= self.max_steps <= 1_000_000:
            raise ValueError(f"max_steps must be an int in [1, 1000000], found {self.max_steps!r}")
        if not isinstance(self.scenario_seed, int) or self.scenario_seed < 0:
            raise ValueError(f"scenario_seed must be an int >= 0, found {self.scenario_seed!r}")
        if not isinstance(self.n_waypoints, int) or not 10 <= self.n_waypoints <= 1000:
            raise ValueError(
                f"n_waypoints must be an int in [10, 1000], found {self.n_waypoints!r}")
        for name, low, high in (("body_spacing", 5e-4, 0.1),):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and low <= value <= high):
                raise ValueError(f"{name} must be in [{low}, {high}], found {value!r}")
        if not isinstance(self.reward, RewardConfig):
            raise ValueError(f"reward must be a RewardConfig, found {type(self.reward).__name__}")
        if not isinstance(self.heartbeat, HeartbeatConfig):
            raise ValueError(f"heartbeat must be a HeartbeatConfig, found "
                             f"{type(self.heartbeat).__name__}")
        if self.targets not in TARGET_MODES:
            raise ValueError(f"targets must be one of {TARGET_MODES}, found {self.targets!r}")
        if self.exit_rule not in EXIT_RULES:
            raise ValueError(f"exit_rule must be one of {EXIT_RULES}, found {self.exit_rule!r}")
        if self.observation_kind not in OBS_KINDS:
            raise ValueError(f"observation_kind must be one of {OBS_KINDS}, found "
                             f"{self.observation_kind!r}")
        self.catheter  # noqa: B018 - validates dt, theta_max, segment_length, ...
        self.observation  # noqa: B018 - validates ray_length, position_scale

    @property
    def catheter(self) -> CatheterConfig:
        """The catheter's constraints as a :class:`CatheterConfig`."""
        return CatheterConfig(
            theta_max=self.theta_max, segment_length=self.segment_length,
            outer_diameter=self.outer_diameter, max_insertion_speed=self.max_insertion_speed,
            dt=self.dt, forward_only=self.forward_only,
        )

    @property
    def observation(self) -> ObservationConfig:
        """The observation normalisers as an :class:`ObservationConfig`."""
        return ObservationConfig(position_scale=self.position_scale, ray_length=self.ray_length,
                                 kind=self.observation_kind)

    @classmethod
    def from_options(cls, options: str = "ours", **fields: Any) -> EnvConfig:
        """The configuration of the option set ``options`` (:data:`OPTION_SETS`) with the other
        ``fields`` given (``mode``, ``anatomy``...).

        Raises:
            ValueError: an unknown option set, or a field the option set fixes.
        """
        check_options(options)
        bundle = OPTION_SETS[options]
        fixed = sorted(set(fields) & set(bundle))
        if fixed:
            raise ValueError(f"env options {options!r} fix {fixed}: expected the other "
                             f"EnvConfig fields, found them given too")
        return cls(**{**bundle, **fields})

    @property
    def options(self) -> str:
        """The option set this configuration follows (:data:`OPTION_SETS`), or ``custom``."""
        for name, bundle in OPTION_SETS.items():
            if all(getattr(self, k) == v for k, v in bundle.items()):
                return name
        return "custom"

    def with_options(self, options: str) -> EnvConfig:
        """This configuration with the values of option set ``options`` (:data:`OPTION_SETS`).

        Raises:
            ValueError: an unknown option set.
        """
        check_options(options)
        return dataclasses.replace(self, **OPTION_SETS[options])


#: The named env option sets (module docstring): the values of :class:`EnvConfig` each fixes.
OPTION_SETS: Mapping[str, Mapping[str, Any]] = {
    "ours": {"observation_kind": "ours", "forward_only": False, "reward": RewardConfig(),
             "heartbeat": HeartbeatConfig(), "targets": "fixed", "exit_rule": "discs"},
    "paper_code": {"observation_kind": "paper_code", "forward_only": True,
                   "reward": PAPER_CODE_REWARD, "heartbeat": PAPER_CODE_HEARTBEAT,
                   "targets": "fixed", "exit_rule": "box",
                   "max_steps": PAPER_CODE_MAX_STEPS},
    "sphere_targets": {"observation_kind": "ours", "forward_only": False,
                       "reward": RewardConfig(), "heartbeat": HeartbeatConfig(),
                       "targets": "sphere", "exit_rule": "discs"},
}


def check_options(options: Any) -> str:
    """``options`` if it names an option set, else ValueError ("expected one of ...")."""
    if not isinstance(options, str) or options not in OPTION_SETS:
        raise ValueError(f"env options: expected one of {sorted(OPTION_SETS)}, found "
                         f"{options!r}")
    return options

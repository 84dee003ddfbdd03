"""The catheter model: the one owner of the follow-the-leader (FTL) kinematics and the observation.

Everything that defines how the steerable catheter moves and what a policy observes lives here:
the parameters, the bend convention, the retraction rule, the observation specification, and
every form of one step and of one observation. The simulator (:mod:`cgail_sim.env`), the
planner's rollout (:mod:`cgail_planner.core.planner`, :mod:`cgail_planner.core.rollout_kernel`)
and the phantom's physics (:mod:`cgail_rig.core.phantom`) call these; none of them repeats a
number or a formula of the model. ``test_ftl_model.py`` holds the forms equal to each other and
``test_model_parity.py`` holds the env episode, the planner's two rollouts and the phantom to the
same tip path.

**Conventions** (SI units; the paper's numbers are quoted in mm/deg for readability; paper
section III-A):

* **Tip frame F_A.** The tip pose is ``q_t = [R | p]`` with ``R`` a 3x3 rotation matrix whose
  columns are the tip axes ``x_A, y_A, z_A`` expressed in the world frame ``phantom`` and ``p``
  the tip position. The catheter inserts along ``y_A`` (the heading).
* **Bend convention** (:data:`BEND_CONVENTION`). One step ``[alpha, gamma, delta_l]`` bends the
  tip by ``alpha`` about ``x_A`` and by ``gamma`` about ``z_A`` (intrinsic rotations, x first),
  then inserts by ``delta_l`` along the new heading::

      R_{t+1} = R_t @ Rx(alpha) @ Rz(gamma)
      p_{t+1} = p_t + delta_l * R_{t+1}[:, 1]

  so the paper's ``R(alpha, 0, gamma)`` (Euler x-y-z with zero y) is the per-step increment.
  Each step bend lies in ``[-theta_max^t, theta_max^t]`` with
  ``theta_max^t = theta_max * |delta_l| / L`` (paper eq. 2): the steerable segment of length
  ``L`` bent by a *segment bend* ``b`` (``|b| <= theta_max``) turns the heading by
  ``b |delta_l| / L`` per inserted ``delta_l`` (an arc of constant curvature ``b / L``). A
  policy's normalised bend ``a`` is the segment bend ``a * theta_max``; the rig's measured PAM
  bend is a segment bend in rad (:func:`segment_bend_step`).
* **Normalised actions.** Policies act in ``a in [-1, 1]^3`` (out-of-range values are clipped)::

      delta_l = a[2] * v_max * dt          (|a[2]| * v_max * dt when forward_only)
      alpha   = a[0] * theta_max^t(|delta_l|)
      gamma   = a[1] * theta_max^t(|delta_l|)

  ``CatheterConfig.forward_only`` (the ``paper_code`` option set) is the authors' insertion
  rule: a negative ``a[2]`` also advances the tip, and nothing retracts.

* **Body and retraction rule** (:data:`RETRACTION_RULE`). The body is the chain of tip poses
  (nodes) with their arc lengths; every inserting step appends the new tip pose. A body starts as
  an *introducer* from its proximal end (just outside the open descending end of the aorta) to
  the start pose (:func:`seed_body`): straight (:func:`introducer_tail`), or, where a straight
  one would leave the lumen, a bent tube along the centerline
  (:func:`cgail_sim.scenarios.introducer_path`). Retraction (``delta_l < 0``) slides
  the tip back along its own body by ``|delta_l|``: nodes passed are dropped, the tip is
  interpolated on the segment it stops on and keeps the orientation of that segment's distal
  node; bends are ignored while retracting. The tip stops at the proximal end of the
  introducer. The planner's rollout starts its body the same way from the tip pose it plans
  from.
* **Time step.** ``dt = 0.1 s`` with the maximal insertion speed ``5 mm/s``: ``|delta_l| <= 0.5
  mm`` and ``|alpha|, |gamma| <= 0.9 deg`` per step.

**Observation** (:class:`ObservationSpec`), one of two kinds (``ObservationConfig.kind``):

* ``ours`` (the default; layout :data:`OBS_LAYOUT`, 41 floats): the tip position relative to
  the anatomy's bounding-box centre over ``position_scale``, the tip axes,
  ``u = ||p_g - p_t|| / d_max`` and ``v = (p_g - p_t) / d_max``, and the hit distances of
  :data:`RAY_DIRECTIONS` (25 rays in the tip frame) over ``ray_length``, clipped to [0, 1].
  Every division is a division (no reciprocal multiplications), in the same order in every
  form, so the forms give the same float32 observation.
* ``paper_code`` (the authors' Unity code, ``docs/fidelity.md``; 27 floats): the tip position
  relative to the bounding-box centre in mm, the tip quaternion ``(x, y, z, w)`` with
  ``w >= 0``, the unit direction to the target, the distance over 50 mm, and 16 probe values:
  at each point of :data:`PROBE_OFFSETS` (two rings of 8 in the tip frame) the distance to the
  nearest wall point in mm where it is below :data:`PROBE_RANGE` (0.8 mm), else 1. One numba
  function (:func:`observe_probes_nb`) computes it for every form.

A form is handed the *sensor readings* of the pose: the rays' hit distances (``ours``, m,
``ray_length`` where nothing is hit) or the probes' nearest-wall distances (``paper_code``, m,
inf where no wall is within :data:`PROBE_RANGE`); :func:`sensor_points` places the sensors.

**Forms**, side by side below:

===================  ==========================  ==========================  ===================
what                 batched (the env)           single pose (Python)        numba (the kernel)
===================  ==========================  ==========================  ===================
action -> command    :func:`action_to_command`   :func:`action_to_command`   :func:`command_nb`
one inserting step   :func:`advance_batch`       :func:`advance_pose`        :func:`advance_nb`
steps at one bend    (as one step)               :func:`advance_pose_steps`  (as one step)
steer at a point     :func:`steer_towards`       :func:`steer_towards`       :func:`steer_nb`
retraction           :func:`retract_chain` (one numba implementation, called by every form)
observation          :func:`observe_batch`       :func:`observe_pose`        :func:`observe_nb`
paper_code obs.      :func:`observe_probes_nb` (one numba implementation, called by every form)
===================  ==========================  ==========================  ===================

**Contract.** :class:`PolicyContract` is the model a policy was trained and evaluated with
(parameters with the insertion rule, observation spec with its kind, anatomy, mode, env option
set, training notes); the ONNX export writes it into the model's metadata
(:data:`CONTRACT_KEY`) and the planner builds itself from it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
import json
import math
from typing import Any, NamedTuple

from numba import njit
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# ======================================================================== parameters
#: Default maximal bending angle theta_max (paper: 90 deg).
THETA_MAX_DEFAULT = math.pi / 2.0

#: Identifier of the bend convention of this module (module docstring); recorded in contracts.
BEND_CONVENTION = ("R <- R Rx(alpha) Rz(gamma); p <- p + delta_l R[:, 1]; "
                   "|alpha|, |gamma| <= theta_max |delta_l| / L")
#: Identifier of the retraction rule of this module (module docstring); recorded in contracts.
RETRACTION_RULE = "slide back along the body, distal node's rotation, stop at the introducer tail"


def _check_range(
    name: str, value: float, low: float, high: float, *, low_open: bool = False
) -> None:
    """Raise ValueError unless ``low <= value <= high`` (``low < value`` when ``low_open``)."""
    ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
          and math.isfinite(value) and (value > low if low_open else value >= low)
          and value <= high)
    if not ok:
        bracket = "(" if low_open else "["
        raise ValueError(f"{name} must be in {bracket}{low}, {high}], found {value!r}")


@dataclass(frozen=True)
class CatheterConfig:
    """Geometric and kinematic constraints of the steerable catheter (paper, section III-A)."""

    theta_max: float = THETA_MAX_DEFAULT
    """Maximal bending angle of the steerable segment, rad (paper: 90 deg); in (0, pi]."""
    segment_length: float = 0.050
    """Length L of the steerable distal segment, m (paper: 50 mm); in [1 mm, 0.5 m]."""
    outer_diameter: float = 0.007
    """Outer diameter of the catheter, m (paper: 7 mm); in [0.5 mm, 20 mm]."""
    max_insertion_speed: float = 0.005
    """Maximal insertion/retraction speed v_max, m/s (paper: 5 mm/s); in (0, 0.1]."""
    dt: float = 0.1
    """Control time step, s: ``|delta_l| <= v_max * dt`` (0.5 mm by default); in [1 ms, 2 s]."""
    forward_only: bool = False
    """Insertion rule. False (ours): ``a[2] < 0`` retracts along the body (the rig retracts).
    True (the authors' code, ``moveY = Mathf.Abs(a2)``; the ``paper_code`` option set): the tip
    inserts ``|a[2]| * v_max * dt``, so a negative ``a[2]`` also advances it."""

    def __post_init__(self) -> None:
        _check_range("theta_max", self.theta_max, 0.0, math.pi, low_open=True)
        _check_range("segment_length", self.segment_length, 1e-3, 0.5)
        _check_range("outer_diameter", self.outer_diameter, 5e-4, 0.02)
        _check_range("max_insertion_speed", self.max_insertion_speed, 0.0, 0.1, low_open=True)
        _check_range("dt", self.dt, 1e-3, 2.0)
        if not isinstance(self.forward_only, bool):
            raise ValueError(f"forward_only must be a bool, found {self.forward_only!r}")

    @property
    def radius(self) -> float:
        """Catheter (and tip sphere) radius, m."""
        return 0.5 * self.outer_diameter

    @property
    def max_step_insertion(self) -> float:
        """Largest insertion (or retraction) per step ``v_max * dt``, m."""
        return self.max_insertion_speed * self.dt


# ======================================================================== observation
#: Polar angles (deg from the heading ``y_A``) of the three rings of observation rays.
RAY_POLAR_DEG = (30.0, 60.0, 90.0)
#: Rays per ring, at azimuths 0, 360/n, ... deg measured from ``x_A`` towards ``z_A``.
RAY_AZIMUTHS = 8


def _ray_directions() -> FloatArray:
    """The fixed ray set in tip-frame coordinates ``(x_A, y_A, z_A)``: 25 unit vectors.

    Ray 0 points along the heading ``y_A``; rays 1-8, 9-16 and 17-24 form rings at polar angles
    :data:`RAY_POLAR_DEG` (30, 60 and 90 deg) from ``y_A``, at azimuths 0, 45, ..., 315 deg
    measured from ``x_A`` towards ``z_A``.
    """
    dirs = [np.array([0.0, 1.0, 0.0])]
    for polar in RAY_POLAR_DEG:
        th = math.radians(polar)
        for k in range(RAY_AZIMUTHS):
            az = math.radians(360.0 / RAY_AZIMUTHS * k)
            dirs.append(np.array([math.sin(th) * math.cos(az), math.cos(th),
                                  math.sin(th) * math.sin(az)]))
    out = np.array(dirs)
    out[np.abs(out) < 1e-15] = 0.0
    return out


#: (25, 3) ray directions in the tip frame (see :func:`_ray_directions`).
RAY_DIRECTIONS = _ray_directions()
RAY_DIRECTIONS.setflags(write=False)
N_RAYS = len(RAY_DIRECTIONS)

#: Observation kinds (:attr:`ObservationConfig.kind`): ours, and the authors' Unity code.
OBS_KINDS = ("ours", "paper_code")
#: ``paper_code`` probe rings ``(radius, distance ahead of the tip)``, m: the authors' code
#: places 8 probes at radius 7 mm, 1 mm ahead, and 8 at radius 9 mm, 15 mm ahead
#: (``docs/fidelity.md``, "Numbers the option set needs" 2).
PROBE_RINGS = ((0.007, 0.001), (0.009, 0.015))
#: A probe reads the nearest-wall distance where it is below this, m, else 1 (the authors'
#: 0.8 mm particle search radius).
PROBE_RANGE = 0.0008
#: ``paper_code`` target distance normaliser, m (the authors' fixed 50, not ``d_max``).
PROBE_DISTANCE_SCALE = 0.050
#: Entries of a ``paper_code`` observation before the probes (position, quaternion, direction,
#: distance).
PROBE_POSE_DIM = 11


def _probe_offsets() -> FloatArray:
    """The ``paper_code`` probe points in tip-frame coordinates ``(x_A, y_A, z_A)``, m: (16, 3).

    Probe ``j`` of ring ``k`` (:data:`PROBE_RINGS`) sits at azimuth ``j * 45`` deg, measured
    from ``x_A`` towards ``z_A`` as for :data:`RAY_DIRECTIONS`:
    ``(radius cos(az), ahead, radius sin(az))``.
    """
    out = []
    for radius, ahead in PROBE_RINGS:
        for j in range(RAY_AZIMUTHS):
            az = math.radians(360.0 / RAY_AZIMUTHS * j)
            out.append([radius * math.cos(az), ahead, radius * math.sin(az)])
    arr = np.array(out)
    arr[np.abs(arr) < 1e-15] = 0.0
    return arr


#: (16, 3) probe points in the tip frame, m (see :func:`_probe_offsets`).
PROBE_OFFSETS = _probe_offsets()
PROBE_OFFSETS.setflags(write=False)


class ObsField(NamedTuple):
    """One block of the observation vector."""

    name: str
    start: int
    stop: int
    description: str


def obs_layout(n_rays: int = N_RAYS, kind: str = "ours") -> tuple[ObsField, ...]:
    """The observation layout with ``n_rays`` rays (:data:`OBS_LAYOUT` for the default set),
    or with ``n_rays`` probes when ``kind`` is ``paper_code``."""
    if kind == "paper_code":
        return (
            ObsField("tip_position", 0, 3, "(p_t - origin) in mm, phantom frame"),
            ObsField("tip_quaternion", 3, 7, "rotation R as (x, y, z, w), w >= 0"),
            ObsField("target_direction", 7, 10, "(p_g - p_t) / ||p_g - p_t||, phantom frame"),
            ObsField("target_distance", 10, 11, "||p_g - p_t|| / 50 mm"),
            ObsField("probes", 11, 11 + n_rays,
                     "nearest-wall distance in mm where < 0.8 mm, else 1, at PROBE_OFFSETS"),
        )
    return (
        ObsField("tip_position", 0, 3, "(p_t - origin) / position_scale, phantom frame"),
        ObsField("tip_x_axis", 3, 6, "x_A: first column of the tip rotation R"),
        ObsField("tip_heading", 6, 9, "y_A: second column of R (insertion direction)"),
        ObsField("tip_z_axis", 9, 12, "z_A: third column of R"),
        ObsField("target_distance", 12, 13, "u = ||p_g - p_t|| / d_max"),
        ObsField("target_vector", 13, 16, "v = (p_g - p_t) / d_max, phantom frame"),
        ObsField("rays", 16, 16 + n_rays,
                 "hit distance / ray_length in [0, 1] along RAY_DIRECTIONS (1 = no wall)"),
    )


#: Observation layout (stored in the policy contract); see :class:`ObservationSpec`.
OBS_LAYOUT: tuple[ObsField, ...] = obs_layout()
OBS_DIM = OBS_LAYOUT[-1].stop
#: Entries before the rays (position, axes, u, v).
OBS_POSE_DIM = 16


@dataclass(frozen=True)
class ObservationConfig:
    """The anatomy-independent normalisers of the observation."""

    position_scale: float = 0.15
    """Tip positions are observed as ``(p - origin) / position_scale``, m; in [1 cm, 10 m]."""
    ray_length: float = 0.040
    """Length of every observation ray, m (hits are normalised by it); in [5 mm, 0.2 m]."""
    kind: str = "ours"
    """``ours`` (41 floats, rays) or ``paper_code`` (27 floats, probes: the authors' code; it
    uses neither ``position_scale`` nor ``ray_length``); module docstring."""

    def __post_init__(self) -> None:
        _check_range("position_scale", self.position_scale, 0.01, 10.0)
        _check_range("ray_length", self.ray_length, 0.005, 0.2)
        if self.kind not in OBS_KINDS:
            raise ValueError(f"observation kind must be one of {OBS_KINDS}, found "
                             f"{self.kind!r}")


@dataclass(frozen=True, eq=False)
class ObservationSpec:
    """Everything needed to build an observation: normalisers, anatomy frame and sensor set.

    Built from a scenario set by :meth:`for_world` (the env) or from a policy's contract
    (:meth:`from_dict`, the planner). ``config.kind`` selects the layout (module docstring):
    ``ours`` reads ``ray_directions``, ``paper_code`` reads ``probe_offsets``.
    """

    origin: FloatArray
    """(3,) observation origin: the anatomy's bounding-box centre, m."""
    d_max: float
    """Distance normaliser of ``u`` and ``v``, m (> 0; ``ours`` only)."""
    config: ObservationConfig = field(default_factory=ObservationConfig)
    """Kind, position scale and ray length."""
    ray_directions: FloatArray = field(default_factory=lambda: RAY_DIRECTIONS)
    """(R, 3) unit ray directions in the tip frame (``ours``)."""
    probe_offsets: FloatArray = field(default_factory=lambda: PROBE_OFFSETS)
    """(P, 3) probe points in the tip frame, m (``paper_code``)."""

    def __post_init__(self) -> None:
        origin = np.array(self.origin, dtype=np.float64)
        rays = np.ascontiguousarray(self.ray_directions, dtype=np.float64)
        probes = np.ascontiguousarray(self.probe_offsets, dtype=np.float64)
        if origin.shape != (3,) or not np.isfinite(origin).all():
            raise ValueError(f"origin must be a finite (3,) position, found {self.origin!r}")
        _check_range("d_max", self.d_max, 0.0, 100.0, low_open=True)
        if not isinstance(self.config, ObservationConfig):
            raise ValueError(f"config must be an ObservationConfig, found "
                             f"{type(self.config).__name__}")
        if rays.ndim != 2 or rays.shape[1] != 3 or len(rays) < 1 or not np.isfinite(rays).all() \
                or np.abs(np.linalg.norm(rays, axis=1) - 1.0).max() > 1e-9:
            raise ValueError(f"ray_directions must be (R, 3) unit vectors, found shape "
                             f"{rays.shape}")
        if probes.ndim != 2 or probes.shape[1] != 3 or len(probes) < 1 \
                or not np.isfinite(probes).all() or np.abs(probes).max() > 0.2:
            raise ValueError(f"probe_offsets must be (P, 3) finite points within 0.2 m of the "
                             f"tip, found shape {probes.shape}")
        for a in (origin, rays, probes):
            a.setflags(write=False)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "d_max", float(self.d_max))
        object.__setattr__(self, "ray_directions", rays)
        object.__setattr__(self, "probe_offsets", probes)

    @classmethod
    def for_world(cls, scenarios: Any, config: ObservationConfig | None = None, *,
                  d_max: float | None = None) -> ObservationSpec:
        """The spec of a scenario set (``origin``, and ``d_max`` unless given: the scenario
        set's :meth:`~cgail_sim.scenarios.ScenarioSet.d_max_for` its env's targets)
        with the default sensor sets."""
        return cls(origin=np.asarray(scenarios.origin),
                   d_max=float(scenarios.d_max if d_max is None else d_max),
                   config=config or ObservationConfig())

    @property
    def kind(self) -> str:
        """``ours`` or ``paper_code`` (:attr:`ObservationConfig.kind`)."""
        return self.config.kind

    @property
    def n_rays(self) -> int:
        """Number of sensors: rays R (``ours``) or probes P (``paper_code``)."""
        sensors = self.probe_offsets if self.kind == "paper_code" else self.ray_directions
        return int(sensors.shape[0])

    @property
    def dim(self) -> int:
        """Observation size: ``16 + R`` (``ours``) or ``11 + P`` (``paper_code``)."""
        return (PROBE_POSE_DIM if self.kind == "paper_code" else OBS_POSE_DIM) + self.n_rays

    @property
    def position_scale(self) -> float:
        """Position normaliser, m."""
        return self.config.position_scale

    @property
    def ray_length(self) -> float:
        """Ray length, m."""
        return self.config.ray_length

    @property
    def no_reading(self) -> float:
        """The sensor reading where no wall is sensed: ``ray_length`` for a ray, inf for a
        probe."""
        return math.inf if self.kind == "paper_code" else self.ray_length

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (the contract's ``observation``)."""
        out = {
            "kind": self.kind, "dim": self.dim,
            "fields": [f._asdict() for f in obs_layout(self.n_rays, self.kind)],
            "origin": self.origin.tolist(), "d_max": self.d_max,
            "position_scale": self.position_scale, "ray_length": self.ray_length,
            "ray_directions_tip_frame": self.ray_directions.tolist(),  # (exact in JSON)
        }
        if self.kind == "paper_code":
            out["probe_offsets_tip_frame_m"] = self.probe_offsets.tolist()
            out["probe_range_m"] = PROBE_RANGE
            out["distance_scale_m"] = PROBE_DISTANCE_SCALE
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ObservationSpec:
        """Inverse of :meth:`to_dict` (a dict without ``kind``, written before it existed, is
        ``ours``).

        Raises:
            ValueError: a missing key, a bad value, or a layout other than :func:`obs_layout`
                (the only ones this code can build).
        """
        try:
            kind = data.get("kind", "ours")
            probes = data.get("probe_offsets_tip_frame_m", PROBE_OFFSETS)
            spec = cls(origin=np.asarray(data["origin"], dtype=np.float64),
                       d_max=float(data["d_max"]),
                       config=ObservationConfig(position_scale=float(data["position_scale"]),
                                                ray_length=float(data["ray_length"]),
                                                kind=kind),
                       ray_directions=np.asarray(data["ray_directions_tip_frame"],
                                                 dtype=np.float64),
                       probe_offsets=np.asarray(probes, dtype=np.float64))
            fields = [ObsField(**f) for f in data["fields"]]
        except (KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"observation spec: expected the keys of ObservationSpec.to_dict, "
                             f"found {sorted(data) if isinstance(data, Mapping) else data!r} "
                             f"({exc})") from None
        if tuple(fields) != obs_layout(spec.n_rays, kind) or int(data["dim"]) != spec.dim:
            raise ValueError(f"observation layout: expected "
                             f"{[f.name for f in obs_layout(spec.n_rays, kind)]} "
                             f"(dim {spec.dim}), found {[f.name for f in fields]} "
                             f"(dim {data['dim']})")
        if kind == "paper_code":
            for key, want in (("probe_range_m", PROBE_RANGE),
                              ("distance_scale_m", PROBE_DISTANCE_SCALE)):
                if data.get(key) != want:
                    raise ValueError(f"observation {key}: expected {want!r}, found "
                                     f"{data.get(key)!r}")
        return spec

    def same_as(self, other: ObservationSpec, *, atol: float = 0.0) -> bool:
        """Whether two specs give the same observations (numbers within ``atol``)."""
        return (self.config == other.config and self.n_rays == other.n_rays
                and bool(np.allclose(self.origin, other.origin, rtol=0.0, atol=atol))
                and abs(self.d_max - other.d_max) <= atol
                and bool(np.allclose(self.ray_directions, other.ray_directions, rtol=0.0,
                                     atol=1e-12))
                and self.probe_offsets.shape == other.probe_offsets.shape
                and bool(np.allclose(self.probe_offsets, other.probe_offsets, rtol=0.0,
                                     atol=1e-12)))

# ------------------------------------------------------------------ observation: the forms
def observe_batch(spec: ObservationSpec, tips: FloatArray, rotations: FloatArray,
                  targets: FloatArray, hits: FloatArray) -> NDArray[np.float32]:
    """(N, dim) float32 observations of N tip poses (the env's form).

    Args:
        spec: observation spec.
        tips: (N, 3) tip positions, m.
        rotations: (N, 3, 3) tip rotations.
        targets: (N, 3) targets, m.
        hits: (N, R) sensor readings, m: ray hit distances (``ray_length`` where nothing is
            hit), or, for ``paper_code``, probe nearest-wall distances (inf where no wall is
            within :data:`PROBE_RANGE`).
    """
    n = tips.shape[0]
    if spec.kind == "paper_code":
        row = np.empty(spec.dim)
        out = np.empty((n, spec.dim), dtype=np.float32)
        for i in range(n):
            p, g = tips[i], targets[i]
            observe_probes_nb(row, p[0], p[1], p[2], rotations[i], g[0], g[1], g[2],
                              np.asarray(hits[i], dtype=np.float64), spec.origin)
            out[i] = row
        return out
    obs = np.empty((n, spec.dim), dtype=np.float32)
    obs[:, 0:3] = (tips - spec.origin) / spec.position_scale
    obs[:, 3:12] = rotations.transpose(0, 2, 1).reshape(n, 9)
    vec = (targets - tips) / spec.d_max
    obs[:, 12] = np.linalg.norm(vec, axis=1)
    obs[:, 13:16] = vec
    obs[:, 16:] = normalised_hits(hits, spec.ray_length)
    return obs


def observe_pose(spec: ObservationSpec, p: FloatArray, r: FloatArray, goal: FloatArray,
                 hits: FloatArray) -> NDArray[np.float32]:
    """(dim,) float32 observation of one tip pose ``[r | p]`` towards ``goal`` (single form).

    ``hits`` are the (R,) sensor readings (m) of that pose (:func:`observe_batch`).
    """
    if spec.kind == "paper_code":
        row = np.empty(spec.dim)
        observe_probes_nb(row, float(p[0]), float(p[1]), float(p[2]),
                          np.ascontiguousarray(r, dtype=np.float64), float(goal[0]),
                          float(goal[1]), float(goal[2]), np.asarray(hits, dtype=np.float64),
                          spec.origin)
        return row.astype(np.float32)
    obs = np.empty(spec.dim, dtype=np.float32)
    obs[0:3] = (p - spec.origin) / spec.position_scale
    obs[3:12] = r.T.reshape(9)
    vec = (goal - p) / spec.d_max
    vx, vy, vz = vec.tolist()
    obs[12] = math.sqrt(vx * vx + vy * vy + vz * vz)
    obs[13:16] = vec
    obs[16:] = normalised_hits(hits, spec.ray_length)
    return obs


def normalised_hits(hits: FloatArray, ray_length: float) -> FloatArray:
    """Ray hit distances (m) over ``ray_length``, clipped to [0, 1] (the observed rays)."""
    out = np.asarray(hits, dtype=np.float64) / ray_length
    np.minimum(out, 1.0, out=out)  # (as np.clip, cheaper on small arrays)
    np.maximum(out, 0.0, out=out)
    return out


@njit(cache=True)
def observe_nb(obs, px, py, pz, r, gx, gy, gz, hits, origin, position_scale, d_max, ray_length):
    """:func:`observe_pose` in numba: writes the float32-rounded observation into ``obs``
    ((16 + R,) float64) from the tip ``(px, py, pz)``, rotation ``r``, goal ``(gx, gy, gz)``
    and the (R,) hit distances ``hits``."""
    obs[0] = np.float32((px - origin[0]) / position_scale)
    obs[1] = np.float32((py - origin[1]) / position_scale)
    obs[2] = np.float32((pz - origin[2]) / position_scale)
    for i in range(3):
        for j in range(3):
            obs[3 + 3 * i + j] = np.float32(r[j, i])
    vx = (gx - px) / d_max
    vy = (gy - py) / d_max
    vz = (gz - pz) / d_max
    obs[12] = np.float32(math.sqrt(vx * vx + vy * vy + vz * vz))
    obs[13] = np.float32(vx)
    obs[14] = np.float32(vy)
    obs[15] = np.float32(vz)
    for k in range(hits.shape[0]):
        obs[16 + k] = np.float32(max(min(hits[k] / ray_length, 1.0), 0.0))


@njit(cache=True)
def quaternion_nb(r, q):
    """Write the unit quaternion ``(x, y, z, w)`` of rotation ``r`` (3, 3) into ``q`` (4,),
    with the sign that makes ``w >= 0`` (the authors' code does not fix a sign; this one is
    deterministic). Shepperd's method: the largest of ``w, x, y, z`` is taken from the
    diagonal, the others from the off-diagonal sums, so no branch divides by a small number.
    """
    t = r[0, 0] + r[1, 1] + r[2, 2]
    if t > 0.0:
        s = 2.0 * math.sqrt(t + 1.0)
        w, x = 0.25 * s, (r[2, 1] - r[1, 2]) / s
        y, z = (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        w, x = (r[2, 1] - r[1, 2]) / s, 0.25 * s
        y, z = (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        w, x = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s
        y, z = 0.25 * s, (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        w, x = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s
        y, z = (r[1, 2] + r[2, 1]) / s, 0.25 * s
    sign = -1.0 if w < 0.0 else 1.0
    q[0], q[1], q[2], q[3] = sign * x, sign * y, sign * z, sign * w


@njit(cache=True)
def observe_probes_nb(obs, px, py, pz, r, gx, gy, gz, dists, origin):
    """The ``paper_code`` observation (module docstring) of the tip ``(px, py, pz)`` with
    rotation ``r`` towards ``(gx, gy, gz)``, written float32-rounded into ``obs`` ((11 + P,)
    float64); ``dists`` are the (P,) probe nearest-wall distances, m (inf where none is within
    :data:`PROBE_RANGE`). Every form of the ``paper_code`` observation calls this."""
    obs[0] = np.float32((px - origin[0]) * 1000.0)
    obs[1] = np.float32((py - origin[1]) * 1000.0)
    obs[2] = np.float32((pz - origin[2]) * 1000.0)
    q = np.empty(4)
    quaternion_nb(r, q)
    for k in range(4):
        obs[3 + k] = np.float32(q[k])
    dx, dy, dz = gx - px, gy - py, gz - pz
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d > 0.0:
        obs[7], obs[8], obs[9] = np.float32(dx / d), np.float32(dy / d), np.float32(dz / d)
    else:  # (on the target: no direction)
        obs[7], obs[8], obs[9] = 0.0, 0.0, 0.0
    obs[10] = np.float32(d / PROBE_DISTANCE_SCALE)
    for k in range(dists.shape[0]):
        obs[11 + k] = np.float32(dists[k] * 1000.0) if dists[k] < PROBE_RANGE else 1.0


def sensor_points(spec: ObservationSpec, tips: FloatArray, rotations: FloatArray) -> FloatArray:
    """Where the sensors of N tip poses are, in the world frame: (N, S, 3).

    ``ours``: the ray directions ``R d`` (the rays start at the tip). ``paper_code``: the probe
    points ``p + R o``, m.
    """
    rots = np.asarray(rotations, dtype=np.float64)
    if spec.kind == "paper_code":
        return (np.asarray(tips, dtype=np.float64)[:, None, :]
                + np.matmul(spec.probe_offsets, rots.transpose(0, 2, 1)))
    return np.matmul(spec.ray_directions, rots.transpose(0, 2, 1))


# ======================================================================== one step
def bend_limit(delta_l: FloatArray | float, theta_max: float, segment_length: float) -> FloatArray:
    """Per-step bend limit ``theta_max^t = theta_max * |delta_l| / L`` (paper eq. 2), rad."""
    return theta_max * np.abs(np.asarray(delta_l, dtype=np.float64)) / segment_length


def action_to_command(
    action: FloatArray, theta_max: float, segment_length: float, max_step_insertion: float,
    forward_only: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Map normalised actions ``a in [-1, 1]^3`` to ``(alpha, gamma, delta_l)`` (any shape).

    Args:
        action: ``(..., 3)`` normalised actions; values outside [-1, 1] are clipped.
        theta_max: maximal bending angle, rad.
        segment_length: steerable segment length L, m.
        max_step_insertion: ``v_max * dt``, m.
        forward_only: insert ``|a[2]|`` (:attr:`CatheterConfig.forward_only`).

    Returns:
        ``alpha`` and ``gamma`` (rad) and ``delta_l`` (m), each of shape ``action.shape[:-1]``.
    """
    a = np.minimum(np.maximum(np.asarray(action, dtype=np.float64), -1.0), 1.0)  # (as np.clip)
    a2 = np.abs(a[..., 2]) if forward_only else a[..., 2]
    delta_l = a2 * max_step_insertion
    limit = bend_limit(delta_l, theta_max, segment_length)
    return a[..., 0] * limit, a[..., 1] * limit, delta_l


@njit(cache=True)
def command_nb(a0, a1, a2, theta_max, segment_length, max_step_insertion, forward_only):
    """:func:`action_to_command` of one action in numba: ``(alpha, gamma, delta_l)``."""
    a0 = min(max(a0, -1.0), 1.0)
    a1 = min(max(a1, -1.0), 1.0)
    a2 = min(max(a2, -1.0), 1.0)
    if forward_only:
        a2 = abs(a2)
    dl = a2 * max_step_insertion
    limit = theta_max * abs(dl) / segment_length
    return a0 * limit, a1 * limit, dl


def command_to_action(
    alpha: FloatArray | float,
    gamma: FloatArray | float,
    delta_l: FloatArray | float,
    theta_max: float,
    segment_length: float,
    max_step_insertion: float,
) -> FloatArray:
    """Inverse of :func:`action_to_command` (for experts and demonstrations).

    Bends beyond ``theta_max^t`` saturate at +-1; with ``delta_l == 0`` the bend entries are 0.
    """
    dl = np.clip(np.asarray(delta_l, dtype=np.float64), -max_step_insertion, max_step_insertion)
    limit = bend_limit(dl, theta_max, segment_length)
    safe = np.where(limit > 0.0, limit, 1.0)
    a0 = np.where(limit > 0.0, np.asarray(alpha, dtype=np.float64) / safe, 0.0)
    a1 = np.where(limit > 0.0, np.asarray(gamma, dtype=np.float64) / safe, 0.0)
    out = np.stack(np.broadcast_arrays(a0, a1, dl / max_step_insertion), axis=-1)
    return np.clip(out, -1.0, 1.0)


def segment_bend_step(bend: tuple[float, float], delta_l: float, theta_max: float,
                      segment_length: float) -> tuple[float, float]:
    """The step bends ``(alpha, gamma)`` of a segment bend ``bend`` (rad) over ``delta_l``.

    The rig's measured PAM bend is the bend of the whole steerable segment: as a normalised
    action it is ``bend / theta_max`` (saturated at +-1), so the step bends by
    ``bend * |delta_l| / L`` (module docstring), computed as :func:`action_to_command` does.
    """
    limit = float(bend_limit(delta_l, theta_max, segment_length))
    return (min(max(float(bend[0]) / theta_max, -1.0), 1.0) * limit,
            min(max(float(bend[1]) / theta_max, -1.0), 1.0) * limit)


def steer_towards(tip_position: FloatArray, tip_rotation: FloatArray, goal: FloatArray,
                  config: CatheterConfig, theta_max: float | None = None,
                  insertion: float = 1.0) -> FloatArray:
    """Normalised action that turns the heading as far as allowed towards ``goal``.

    One-step inverse kinematics of the bend: with ``d = R^T (goal - p)`` in the tip frame,
    ``Rx(alpha) Rz(gamma) e_y = (-sin g, cos g cos a, cos g sin a)`` points along ``d`` for
    ``alpha = atan2(d_z, d_y)`` and ``gamma = atan2(-d_x, hypot(d_y, d_z))``. The returned
    ``a[0], a[1]`` are those angles over the step's bend limit ``theta_max^t``, saturated at +-1,
    and ``a[2] = insertion``. Batched over a leading axis.

    Args:
        tip_position: (..., 3) tip positions.
        tip_rotation: (..., 3, 3) tip rotations.
        goal: (..., 3) points to aim at.
        config: catheter constraints.
        theta_max: current maximal bend (default ``config.theta_max``).
        insertion: normalised insertion ``a[2]`` in (0, 1].

    Returns:
        (..., 3) normalised actions for :func:`action_to_command`.
    """
    th = config.theta_max if theta_max is None else theta_max
    d = np.einsum("...ji,...j->...i", tip_rotation, np.asarray(goal) - tip_position)
    alpha = np.arctan2(d[..., 2], d[..., 1])
    gamma = np.arctan2(-d[..., 0], np.hypot(d[..., 1], d[..., 2]))
    limit = float(bend_limit(insertion * config.max_step_insertion, th, config.segment_length))
    a0 = np.clip(alpha / limit, -1.0, 1.0)
    a1 = np.clip(gamma / limit, -1.0, 1.0)
    return np.stack(np.broadcast_arrays(a0, a1, np.full_like(a0, insertion)), axis=-1)


@njit(cache=True)
def steer_nb(p, r, goal, limit):
    """:func:`steer_towards` of one pose in numba: ``(a0, a1)`` for the step bend limit
    ``limit`` (rad, > 0) of the insertion the caller commands."""
    g0, g1, g2 = goal[0] - p[0], goal[1] - p[1], goal[2] - p[2]
    d0 = r[0, 0] * g0 + r[1, 0] * g1 + r[2, 0] * g2
    d1 = r[0, 1] * g0 + r[1, 1] * g1 + r[2, 1] * g2
    d2 = r[0, 2] * g0 + r[1, 2] * g1 + r[2, 2] * g2
    alpha = math.atan2(d2, d1)
    gamma = math.atan2(-d0, math.hypot(d1, d2))
    return min(max(alpha / limit, -1.0), 1.0), min(max(gamma / limit, -1.0), 1.0)


def bend_rotation(alpha: FloatArray | float, gamma: FloatArray | float) -> FloatArray:
    """Batched ``Rx(alpha) @ Rz(gamma)``: ``(...,)`` angles -> ``(..., 3, 3)`` rotations.

    The closed form of ``scipy.spatial.transform.Rotation.from_euler('XZ', [alpha, gamma])``
    (tested equal), written out because it runs in every step.
    """
    ca, sa = np.cos(alpha), np.sin(alpha)
    cg, sg = np.cos(gamma), np.sin(gamma)
    # Rx(a) @ Rz(g) = [[cg, -sg, 0], [ca*sg, ca*cg, -sa], [sa*sg, sa*cg, ca]]
    out = np.empty((*np.broadcast(ca, cg).shape, 3, 3))
    out[..., 0, 0] = cg
    out[..., 0, 1] = -sg
    out[..., 0, 2] = 0.0
    out[..., 1, 0] = ca * sg
    out[..., 1, 1] = ca * cg
    out[..., 1, 2] = -sa
    out[..., 2, 0] = sa * sg
    out[..., 2, 1] = sa * cg
    out[..., 2, 2] = ca
    return out


def advance_batch(rotations: FloatArray, positions: FloatArray, alpha: FloatArray,
                  gamma: FloatArray, delta_l: FloatArray) -> tuple[FloatArray, FloatArray]:
    """One inserting step of N tips: ``(R @ Rx(alpha) Rz(gamma), p + delta_l y_A')``.

    Args:
        rotations: (N, 3, 3) tip rotations.
        positions: (N, 3) tip positions, m.
        alpha, gamma: (N,) step bends, rad (within the bend limit).
        delta_l: (N,) insertions, m (> 0).

    Returns:
        The new ``(rotations, positions)``.
    """
    r_new = rotations @ bend_rotation(alpha, gamma)
    return r_new, positions + delta_l[:, None] * r_new[:, :, 1]


def advance_pose(p: FloatArray, r: FloatArray, alpha: float, gamma: float, delta_l: float
                 ) -> tuple[FloatArray, FloatArray]:
    """:func:`advance_batch` of one tip: the new ``(position, rotation)`` (the bend matrix of
    :func:`bend_rotation` from Python floats: a third of its cost on one pose)."""
    ca, sa, cg, sg = math.cos(alpha), math.sin(alpha), math.cos(gamma), math.sin(gamma)
    bend = np.array([[cg, -sg, 0.0], [ca * sg, ca * cg, -sa], [sa * sg, sa * cg, ca]])
    r_new: FloatArray = r @ bend
    return p + delta_l * r_new[:, 1], r_new


def advance_pose_steps(p: FloatArray, r: FloatArray, alpha: float, gamma: float,
                       delta_l: float, steps: int) -> tuple[FloatArray, FloatArray]:
    """``steps`` calls of :func:`advance_pose` at one bend ``(alpha, gamma)``: the tip's
    positions ``(steps + 1, 3)`` (the start first) and its final rotation.

    The same arithmetic as the calls, so the same bits, with the bend matrix built once: the
    arc of a held bend (the planner's suggested-bend marker, the simulated bench's clamped
    segment: ~100 steps a reading) is this loop, and the matrix was most of each call's cost.
    """
    ca, sa, cg, sg = math.cos(alpha), math.sin(alpha), math.cos(gamma), math.sin(gamma)
    bend = np.array([[cg, -sg, 0.0], [ca * sg, ca * cg, -sa], [sa * sg, sa * cg, ca]])
    out = np.empty((steps + 1, 3))
    out[0] = p
    for k in range(1, steps + 1):
        r = r @ bend
        p = p + delta_l * r[:, 1]
        out[k] = p
    return out, r


@njit(cache=True)
def advance_nb(p, r, alpha, gamma, dl):
    """:func:`advance_pose` in numba, in place on ``p`` (3,) and ``r`` (3, 3)."""
    ca, sa, cg, sg = math.cos(alpha), math.sin(alpha), math.cos(gamma), math.sin(gamma)
    # r <- r @ [[cg, -sg, 0], [ca sg, ca cg, -sa], [sa sg, sa cg, ca]]
    b10, b11, b20, b21 = ca * sg, ca * cg, sa * sg, sa * cg
    for a in range(3):
        r0a, r1a, r2a = r[a, 0], r[a, 1], r[a, 2]
        r[a, 0] = r0a * cg + r1a * b10 + r2a * b20
        r[a, 1] = r0a * (-sg) + r1a * b11 + r2a * b21
        r[a, 2] = r0a * 0.0 + r1a * (-sa) + r2a * ca
    for a in range(3):
        p[a] = p[a] + dl * r[a, 1]


# ------------------------------------------------------------------ body and retraction
def introducer_tail(exit_point: FloatArray, exit_normal: FloatArray, position: FloatArray,
                    rotation: FloatArray) -> FloatArray:
    """(3,) proximal end of the straight body behind a start pose (the retraction limit).

    Straight back along ``-y_A`` to 5 mm beyond the exit plane (through ``exit_point``, unit
    ``exit_normal`` pointing out of the lumen), or straight out of the exit end when the heading
    does not point away from it.
    """
    n = np.asarray(exit_normal, dtype=np.float64)
    p = np.asarray(position, dtype=np.float64)
    h = np.asarray(rotation, dtype=np.float64)[:, 1]
    depth = float((p - exit_point) @ n)  # < 0 inside
    cos = float(h @ n)
    if cos < -0.2:
        return p - (depth - 0.005) / cos * h
    return np.asarray(exit_point, dtype=np.float64) + 0.005 * n


def _minimal_rotation(a: FloatArray, b: FloatArray) -> FloatArray:
    """(3, 3) the smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-12:
        raise ValueError(f"introducer must not turn back on itself, found directions "
                         f"{a.round(3).tolist()} and {b.round(3).tolist()}")
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def introducer_rotations(introducer: FloatArray, p0: FloatArray, r0: FloatArray) -> FloatArray:
    """(K, 3, 3) rotations of the introducer nodes ``introducer`` (K, 3) behind ``[r0 | p0]``.

    A straight introducer (K = 1) carries the start's rotation ``r0``. On a bent one, node ``j``
    carries ``r0`` turned by the smallest rotation from the start heading to the direction the
    tip travels when it reaches that node (node 0: the direction to node 1), so a tip retracted
    into the introducer faces along it, with no twist about its axis.
    """
    intro = np.asarray(introducer, dtype=np.float64).reshape(-1, 3)
    r0 = np.asarray(r0, dtype=np.float64)
    k = len(intro)
    out = np.empty((k, 3, 3))
    if k == 1:
        out[0] = r0
        return out
    nodes = np.vstack([intro, np.asarray(p0, dtype=np.float64)[None]])
    seg = np.diff(nodes, axis=0)
    length = np.linalg.norm(seg, axis=1)
    if not np.all(length > 1e-9):
        raise ValueError(f"introducer nodes must be distinct, found a segment of "
                         f"{float(length.min()):.3g} m")
    heading = seg / length[:, None]
    h0 = r0[:, 1]
    for j in range(k):
        d = heading[max(j - 1, 0)]
        out[j] = _minimal_rotation(h0, d) @ r0
    return out


def seed_body(positions: FloatArray, rotations: FloatArray, arc: FloatArray,
              introducer: FloatArray, p0: FloatArray, r0: FloatArray) -> int:
    """Write a new body into one chain: the introducer, then the tip at ``[r0 | p0]``.

    Args:
        positions: (C, 3) node positions of the chain (C > K).
        rotations: (C, 3, 3) node rotations.
        arc: (C,) node arc lengths from the proximal end.
        introducer: (3,) the proximal end of a straight introducer (:func:`introducer_tail`),
            or (K, 3) the nodes of a bent one, proximal end first, the start pose excluded.
        p0: (3,) start position.
        r0: (3, 3) start rotation.

    Returns:
        The number of nodes written, K + 1 (2 for a straight introducer; rotations from
        :func:`introducer_rotations`, arc lengths along the nodes).
    """
    intro = np.asarray(introducer, dtype=np.float64).reshape(-1, 3)
    p0 = np.asarray(p0, dtype=np.float64)
    k = len(intro)
    if k == 1:  # (the straight introducer, as it always was)
        positions[0] = intro[0]
        positions[1] = p0
        rotations[0] = r0
        rotations[1] = r0
        arc[0] = 0.0
        arc[1] = float(np.linalg.norm(p0 - intro[0]))
        return 2
    positions[:k] = intro
    positions[k] = p0
    rotations[:k] = introducer_rotations(intro, p0, r0)
    rotations[k] = r0
    arc[0] = 0.0
    arc[1:k + 1] = np.cumsum(np.linalg.norm(np.diff(positions[:k + 1], axis=0), axis=1))
    return k + 1


@njit(cache=True)
def retract_chain(positions, arc, n, distance):
    """The retraction rule (module docstring) on one chain; every form calls this one.

    Args:
        positions: (K, 3) node positions (modified: the new tip node may be interpolated).
        arc: (K,) arc length of each node from the proximal end, increasing (modified).
        n: number of valid nodes (>= 1); the last one is the tip.
        distance: how far to slide back, m (>= 0).

    Returns:
        ``(n_new, travelled)``: the number of nodes left and the arc length travelled, m. The
        tip's rotation is that of node ``n_new - 1`` (the distal node of the segment it stops
        on), whose rotation is unchanged.
    """
    s_tip = arc[n - 1]
    s_new = max(s_tip - distance, 0.0)
    k = n - 1
    while k > 0 and arc[k] > s_new:  # the last node at or below s_new
        k -= 1
    if s_new - arc[k] <= 1e-12 or k == n - 1:
        return k + 1, s_tip - s_new
    frac = (s_new - arc[k]) / (arc[k + 1] - arc[k])
    for a in range(3):
        positions[k + 1, a] = positions[k, a] + frac * (positions[k + 1, a] - positions[k, a])
    arc[k + 1] = s_new
    return k + 2, s_tip - s_new


def frame_from_heading(heading: FloatArray, up_hint: FloatArray | None = None) -> FloatArray:
    """A tip rotation whose y axis is ``heading``; x is chosen perpendicular to ``up_hint``.

    Args:
        heading: (3,) direction (normalised here).
        up_hint: (3,) vector the tip z axis should lean towards (default world +x, or +y when the
            heading is nearly parallel to x).

    Returns:
        (3, 3) rotation with columns ``x_A, y_A, z_A``.
    """
    y = np.asarray(heading, dtype=np.float64)
    norm = float(np.linalg.norm(y))
    if not math.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"heading must be a finite non-zero vector, found {heading!r}")
    y = y / norm
    hint = np.array([1.0, 0.0, 0.0]) if up_hint is None else np.asarray(up_hint, dtype=float)
    if abs(float(np.dot(hint, y))) > 0.95 * float(np.linalg.norm(hint)):
        hint = np.array([0.0, 1.0, 0.0]) if abs(y[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(y, hint)
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=1)


class CatheterBatch:
    """N follow-the-leader catheters; each body is a chain of tip poses (nodes).

    Node ``k`` of environment ``i`` has position ``positions[i, k]``, rotation
    ``rotations[i, k]`` and arc length ``arc[i, k]`` (m, measured from the first introducer node).
    ``n_nodes[i]`` nodes are valid; the last one is the tip.
    """

    def __init__(self, n_envs: int, config: CatheterConfig, capacity: int = 256,
                 max_step: float | None = None) -> None:
        if n_envs < 1:
            raise ValueError(f"n_envs must be >= 1, found {n_envs}")
        self.config = config
        #: Largest insertion per :meth:`step`, m (default ``config.max_step_insertion``).
        self.max_step = config.max_step_insertion if max_step is None else float(max_step)
        self.n_envs = n_envs
        self.theta_max = config.theta_max
        cap = max(int(capacity), 4)
        self.positions = np.zeros((n_envs, cap, 3))
        self.rotations = np.tile(np.eye(3), (n_envs, cap, 1, 1))
        self.arc = np.zeros((n_envs, cap))
        self.n_nodes = np.zeros(n_envs, dtype=np.int64)
        self._rows = np.arange(n_envs)

    # ------------------------------------------------------------------ state
    @property
    def capacity(self) -> int:
        """Number of nodes each chain can hold before the arrays grow."""
        return int(self.positions.shape[1])

    @property
    def tip_index(self) -> NDArray[np.int64]:
        """(N,) index of each tip node."""
        return self.n_nodes - 1

    @property
    def tip_position(self) -> FloatArray:
        """(N, 3) tip positions, m."""
        return self.positions[self._rows, self.tip_index]

    @property
    def tip_rotation(self) -> FloatArray:
        """(N, 3, 3) tip rotations (columns x_A, y_A, z_A)."""
        return self.rotations[self._rows, self.tip_index]

    @property
    def inserted_length(self) -> FloatArray:
        """(N,) arc length of the body from the first introducer node to the tip, m."""
        return self.arc[self._rows, self.tip_index]

    def set_theta_max(self, theta_max: float) -> None:
        """Change the maximal bending angle (curriculum), rad, in (0, pi]."""
        _check_range("theta_max", theta_max, 0.0, math.pi, low_open=True)
        self.theta_max = float(theta_max)

    def reset_env(self, i: int, start_position: FloatArray, start_rotation: FloatArray,
                  introducer: FloatArray) -> None:
        """Put catheter ``i`` at its start pose with its introducer behind it.

        Args:
            i: environment index.
            start_position: (3,) tip position, m.
            start_rotation: (3, 3) tip rotation.
            introducer: (3,) the proximal end of a straight introducer (outside the lumen,
                behind the start pose along ``-y_A``), or (K, 3) the nodes of a bent one,
                proximal end first (:func:`seed_body`).
        """
        k = np.asarray(introducer).reshape(-1, 3).shape[0]
        while k + 1 >= self.capacity:
            self._grow()
        self.n_nodes[i] = seed_body(self.positions[i], self.rotations[i], self.arc[i],
                                    introducer, start_position, start_rotation)

    def _grow(self) -> None:
        cap = self.capacity
        self.positions = np.concatenate([self.positions, np.zeros_like(self.positions)], axis=1)
        self.rotations = np.concatenate([self.rotations, np.zeros_like(self.rotations)], axis=1)
        self.arc = np.concatenate([self.arc, np.zeros_like(self.arc)], axis=1)
        self.rotations[:, cap:] = np.eye(3)

    # ------------------------------------------------------------------ motion
    def step(
        self, alpha: FloatArray, gamma: FloatArray, delta_l: FloatArray,
        active: NDArray[np.bool_] | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Advance every catheter by one command (already within the limits, see module doc).

        Args:
            alpha: (N,) bend about x_A, rad; clipped to +-theta_max^t.
            gamma: (N,) bend about z_A, rad; clipped to +-theta_max^t.
            delta_l: (N,) insertion (>0) or retraction (<0), m; clipped to +-max_step.
            active: (N,) bool, environments to move (default all).

        Returns:
            The applied ``(alpha, gamma, delta_l)``: bends are 0 while retracting and
            ``delta_l`` is the signed distance the tip actually travelled along the body.
        """
        if (self.n_envs == 1 and active is None and type(alpha) is np.ndarray
                and type(gamma) is np.ndarray and type(delta_l) is np.ndarray
                and alpha.shape == gamma.shape == delta_l.shape == (1,)):
            return self._step_one(float(alpha[0]), float(gamma[0]), float(delta_l[0]))
        cfg = self.config
        # (np.minimum/np.maximum: the same values as np.clip for finite input, a third of the
        # cost on the tiny arrays of a single environment)
        m = self.max_step
        dl = np.minimum(np.maximum(np.asarray(delta_l, dtype=np.float64), -m), m)
        limit = bend_limit(dl, self.theta_max, cfg.segment_length)
        al = np.minimum(np.maximum(np.asarray(alpha, dtype=np.float64), -limit), limit)
        ga = np.minimum(np.maximum(np.asarray(gamma, dtype=np.float64), -limit), limit)
        fwd = dl > 0.0
        back = dl < 0.0
        if active is not None:
            act = np.asarray(active, bool)
            fwd &= act
            back &= act
        applied_dl = np.zeros(self.n_envs)

        if fwd.any():
            idx = np.flatnonzero(fwd)
            tip = self.n_nodes[idx] - 1
            if int(tip.max()) + 1 >= self.capacity:
                self._grow()
            r_new, p_new = advance_batch(self.rotations[idx, tip], self.positions[idx, tip],
                                         al[idx], ga[idx], dl[idx])
            self.positions[idx, tip + 1] = p_new
            self.rotations[idx, tip + 1] = r_new
            self.arc[idx, tip + 1] = self.arc[idx, tip] + dl[idx]
            self.n_nodes[idx] += 1
            applied_dl[idx] = dl[idx]

        for i in np.flatnonzero(back):
            n, travelled = retract_chain(self.positions[i], self.arc[i], int(self.n_nodes[i]),
                                         float(-dl[i]))
            self.n_nodes[i] = n
            applied_dl[i] = -travelled
        applied_al = np.where(fwd, al, 0.0)
        applied_ga = np.where(fwd, ga, 0.0)
        return applied_al, applied_ga, applied_dl

    def _step_one(self, alpha: float, gamma: float, delta_l: float
                  ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """:meth:`step` of a single catheter (the simulated rig's, one per physics sub-step):
        the same operations on Python floats where :meth:`step` works on 1-element arrays
        (clamps as min/max, which like np.minimum/np.maximum return the first argument on a
        tie and propagate NaN; the bend limit in the same order), the step itself by
        :func:`advance_batch` on the same (1, 3, 3) and (1, 3) copies, so the same bits."""
        m = self.max_step
        dl = min(max(delta_l, -m), m)
        limit = self.theta_max * abs(dl) / self.config.segment_length
        applied = np.zeros(1)
        if dl > 0.0:
            al = min(max(alpha, -limit), limit)
            ga = min(max(gamma, -limit), limit)
            tip = int(self.n_nodes[0]) - 1
            if tip + 1 >= self.capacity:
                self._grow()
            idx, at = self._rows, np.array([tip])
            step = np.array([dl])
            r_new, p_new = advance_batch(self.rotations[idx, at], self.positions[idx, at],
                                         np.array([al]), np.array([ga]), step)
            self.positions[0, tip + 1] = p_new[0]
            self.rotations[0, tip + 1] = r_new[0]
            self.arc[0, tip + 1] = self.arc[0, tip] + dl
            self.n_nodes[0] += 1
            applied[0] = dl
            return np.array([al]), np.array([ga]), applied
        if dl < 0.0:
            n, travelled = retract_chain(self.positions[0], self.arc[0], int(self.n_nodes[0]),
                                         -dl)
            self.n_nodes[0] = n
            applied[0] = -travelled
        return np.zeros(1), np.zeros(1), applied

    # ------------------------------------------------------------------ body
    def body_points(self, i: int, spacing: float) -> FloatArray:
        """Body nodes of catheter ``i`` resampled every ``spacing`` m of arc, tip included.

        Returns:
            (B, 3) points from the proximal end to the tip (a capsule chain for the wall).
        """
        n = int(self.n_nodes[i])
        arc = self.arc[i, :n]
        marks = np.arange(0.0, float(arc[-1]), spacing)
        # sorted node indices (marks increase), duplicates dropped, the tip appended
        idx = np.minimum(np.searchsorted(arc, marks, side="left"), n - 1)
        keep = np.empty(idx.size + 1, dtype=bool)
        keep[0] = True
        np.not_equal(idx[1:], idx[:-1], out=keep[1:idx.size])
        idx = np.append(idx, n - 1)
        keep[-1] = idx.size == 1 or idx[-2] != n - 1
        return self.positions[i, idx[keep]]

    def body(self, i: int) -> FloatArray:
        """(n, 3) copy of all body nodes of catheter ``i``, proximal end first."""
        return self.positions[i, : int(self.n_nodes[i])].copy()


# ======================================================================== contract
#: ONNX metadata key of the contract (a JSON string of :meth:`PolicyContract.to_dict`).
CONTRACT_KEY = "catheter_contract"
#: Version of the contract's JSON layout.
CONTRACT_VERSION = 1


def describe_anatomy(label: str, content_hash: str) -> str:
    """An anatomy identity (:func:`cgail_sim.anatomy_spec.anatomy_identity`) in words."""
    if not content_hash:
        return f"built-in {label!r}"
    return f"{label!r} (content hash {content_hash})"


@dataclass(frozen=True, eq=False)
class PolicyContract:
    """The model a policy was trained and evaluated with; the planner builds itself from it.

    ``catheter.theta_max`` is the bend limit the policy's actions are scaled with when it runs
    (:func:`action_to_command`): the one its periodic evaluation (which picked the exported
    checkpoint) and the in-silico evaluation used. A curriculum that lowered theta_max during
    training is recorded in ``training`` (``curriculum_theta_max_deg``, ``final_theta_max_rad``).
    """

    catheter: CatheterConfig
    """Kinematic parameters."""
    observation: ObservationSpec
    """Observation normalisers, anatomy frame and ray set."""
    anatomy: str
    """Anatomy the policy was trained on (``origin`` and ``d_max`` are that anatomy's): a
    built-in name, or the label of a path anatomy (its directory name)."""
    mode: str
    """``static`` or ``dynamic``: the world it was trained in."""
    training: Mapping[str, Any] = field(default_factory=dict)
    """Notes on the training run (preset, steps, curriculum); informational."""
    anatomy_hash: str = ""
    """Content hash of a path anatomy (:attr:`cgail_sim.anatomy.Anatomy.content_hash`,
    what identifies it; :func:`cgail_sim.anatomy_spec.anatomy_identity`); ``""`` for a
    built-in anatomy, which its name identifies."""
    env_options: str = "ours"
    """The env option set the policy was trained in (:data:`cgail_sim.config.
    OPTION_SETS`: ``ours``, ``paper_code``, or ``custom`` for a configuration that is neither):
    what ``evaluate`` rebuilds its env with. Its observation and insertion rule are also in
    ``observation`` and ``catheter``, which the planner reads."""
    anatomies: str = "one"
    """``one``: trained in ``anatomy``, and runs there (another anatomy only with an
    override). ``population``: a generalist, trained across the anatomy population
    (:mod:`cgail_sim.population`); it runs in any anatomy, observed in that anatomy's
    frame (its own ``origin`` and ``d_max``; ``anatomy`` and ``observation`` then only record
    the anatomy its checkpoint was selected in)."""

    def __post_init__(self) -> None:
        if not isinstance(self.env_options, str) or not self.env_options:
            raise ValueError(f"env_options must be a non-empty name, found "
                             f"{self.env_options!r}")
        if self.mode not in ("static", "dynamic"):
            raise ValueError(f"mode must be 'static' or 'dynamic', found {self.mode!r}")
        if not isinstance(self.anatomy, str) or not self.anatomy:
            raise ValueError(f"anatomy must be a non-empty name, found {self.anatomy!r}")
        if self.anatomies not in ("one", "population"):
            raise ValueError(f"anatomies must be 'one' or 'population', found "
                             f"{self.anatomies!r}")
        if not isinstance(self.anatomy_hash, str) or not (
                self.anatomy_hash == "" or (len(self.anatomy_hash) == 16 and all(
                    c in "0123456789abcdef" for c in self.anatomy_hash))):
            raise ValueError(f"anatomy_hash must be '' or 16 hex digits, found "
                             f"{self.anatomy_hash!r}")

    def describe_anatomy(self) -> str:
        """The policy's anatomy in words, e.g. ``built-in 'default'`` or ``'p07' (content
        hash 606110321e2766a5)``."""
        return describe_anatomy(self.anatomy, self.anatomy_hash)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (what the ONNX metadata stores under :data:`CONTRACT_KEY`)."""
        return {
            "version": CONTRACT_VERSION,
            "catheter": asdict(self.catheter),
            "bend_convention": BEND_CONVENTION,
            "retraction_rule": RETRACTION_RULE,
            "action_scaling": {
                "names": ["alpha", "gamma", "delta_l"],
                "alpha_gamma": "a[0:2] * theta_max * |delta_l| / L (rad)",
                "delta_l": ("|a[2]|" if self.catheter.forward_only else "a[2]")
                + " * max_insertion_speed * dt (m)",
            },
            "observation": self.observation.to_dict(),
            "anatomy": self.anatomy,
            **({"anatomy_hash": self.anatomy_hash} if self.anatomy_hash else {}),
            "mode": self.mode,
            "env_options": self.env_options,
            **({"anatomies": self.anatomies} if self.anatomies != "one" else {}),
            "training": dict(self.training),
        }

    def to_json(self) -> str:
        """:meth:`to_dict` as a JSON string."""
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PolicyContract:
        """Inverse of :meth:`to_dict`.

        Raises:
            ValueError: another version, bend convention or retraction rule than this code's,
                a missing key or a bad value ("expected ..., found ...").
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"contract: expected a JSON object, found {type(data).__name__}")
        for key, want in (("version", CONTRACT_VERSION), ("bend_convention", BEND_CONVENTION),
                          ("retraction_rule", RETRACTION_RULE)):
            if data.get(key) != want:
                raise ValueError(f"contract {key}: expected {want!r}, found {data.get(key)!r}")
        try:
            catheter = CatheterConfig(**data["catheter"])
            observation = ObservationSpec.from_dict(data["observation"])
            return cls(catheter=catheter, observation=observation, anatomy=data["anatomy"],
                       mode=data["mode"], training=dict(data.get("training", {})),
                       anatomy_hash=data.get("anatomy_hash", ""),
                       env_options=data.get("env_options", "ours"),
                       anatomies=data.get("anatomies", "one"))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"contract: expected the keys of PolicyContract.to_dict, found "
                             f"{sorted(data)} ({exc})") from None

    @classmethod
    def from_json(cls, text: str) -> PolicyContract:
        """Parse :meth:`to_json` output (see :meth:`from_dict`)."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"contract: expected JSON, found {text[:40]!r}... ({exc})") from None
        return cls.from_dict(data)

"""The phantom's true catheter plant: chamber pressures and sleeve motion -> real bend and advance.

Pure numpy; no rclpy. The simulated phantom (:mod:`cgail_rig.nodes.phantom_node`) feeds it
only what a real catheter feels: the four PAM chamber pressures the regulator bank holds and the
catheter motion at the sleeve driver's gripper. It never sees a controller's estimate, and its
actuator model is its own, so the PAM controller's nominal model
(:mod:`pam_controller.core.bending_model`: a linear gain with a Prandtl-Ishlinskii operator) is
off by as much as a real, unidentified catheter would be. Each phantom draws its plant from the
sourced ranges (:meth:`PlantParams.sample`); :class:`IdealPlant` is the old world, where the
plant equals the controller's nominal model.

**Bend** (per step of ``dt``; chambers 0..3 = alpha+, alpha-, gamma+, gamma-, as in
``pam_controller.core.bending_model.CHAMBER_LABELS``)::

    p~_i  = g_i * max(p_i - p_dz, 0)                         dead zone, gain spread per muscle
    P_d, P_s = p~_pos - p~_neg,  p~_pos + p~_neg             per antagonistic pair
    q P_d th^2 - (1/G0 + beta P_s) th + P_d = 0              McKibben pair equilibrium -> th_s
    th_h  = th_s - H w,   dw = rho (dth_s - sigma |dth_s| w + (sigma - 1) dth_s |w|)
    [a; g]_target = [[cos phi_a, -sin phi_g], [sin phi_a, cos phi_g]] [th_h_alpha; th_h_gamma]
    tau d[a; g]/dt = [a; g]_target - [a; g]                  first-order lag (exact discretisation)

* The equilibrium is the moment balance of two McKibben muscles at offset ``r`` on a segment
  of bending stiffness ``K``, each with Tondu & Lopez's static force
  ``F = pi r0^2 P (a (1 - k eps)^2 - b)``, ``a = 3 / tan^2 alpha0``, ``b = 1 / sin^2 alpha0``
  (Chou & Hannaford 1996 with Tondu & Lopez's correction ``k``), the bending muscle shortening by
  ``eps = kappa th / k`` and its antagonist lengthening by as much. Divided by ``a - b``:
  ``beta = 2 a kappa / (a - b)`` (the force a muscle loses per rad of its own contraction: the
  common-mode pressure stiffens the joint) and ``q = a kappa^2 / (a - b)``. ``G0`` follows from
  the operating gain: ``1 / G0 = 1 / G_op - beta P_ref`` at the reference common mode ``P_ref``.
  The root taken is the one through 0, ``th_s = 2 P_d / (B + sqrt(B^2 - 4 q P_d^2))``.
* Hysteresis: the normalised rate-independent Bouc-Wen model with ``n = 1``
  (Ikhouane & Rodellar 2007), integrated exactly per monotone input increment (closed form, no
  sub-steps). ``w`` in [-1, 1] saturates on a monotone branch, so a major loop is ``2 H`` wide;
  ``rho`` sets how fast a branch turns after a reversal (smooth loops, unlike the controller's
  piecewise-linear PI model) and ``sigma`` its shape. It lags the bend behind the pressure
  (counter-clockwise loops in the pressure-bend plane).
* Cross-coupling: each pair bends in a plane turned by ``phi`` (misaligned chambers).

**Insertion** (per step, from the gripper-side catheter motion ``dg`` of the sleeve driver)::

    eta   = clip(eta0 - s_F F_load, 0, eta0)                 grip slip, worse under load
    x_p  += eta dg                                           proximal shaft
    x_tip = max(x_p - b, min(x_p, x_tip))                    shaft backlash (play of width b)

so the tip moves less than the motor, and a reversal first takes up ``b`` of slack. The load is
what the wall pushes back on the tip (:meth:`CatheterPlant.contact_load`), applied to insertion
only.

**Tip compliance.** A tip pressed into the wall deflects away from it instead of passing
through as a kinematic point: its heading turns inwards (towards the lumen) by the cantilever's
end slope, ``phi = 1.5 d / L + F L^2 / (2 EI)`` for an end deflection ``d`` (the penetration the
wall took back) or an end force ``F`` (a deformable wall's contact force), capped at
``phi_max`` (Gere & Timoshenko, end-loaded cantilever: slope ``F L^2 / 2EI``, deflection
``F L^3 / 3EI``). :class:`cgail_rig.core.phantom.PhantomPhysics` applies it.

Every number, with its source and sampled range, is in ``docs/plant.md`` and in the field
docstrings of :class:`PlantParams`. Where no primary source gives the number for this catheter,
the docstring says "estimate" and defends the range.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
import math
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: Sampled range ``(low, high)`` of each scalar parameter (uniform); sources in the field
#: docstrings and ``docs/plant.md``.
PARAM_RANGES: dict[str, tuple[float, float]] = {
    'dead_zone_pa': (5e3, 40e3),
    'gain_rad_per_pa': (0.8 * 2e-6 * math.pi, 1.2 * 2e-6 * math.pi),
    'braid_angle_rad': (math.radians(17.0), math.radians(25.0)),
    'contraction_per_rad': (0.03, 0.07),
    'hysteresis_half_width_rad': (0.08, 0.25),
    'hysteresis_turn': (0.5, 0.95),
    'hysteresis_shape': (0.6, 1.5),
    'lag_s': (0.05, 0.3),
    'insertion_efficiency': (0.85, 1.0),
    'slip_per_newton': (0.05, 0.4),
    'backlash_m': (0.3e-3, 3e-3),
    'flexural_rigidity_nm2': (1.5e-3, 6.5e-3),
}
#: Sampled range of each muscle's gain factor and of each pair's plane misalignment, rad.
MUSCLE_GAIN_RANGE = (0.9, 1.1)
MISALIGNMENT_RANGE = (-0.1, 0.1)

#: Allowed range ``[low, high]`` of every scalar (validation; wider than the sampled ranges).
_LIMITS: dict[str, tuple[float, float]] = {
    'dead_zone_pa': (0.0, 100e3),
    'gain_rad_per_pa': (1e-8, 1e-4),
    'reference_common_pa': (0.0, 800e3),
    'braid_angle_rad': (math.radians(5.0), math.radians(50.0)),
    'contraction_per_rad': (0.0, 0.2),
    'hysteresis_half_width_rad': (0.0, 0.5),
    'hysteresis_turn': (0.01, 1.0),
    'hysteresis_shape': (0.5, 5.0),
    'lag_s': (0.0, 5.0),
    'insertion_efficiency': (0.01, 1.0),
    'slip_per_newton': (0.0, 5.0),
    'backlash_m': (0.0, 0.01),
    'flexural_rigidity_nm2': (1e-5, 1.0),
    'max_tip_deflection_rad': (0.0, 1.0),
}


@dataclass(frozen=True)
class PlantParams:
    """Parameters of the true catheter plant (module docstring; sources in ``docs/plant.md``).

    The defaults are the nominal plant; :meth:`sample` draws one from the ranges.
    """

    dead_zone_pa: float = 20e3
    """Threshold pressure below which a muscle does not pull (bladder elasticity), Pa. Chou &
    Hannaford 1996 and Tondu & Lopez 2000 both report a threshold pressure for McKibben
    muscles; for thin-walled muscles of a few mm it is tens of kPa (estimate for this size).
    Sampled in [5, 40] kPa."""
    muscle_gain: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    """Gain factor of each muscle (alpha+, alpha-, gamma+, gamma-): the spread between
    nominally identical hand-made muscles (braid angle, bladder wall, length). Estimate: +-10 %
    (a braid angle off by 1 deg changes ``a - b`` by about 7 % at 20 deg, Tondu & Lopez 2000's
    force law). Sampled each in [0.9, 1.1]."""
    gain_rad_per_pa: float = 2e-6 * math.pi
    """Small-signal bend per Pa of differential pressure at the reference common mode, rad/Pa.
    Nominal: the controller's own nominal gain (1.2 x (pi/2) / 300 kPa, itself an estimate from
    the paper's 90 deg stroke; ``pam_controller.core.bending_model``). Sampled +-20 % around
    it: the accuracy of a stroke-based estimate before identification (estimate)."""
    reference_common_pa: float = 300e3
    """Sum of the two pressures of a pair at which ``gain_rad_per_pa`` holds, Pa: the
    controller's 150 kPa bias on both chambers. Not sampled."""
    braid_angle_rad: float = math.radians(20.0)
    """Initial braid angle ``alpha0`` of the McKibben muscles, rad, in the static force law of
    Chou & Hannaford 1996 / Tondu & Lopez 2000 (it must stay below 54.7 deg for the muscle to
    contract). Estimate: braids of about 20 deg are usual for contracting muscles; sampled in
    [17, 25] deg."""
    contraction_per_rad: float = 0.05
    """``kappa = k r / L_m``: a muscle's effective contraction per rad of segment bend. ``k``
    1.25 (Tondu & Lopez 2000's correction factor for the braid's end effects; estimate of its
    size, 1.1-1.4), muscle offset ``r`` 2 mm from
    the neutral axis of the 7 mm catheter (paper IV-B, outer diameter), muscle length ``L_m``
    50 mm (the steerable segment, paper IV-B). Sampled in [0.03, 0.07] (r 1.5-2.5 mm, k
    1.1-1.4)."""
    hysteresis_half_width_rad: float = 0.15
    """``H``: half the width of the major bend loop, rad (the loop is ``2 H`` = 17 deg wide,
    10 % of the +-90 deg range). McKibben muscles have a pressure-contraction hysteresis from
    braid-bladder friction (Chou & Hannaford 1996; Vo-Minh et al. 2011, IEEE/ASME TMech, model
    it with Maxwell-slip elements); Wu et al. 2021 (IEEE RA-L) model this PAM catheter's with an
    LSTM and publish no width a model could use. Estimate, the order of the controller's own
    PI loop (about 0.3 rad); sampled in [0.08, 0.25] rad (loops 5-16 % of the range)."""
    hysteresis_turn: float = 0.8
    """``c`` in (0, 1]: how sharply a branch turns after a reversal, as a share of the sharpest
    turn that keeps the bend monotone in the pressure. It sets Bouc-Wen's ``rho = c / (2 sigma
    H)`` (:attr:`hysteresis_rate_per_rad`): right after a reversal the bend moves at ``1 - c``
    times the anhysteretic rate, the way it does in the same direction as the pressure (a
    friction-dominated muscle stalls at a reversal, Chou & Hannaford 1996; it never moves back).
    A free ``rho`` did not: with ``2 sigma rho H > 1`` (the first draft: ``rho`` 8 /rad, ``H``
    0.15 rad) the bend kept rising for ~20 kPa after the pressure turned down, which no
    physical muscle does and no play-operator model can follow. ``c = 1`` is the stall of a
    play operator; estimate 0.8, sampled in [0.5, 0.95] (``rho`` 2.7 /rad at the nominal ``H``
    and ``sigma``: 95 % of the turn within ``3 / rho`` = 1.1 rad of anhysteretic bend, loops
    smoother than the controller's piecewise-linear ones)."""
    hysteresis_shape: float = 1.0
    """Bouc-Wen ``sigma`` (>= 1/2, Ikhouane & Rodellar 2007): above 1/2 a branch turns faster
    right after a reversal. Estimate; sampled in [0.6, 1.5]."""
    lag_s: float = 0.1
    """Time constant of the bend behind the regulator pressure, s: pneumatic line and muscle
    filling (the regulator's own 80 ms is in the simulated bank) plus the damped segment.
    Estimate: a bandwidth of 0.5-3 Hz for a few cm^3 of muscle behind 1-2 m of 2 mm tubing;
    sampled in [0.05, 0.3] s."""
    misalignment_rad: tuple[float, float] = (0.0, 0.0)
    """Angle of each pair's bending plane from its nominal axis (alpha pair, gamma pair), rad:
    the cross-coupling (a pure alpha pressure bends ``tan(phi_a)`` as much in gamma). Estimate:
    +-0.1 mm placement of a lumen at 2 mm from the axis of a multi-lumen extrusion is +-3 deg,
    plus twist of the segment; sampled each in [-0.1, 0.1] rad (+-6 deg)."""
    insertion_efficiency: float = 0.95
    """``eta0``: catheter advance per gripper advance without tip load (grip micro-slip and the
    shaft's friction in the introducer). Estimate (no slip figure is published for the rig's
    sleeve relay, Omar et al. 2023): a few percent of micro-slip per stroke; sampled in
    [0.85, 1.0]."""
    slip_per_newton: float = 0.15
    """``s_F``: loss of efficiency per N of tip load, 1/N. Estimate: a pneumatic gripper
    holding the catheter with a friction force of a few N slips more as the axial load
    approaches it; at the paper's 0.8 N minor-contact limit the efficiency drops by 12 %.
    Sampled in [0.05, 0.4] /N."""
    backlash_m: float = 1e-3
    """``b``: axial slack of the shaft in the introducer, m: a reversal moves the tip only after
    ``b`` of motion. Kesner & Howe 2011 (IEEE T-RO, "Position control of motion compensation
    cardiac catheters") measured and compensated a friction backlash, of the order of a
    millimetre, in the axial motion of a cardiac catheter in its sheath, larger in a more
    curved sheath. Sampled in [0.3, 3] mm."""
    flexural_rigidity_nm2: float = 2.5e-3
    """``EI`` of the steerable segment, N m^2: a 7 mm tube with a 1 mm wall (``I`` = 8.7e-11
    m^4) in a Pebax 35D-40D-like polymer (flexural modulus 20-75 MPa, Arkema data sheets);
    estimate. Sampled in [1.5e-3, 6.5e-3] N m^2."""
    max_tip_deflection_rad: float = 0.35
    """Cap on the tip's deflection away from the wall per contact, rad (20 deg): the
    small-deflection beam formula is not used beyond it. Not sampled."""

    def __post_init__(self) -> None:
        for name, (low, high) in _LIMITS.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and low <= value <= high):
                raise ValueError(f'{name} must be in [{low}, {high}], found {value!r}')
        gains = np.asarray(self.muscle_gain, dtype=np.float64)
        if gains.shape != (4,) or not np.all((gains > 0.0) & (gains <= 2.0)):
            raise ValueError(f'muscle_gain must be 4 numbers in (0, 2], found '
                             f'{self.muscle_gain!r}')
        phi = np.asarray(self.misalignment_rad, dtype=np.float64)
        if phi.shape != (2,) or not np.all(np.abs(phi) <= 0.5):
            raise ValueError(
                f'misalignment_rad must be 2 angles in [-0.5, 0.5], found '
                f'{self.misalignment_rad!r}')
        if self.beta * self.reference_common_pa >= 1.0 / self.gain_rad_per_pa:
            raise ValueError(
                f'gain_rad_per_pa must be below 1 / (beta * reference_common_pa) = '
                f'{1.0 / (self.beta * self.reference_common_pa):.3g}, found '
                f'{self.gain_rad_per_pa!r}')

    # -- derived McKibben constants --------------------------------------------------------
    @property
    def braid_a(self) -> float:
        """Tondu & Lopez's ``a = 3 / tan^2(alpha0)``."""
        return 3.0 / math.tan(self.braid_angle_rad) ** 2

    @property
    def braid_b(self) -> float:
        """Tondu & Lopez's ``b = 1 / sin^2(alpha0)``."""
        return 1.0 / math.sin(self.braid_angle_rad) ** 2

    @property
    def beta(self) -> float:
        """Stiffening per Pa of common-mode pressure, ``2 a kappa / (a - b)``, 1/rad."""
        a, b = self.braid_a, self.braid_b
        return 2.0 * a * self.contraction_per_rad / (a - b)

    @property
    def quadratic(self) -> float:
        """``q = a kappa^2 / (a - b)``, 1/rad^2."""
        a, b = self.braid_a, self.braid_b
        return a * self.contraction_per_rad ** 2 / (a - b)

    @property
    def inverse_g0(self) -> float:
        """``1 / G0 = 1 / G_op - beta P_ref``: the pair's stiffness without pressure, Pa/rad."""
        return 1.0 / self.gain_rad_per_pa - self.beta * self.reference_common_pa

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def nominal(cls) -> PlantParams:
        """The nominal plant: every parameter at its literature value."""
        return cls()

    @classmethod
    def sample(cls, rng: np.random.Generator) -> PlantParams:
        """Draw a plant from the sourced ranges (uniform in each), e.g. one per session.

        Args:
            rng: the session's generator (``np.random.default_rng(seed)``).
        """
        values: dict[str, Any] = {name: float(rng.uniform(low, high))
                                  for name, (low, high) in PARAM_RANGES.items()}
        values['muscle_gain'] = tuple(float(g) for g in rng.uniform(*MUSCLE_GAIN_RANGE, 4))
        values['misalignment_rad'] = tuple(float(p) for p in rng.uniform(*MISALIGNMENT_RANGE, 2))
        return cls(**values)

    @property
    def hysteresis_rate_per_rad(self) -> float:
        """Bouc-Wen ``rho`` (1/rad of anhysteretic bend) from :attr:`hysteresis_turn`."""
        return self.hysteresis_turn / (2.0 * self.hysteresis_shape
                                       * max(self.hysteresis_half_width_rad, 1e-9))

    def with_values(self, **changes: Any) -> PlantParams:
        """A copy with some fields changed (validated)."""
        return replace(self, **changes)

    def as_dict(self) -> dict[str, object]:
        """Every field by name (for logs and diagnostics)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def bouc_wen_update(w: float, dx: float, rho: float, sigma: float) -> float:
    """Exact rate-independent Bouc-Wen update (``n = 1``) for a monotone input change ``dx``.

    ``dw/dx = rho (1 - sigma sgn(dx) w + (sigma - 1) |w|)`` for ``dx > 0`` (odd in ``(w, dx)``):
    while ``w`` has the sign of ``dx`` it approaches ``sgn(dx)`` exponentially,
    ``1 - w' = (1 - w) exp(-rho dx)``; while it has the other sign, ``u = -sgn(dx) w`` obeys
    ``du/dx = -rho (1 + s u)`` with ``s = 2 sigma - 1``, solved in closed form until ``u`` hits 0.

    Args:
        w: current state in [-1, 1].
        dx: input increment (any size; the update is exact).
        rho: ``rho > 0``, 1/input unit.
        sigma: ``sigma >= 1/2``.
    """
    if dx == 0.0:
        return w
    sign = 1.0 if dx > 0.0 else -1.0
    v, d = sign * w, abs(dx)  # v: w in the direction of motion
    if v < 0.0:
        u = -v
        s = 2.0 * sigma - 1.0
        if s > 1e-12:
            to_zero = math.log1p(s * u) / (rho * s)
        else:
            to_zero = u / rho
        if d < to_zero:
            if s > 1e-12:
                u = u * math.exp(-rho * s * d) + math.expm1(-rho * s * d) / s
            else:
                u = u - rho * d
            return -sign * max(u, 0.0)
        d -= to_zero
        v = 0.0
    v = 1.0 - (1.0 - v) * math.exp(-rho * d)
    return sign * min(v, 1.0)


class Plant(Protocol):
    """What the phantom asks of a plant (:class:`CatheterPlant` or :class:`IdealPlant`)."""

    gripper: float
    """Sum of the gripper-side advances since the reset, m."""
    tip: float
    """The tip's position along the shaft, m (same origin as ``gripper``, up to the slack)."""

    def reset(self) -> None:
        """Straight, vented, no history."""

    def bend(self, pressures: ArrayLike, dt: float) -> tuple[float, float]:
        """The real ``(alpha, gamma)`` after ``dt`` s at the chamber pressures (Pa, 4)."""

    def advance(self, gripper_delta: float, load: float) -> float:
        """The tip's advance (m) for a gripper-side advance ``gripper_delta`` under ``load`` N."""

    def contact_load(self, penetration: float, force: float) -> float:
        """Axial load on the tip (N) of a wall contact."""

    def tip_deflection(self, penetration: float, force: float) -> float:
        """How far the tip's heading turns away from the wall in a contact, rad."""


def _check_pressures(pressures: ArrayLike) -> FloatArray:
    p = np.asarray(pressures, dtype=np.float64).reshape(-1)
    if p.shape != (4,) or not np.isfinite(p).all():
        raise ValueError(f'expected 4 finite chamber pressures, found {np.asarray(pressures)!r}')
    return p


def _check_dt(dt: float) -> float:
    if not (math.isfinite(dt) and dt > 0.0):
        raise ValueError(f'dt must be a positive number of seconds, found {dt!r}')
    return float(dt)


class CatheterPlant:
    """The true plant (module docstring).

    Args:
        params: the plant's parameters (e.g. :meth:`PlantParams.sample`).
        segment_length: length ``L`` of the steerable segment, m: the cantilever of the tip
            compliance (the catheter model's ``CatheterConfig.segment_length``).
    """

    def __init__(self, params: PlantParams | None = None, *,
                 segment_length: float = 0.05) -> None:
        if not (math.isfinite(segment_length) and segment_length > 0.0):
            raise ValueError(f'segment_length must be > 0 m, found {segment_length!r}')
        self.params = params if params is not None else PlantParams()
        self.segment_length = float(segment_length)
        p = self.params
        self._gains = np.asarray(p.muscle_gain, dtype=np.float64)
        ca, cg = math.cos(p.misalignment_rad[0]), math.cos(p.misalignment_rad[1])
        sa, sg = math.sin(p.misalignment_rad[0]), math.sin(p.misalignment_rad[1])
        self._coupling = np.array([[ca, -sg], [sa, cg]])
        self._inv_g0, self._beta, self._q = p.inverse_g0, p.beta, p.quadratic
        self.reset()

    def reset(self) -> None:
        """Straight, vented, virgin hysteresis, backlash slack centred."""
        self.static_bend = np.zeros(2)
        """Anhysteretic bend of each pair, rad (after the last :meth:`bend`)."""
        self.hysteretic_bend = np.zeros(2)
        """Bend of each pair after the hysteresis, before coupling and lag, rad."""
        self._w = np.zeros(2)
        self._bend = np.zeros(2)
        self.proximal = 0.0
        """Position of the shaft at the introducer (slip applied), m, from the reset."""
        self.tip = -0.5 * self.params.backlash_m
        """Position of the tip along the shaft (backlash applied), m, same origin."""
        self.gripper = 0.0
        """Sum of the gripper-side advances, m (the motor's view)."""

    # -- bend ------------------------------------------------------------------------------
    def static_pair_bend(self, pressures: ArrayLike) -> FloatArray:
        """Anhysteretic bend ``[th_alpha, th_gamma]`` (rad) of the two pairs at ``pressures``
        (Pa, 4): dead zone, muscle gains and the McKibben pair equilibrium (no state)."""
        p = _check_pressures(pressures)
        eff = self._gains * np.maximum(p - self.params.dead_zone_pa, 0.0)
        diff = eff[[0, 2]] - eff[[1, 3]]
        common = eff[[0, 2]] + eff[[1, 3]]
        b = self._inv_g0 + self._beta * common
        disc = np.maximum(b * b - 4.0 * self._q * diff * diff, 0.0)
        return 2.0 * diff / (b + np.sqrt(disc))

    def bend(self, pressures: ArrayLike, dt: float) -> tuple[float, float]:
        """Advance the bend by ``dt`` s at ``pressures`` (Pa, 4); returns ``(alpha, gamma)``."""
        dt = _check_dt(dt)
        p = self.params
        static = self.static_pair_bend(pressures)
        for c in range(2):
            self._w[c] = bouc_wen_update(float(self._w[c]), float(static[c] - self.static_bend[c]),
                                         p.hysteresis_rate_per_rad, p.hysteresis_shape)
        self.static_bend = static
        self.hysteretic_bend = static - p.hysteresis_half_width_rad * self._w
        target = self._coupling @ self.hysteretic_bend
        keep = math.exp(-dt / p.lag_s) if p.lag_s > 0.0 else 0.0
        self._bend = target + keep * (self._bend - target)
        return float(self._bend[0]), float(self._bend[1])

    # -- insertion -------------------------------------------------------------------------
    def efficiency(self, load: float) -> float:
        """Tip-side share of a gripper advance under an axial tip load ``load`` (N)."""
        p = self.params
        return min(max(p.insertion_efficiency - p.slip_per_newton * max(load, 0.0), 0.0),
                   p.insertion_efficiency)

    def advance(self, gripper_delta: float, load: float = 0.0) -> float:
        """The tip's advance (m) for a gripper-side catheter advance ``gripper_delta`` (m).

        Args:
            gripper_delta: catheter motion at the driver's gripper this step (motor side), m.
            load: axial load on the tip (N, :meth:`contact_load`); slows insertion only.
        """
        d = float(gripper_delta)
        if not math.isfinite(d):
            raise ValueError(f'gripper_delta must be finite, found {gripper_delta!r}')
        self.gripper += d
        eta = self.efficiency(load if d > 0.0 else 0.0)
        self.proximal += eta * d
        before = self.tip
        self.tip = max(self.proximal - self.params.backlash_m, min(self.proximal, self.tip))
        return self.tip - before

    # -- tip compliance --------------------------------------------------------------------
    @property
    def lateral_stiffness(self) -> float:
        """``3 EI / L^3``: end force per end deflection of the steerable segment, N/m."""
        return 3.0 * self.params.flexural_rigidity_nm2 / self.segment_length ** 3

    def contact_load(self, penetration: float, force: float) -> float:
        """Load (N) of a wall contact on the tip: the wall's own force (a deformable wall) plus
        the force that bends the tip by the penetration the wall took back (a rigid one)."""
        return max(force, 0.0) + self.lateral_stiffness * max(penetration, 0.0)

    def tip_deflection(self, penetration: float, force: float) -> float:
        """Slope (rad) by which the compliant tip turns away from the wall: the end slope of a
        cantilever of length ``L`` bent by ``penetration`` (``1.5 d / L``) or by an end force
        ``force`` (``F L^2 / 2EI``), capped at ``max_tip_deflection_rad``."""
        L = self.segment_length
        slope = (1.5 * max(penetration, 0.0) / L
                 + max(force, 0.0) * L * L / (2.0 * self.params.flexural_rigidity_nm2))
        return min(slope, self.params.max_tip_deflection_rad)


class IdealPlant:
    """The old world, for comparison: the plant IS the controller's nominal model.

    The bend is ``pam_controller``'s nominal :class:`~pam_controller.core.bending_model.
    BendingModel` evaluated forward on the true pressures (its estimate path: the PI operator),
    the tip advances exactly as the gripper, and the tip is a kinematic point (no compliance).
    """

    def __init__(self) -> None:
        from pam_controller.core.bending_model import BendingModel

        self.model = BendingModel()
        self.reset()

    def reset(self) -> None:
        """Virgin hysteresis; motion counters to 0."""
        self.model.reset()
        self.gripper = self.tip = 0.0

    def bend(self, pressures: ArrayLike, dt: float) -> tuple[float, float]:
        """The nominal model's bend at ``pressures`` (Pa, 4); ``dt`` is only checked."""
        _check_dt(dt)
        b = self.model.bend_from_pressures(_check_pressures(pressures))
        return float(b[0]), float(b[1])

    def advance(self, gripper_delta: float, load: float = 0.0) -> float:
        """The tip moves as the gripper."""
        d = float(gripper_delta)
        if not math.isfinite(d):
            raise ValueError(f'gripper_delta must be finite, found {gripper_delta!r}')
        self.gripper += d
        self.tip += d
        return d

    def contact_load(self, penetration: float, force: float) -> float:
        """No slip: the load is not used."""
        return 0.0

    def tip_deflection(self, penetration: float, force: float) -> float:
        """A kinematic tip: no deflection."""
        return 0.0


def make_plant(kind: str, seed: int, *,
               segment_length: float = 0.05) -> CatheterPlant | IdealPlant:
    """The phantom's plant: ``'true'`` (drawn from the ranges with ``seed``), ``'nominal'``
    (the true plant's structure at the nominal values) or ``'ideal'`` (:class:`IdealPlant`)."""
    if kind == 'true':
        return CatheterPlant(PlantParams.sample(np.random.default_rng(seed)),
                             segment_length=segment_length)
    if kind == 'nominal':
        return CatheterPlant(PlantParams.nominal(), segment_length=segment_length)
    if kind == 'ideal':
        return IdealPlant()
    raise ValueError(f"plant must be 'true', 'nominal' or 'ideal', found {kind!r}")

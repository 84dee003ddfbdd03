"""Bend (alpha, gamma) <-> four PAM chamber pressures, with Prandtl-Ishlinskii hysteresis.

The steerable segment (50 mm, max 90 deg; paper section IV-B, after Devreker 2015 and Wu 2021)
is bent by two antagonistic pairs of pneumatic artificial muscles (PAMs):

=======  ============  =================================================
index    label         effect when its pressure rises
=======  ============  =================================================
0        ``alpha_pos`` bends towards +alpha (rotation about the tip x axis)
1        ``alpha_neg`` bends towards -alpha
2        ``gamma_pos`` bends towards +gamma (rotation about the tip z axis)
3        ``gamma_neg`` bends towards -gamma
=======  ============  =================================================

Model::

    dp_alpha = p0 - p1,  dp_gamma = p2 - p3               (differential pressure, Pa)
    h_alpha = PI[dp_alpha],  h_gamma = PI[dp_gamma]        (Prandtl-Ishlinskii, core.hysteresis)
    [alpha; gamma] = b0 + K [h_alpha; h_gamma]             (per-axis offset, gain and coupling)
    K = [[s_alpha, c_ag], [c_ga, s_gamma]]
    p0, p1 = bias + dp_alpha / 2, bias - dp_alpha / 2      (antagonistic, common-mode bias)

``b0`` (:attr:`BendingModelConfig.bend_offset_rad`) is the bend at zero differential pressure
around the bias (unequal muscles of a pair), ``s`` (:attr:`BendingModelConfig.gain_scale`) each
axis's gain relative to the operator's common one, ``c`` (:attr:`BendingModelConfig.coupling`)
how much one pair bends the other axis (misaligned bending planes). Nominal: ``b0 = 0``,
``K = I``, the two axes decoupled and equal. The pressure -> bend direction
(:meth:`BendingModel.bend_from_pressures`, used on measured pressures) is the forward model and
the bend -> pressure direction (:meth:`BendingModel.pressures_for_bend`, used on commands) its
exact inverse from the current play state, ``h = K^-1 (bend - b0)`` then the PI inverse per
axis (feed-forward hysteresis compensation, Kuhnen 2003). ``identify_pam`` fits all of them on
the bench (:mod:`pam_controller.core.identification`).

Where the parameter values come from:

- pressure range 0..300 kPa gauge and bias 150 kPa: estimate (McKibben-type PAMs of this size
  run at a few bar; Devreker 2015 and Wu 2021 do not give a usable table);
- gain 2*pi*1e-6 rad/Pa = 1.2 x (pi/2) / 300 kPa: estimate chosen so the full differential
  range reaches the paper's 90 deg with a 20 % margin for the hysteresis lag;
- hysteresis (fraction 0.5 of the gain on 8 plays up to 100 kPa, decaying density): estimate
  giving a major loop about 10 % of the bend range wide, the order of magnitude of the
  input-output hysteresis reported for this PAM catheter in Wu et al. 2021, "Hysteresis
  modeling of robotic catheters based on long short-term memory network for improved
  environment reconstruction" (IEEE RA-L), who model it with an LSTM, so no PI parameters
  are published. Identify them on the rig (sinusoidal pressure sweeps + EM-tracked tip angle,
  least squares on the play weights) before relying on them.

Not modelled: the PAM's static nonlinearity (dead zone at low pressure, so the offset ``b0`` is
wrong for vented chambers; stiffening near full contraction), the lag of the bend behind the
pressure (rate dependence), contact with the vessel wall.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pam_controller.core.hysteresis import HysteresisConfig, PrandtlIshlinskii
from pam_controller.errors import CommandRejectedError

FloatArray = NDArray[np.float64]

CHAMBER_LABELS: tuple[str, str, str, str] = ('alpha_pos', 'alpha_neg', 'gamma_pos', 'gamma_neg')
"""Order of the four chambers everywhere (arrays, CAN channels 0..3, topic layout)."""

BEND_JOINT_NAMES: tuple[str, str] = ('bend_alpha', 'bend_gamma')
"""JointState names of the two bend angles (docs/interfaces.md)."""

HARD_MAX_PRESSURE_PA = 400e3
"""No configuration may set a maximum pressure above this (regulator rating, estimate; the CAN
setpoint signal encodes 0..409.5 kPa)."""

HARD_MAX_BEND_RAD = math.pi / 2.0
"""The catheter's maximum bend, 90 deg (paper section IV-B)."""

MAX_BEND_OFFSET_RAD = 0.5
"""Largest ``|bend_offset_rad|`` accepted, rad (29 deg; the plant's sampled muscles give up to
~0.15 rad, ``docs/plant.md``)."""

GAIN_SCALE_RANGE: tuple[float, float] = (0.5, 2.0)
"""Accepted range of each axis's ``gain_scale``."""

MAX_COUPLING = 0.5
"""Largest ``|coupling|`` accepted (a bending plane turned by 30 deg)."""


def _check_pair(name: str, value: tuple[float, float], low: float, high: float) -> None:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (2,) or not (np.isfinite(arr) & (arr >= low) & (arr <= high)).all():
        raise ValueError(f'{name} must be 2 numbers in [{low}, {high}], found {value!r}')


@dataclass(frozen=True)
class BendingModelConfig:
    """Pressure limits and the bend <-> pressure model parameters."""

    min_pressure_pa: float = 0.0
    """Lowest gauge pressure any chamber is commanded, Pa. In [0, max_pressure_pa)."""

    max_pressure_pa: float = 300e3
    """Highest gauge pressure any chamber is commanded, Pa (the pressure cap).
    In (min_pressure_pa, 400e3]."""

    bias_pressure_pa: float = 150e3
    """Common-mode pressure of each antagonistic pair, Pa; strictly between min and max."""

    max_bend_rad: float = HARD_MAX_BEND_RAD
    """Cap on the total bend ``hypot(alpha, gamma)``, rad, in (0, pi/2]."""

    hysteresis: HysteresisConfig = field(default_factory=HysteresisConfig)
    """The PI operator mapping differential pressure (Pa) to bend (rad) on each axis."""

    bend_offset_rad: tuple[float, float] = (0.0, 0.0)
    """``b0``: bend ``(alpha, gamma)`` at zero differential pressure around the bias, rad
    (unequal muscles of a pair: a gain spread of +-10 % and a dead zone give up to ~0.15 rad,
    ``docs/plant.md``). Each in [-0.5, 0.5] rad."""

    gain_scale: tuple[float, float] = (1.0, 1.0)
    """``(s_alpha, s_gamma)``: each axis's gain as a share of ``hysteresis.gain`` (the diagonal
    of ``K``). Each in [0.5, 2]."""

    coupling: tuple[float, float] = (0.0, 0.0)
    """``(c_ag, c_ga)``: the off-diagonal of ``K``, alpha bend per unit of the gamma operator's
    output and gamma per unit of alpha's (a bending plane turned by ``phi`` gives
    ``sin(phi)``). Each in [-0.5, 0.5], and ``det K >= 0.5 s_alpha s_gamma``
    (``K`` well inside the invertible range)."""

    def __post_init__(self) -> None:
        for name in ('min_pressure_pa', 'max_pressure_pa', 'bias_pressure_pa', 'max_bend_rad'):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ValueError(f'{name} must be a finite number, found {value}')
        _check_pair('bend_offset_rad', self.bend_offset_rad, -MAX_BEND_OFFSET_RAD,
                    MAX_BEND_OFFSET_RAD)
        _check_pair('gain_scale', self.gain_scale, *GAIN_SCALE_RANGE)
        _check_pair('coupling', self.coupling, -MAX_COUPLING, MAX_COUPLING)
        (sa, sg), (cag, cga) = self.gain_scale, self.coupling
        if not (sa * sg - cag * cga >= 0.5 * sa * sg):
            raise ValueError(
                f'coupling must keep det K = s_alpha s_gamma - c_ag c_ga >= 0.5 s_alpha s_gamma '
                f'= {0.5 * sa * sg:.6g}, found {sa * sg - cag * cga:.6g} (gain_scale '
                f'{self.gain_scale}, coupling {self.coupling})')
        if not (0.0 <= self.min_pressure_pa < self.max_pressure_pa):
            raise ValueError(
                f'min_pressure_pa must be in [0, max_pressure_pa={self.max_pressure_pa}), '
                f'found {self.min_pressure_pa}')
        if not (self.max_pressure_pa <= HARD_MAX_PRESSURE_PA):
            raise ValueError(
                f'max_pressure_pa must be <= {HARD_MAX_PRESSURE_PA}, found {self.max_pressure_pa}')
        if not (self.min_pressure_pa < self.bias_pressure_pa < self.max_pressure_pa):
            raise ValueError(
                f'bias_pressure_pa must be in ({self.min_pressure_pa}, {self.max_pressure_pa}), '
                f'found {self.bias_pressure_pa}')
        if not (0.0 < self.max_bend_rad <= HARD_MAX_BEND_RAD):
            raise ValueError(
                f'max_bend_rad must be in (0, {HARD_MAX_BEND_RAD}], found {self.max_bend_rad}')

    @property
    def axis_matrix(self) -> FloatArray:
        """``K = [[s_alpha, c_ag], [c_ga, s_gamma]]`` (module docstring)."""
        (sa, sg), (cag, cga) = self.gain_scale, self.coupling
        return np.array([[sa, cag], [cga, sg]], dtype=np.float64)

    @property
    def max_differential_pa(self) -> float:
        """Largest |p_pos - p_neg| reachable around the bias within the pressure limits."""
        return 2.0 * min(self.max_pressure_pa - self.bias_pressure_pa,
                         self.bias_pressure_pa - self.min_pressure_pa)


def check_bend(bend: ArrayLike, max_bend_rad: float) -> FloatArray:
    """Validate a bend command ``[alpha, gamma]`` (rad) and return it as an array.

    Raises:
        CommandRejectedError: wrong size, NaN/inf, or ``hypot(alpha, gamma) > max_bend_rad``.
    """
    arr = np.asarray(bend, dtype=np.float64).reshape(-1)
    if arr.shape != (2,):
        raise CommandRejectedError(f'expected 2 bend angles [alpha, gamma], found {arr.size}')
    if not np.isfinite(arr).all():
        raise CommandRejectedError(f'expected finite bend angles, found {arr.tolist()}')
    total = float(np.hypot(arr[0], arr[1]))
    if total > max_bend_rad + 1e-12:
        raise CommandRejectedError(
            f'expected total bend hypot(alpha, gamma) <= {max_bend_rad:.6f} rad, '
            f'found {total:.6f} rad (alpha={arr[0]:.6f}, gamma={arr[1]:.6f})')
    return arr


def check_pressures(pressures: ArrayLike) -> FloatArray:
    """Validate four chamber pressures (Pa); raises ``ValueError`` on wrong size or NaN/inf."""
    arr = np.asarray(pressures, dtype=np.float64).reshape(-1)
    if arr.shape != (4,):
        raise ValueError(f'expected 4 chamber pressures, found {arr.size}')
    if not np.isfinite(arr).all():
        raise ValueError(f'expected finite pressures, found {arr.tolist()}')
    return arr


class BendingModel:
    """Stateful bend <-> pressure model.

    It keeps two hysteresis states: the command path (what was sent, used to invert) and the
    estimate path (what was measured, used to estimate the bend). Both start virgin (straight,
    vented).
    """

    def __init__(self, config: BendingModelConfig | None = None) -> None:
        self.config = config if config is not None else BendingModelConfig()
        self._command = PrandtlIshlinskii(self.config.hysteresis, channels=2)
        self._estimate = PrandtlIshlinskii(self.config.hysteresis, channels=2)
        self._offset = np.asarray(self.config.bend_offset_rad, dtype=np.float64)
        self._k = self.config.axis_matrix
        self._k_inv = np.linalg.inv(self._k)

    def reset(self) -> None:
        """Forget both hysteresis histories."""
        self._command.reset()
        self._estimate.reset()

    def clip_pressures(self, pressures: ArrayLike) -> FloatArray:
        """Clip to ``[min_pressure_pa, max_pressure_pa]`` (NaN/inf raise ``ValueError``)."""
        arr = check_pressures(pressures)
        return arr.clip(self.config.min_pressure_pa, self.config.max_pressure_pa)

    def differential_to_pressures(self, dp: ArrayLike) -> FloatArray:
        """``[dp_alpha, dp_gamma]`` -> the four chamber pressures around the bias, clipped."""
        d = np.asarray(dp, dtype=np.float64).reshape(2)
        b = self.config.bias_pressure_pa
        p = np.array([b + d[0] / 2, b - d[0] / 2, b + d[1] / 2, b - d[1] / 2])
        return self.clip_pressures(p)

    @staticmethod
    def pressures_to_differential(pressures: ArrayLike) -> FloatArray:
        """Four chamber pressures -> ``[p0 - p1, p2 - p3]``."""
        p = check_pressures(pressures)
        return np.array([p[0] - p[1], p[2] - p[3]])

    def pressures_for_bend(self, bend: ArrayLike) -> FloatArray:
        """Pressures (Pa, 4) that produce ``bend = [alpha, gamma]`` (rad), hysteresis compensated.

        The differential pressure is limited to what the pressure range allows (the bend then
        falls short, never the pressure cap), and the command state is updated with what is
        returned.

        Raises:
            CommandRejectedError: see :func:`check_bend`.
        """
        target = check_bend(bend, self.config.max_bend_rad)
        dp = self._command.solve(self._k_inv @ (target - self._offset))
        lim = self.config.max_differential_pa
        dp = dp.clip(-lim, lim)
        self._command.apply(dp)
        return self.differential_to_pressures(dp)

    def note_sent_pressures(self, pressures: ArrayLike) -> None:
        """Tell the command path that ``pressures`` were sent outside ``pressures_for_bend``
        (e.g. a vent), so the next inversion starts from the right hysteresis state."""
        self._command.apply(self.pressures_to_differential(pressures))

    def bend_from_pressures(self, pressures: ArrayLike) -> FloatArray:
        """Estimated bend ``[alpha, gamma]`` (rad) from measured pressures (Pa, 4).

        Feeds the estimate path's hysteresis state; call it with every measurement in order.
        """
        return self._offset + self._k @ self._estimate.apply(
            self.pressures_to_differential(pressures))

    def bend_for_pressures_without_memory(self, pressures: ArrayLike) -> FloatArray:
        """Anhysteretic bend (``b0 + K gain dp``) for pressures: the centre line of the
        loops."""
        return self._offset + self._k @ (self.config.hysteresis.gain
                                         * self.pressures_to_differential(pressures))

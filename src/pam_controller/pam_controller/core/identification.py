"""Identification of the bending model on the bench: excitation, bend from the EM pose, the fit.

Pure numpy and scipy; no rclpy, no messages. ``identify_pam``
(:mod:`cgail_rig.identify_pam`) runs the excitation on a rig (simulated or real),
records the EM tip pose and the measured pressures, and hands them here as arrays.

**Bench fixture.** The catheter is clamped at the base of its steerable segment, in free air,
with the EM sensor at the tip. The insertion is held. The segment is a constant-curvature arc
(the catheter model's bend convention, ``cgail_sim.ftl_model``): per length ``dl`` the
heading turns by ``alpha dl / L`` about ``x`` and by ``gamma dl / L`` about ``z``. Over the
whole segment the tip's rotation relative to the base is then the rotation vector
``(alpha, ~0, gamma)`` in the base frame: the bend is read from ``log(R_base^T R_tip)``
(:func:`bend_from_rotations`). The base orientation is measured while every chamber is vented
(:func:`base_rotation`): below the muscles' threshold pressure the segment is straight.

**Excitation** (:class:`ExcitationConfig`, :func:`excitation_schedule`), in differential
pressure around the bias, one axis at a time, then both:

1. ``rest_s`` vented (nothing commanded: the controller's watchdog holds the chambers vented),
   for the base orientation;
2. ``settle_s`` at the bias (zero differential);
3. per axis, one triangular cycle ``0 -> +A_k -> -A_k -> 0`` for each amplitude
   ``A_k = level_k * amplitude_pa``, growing, at a constant slope ``sweep_rate_pa_s``: the
   nested loops of a Prandtl-Ishlinskii identification (Kuhnen 2003: the loops' reversal
   points expose the play thresholds). The slope is slow against the plant's lag (at
   25 kPa/s and a 0.1 s lag the bend trails by 2.5 kPa, 1 % of the stroke);
4. a multisine on both axes at once, ``multisine_periods`` periods of ``1 / f0``: odd
   harmonics of ``f0`` on alpha, even ones on gamma (uncorrelated axes), up to
   ``multisine_max_hz``, Schroeder phases (a low crest factor; Schroeder 1970, IEEE T-IT
   16(1)), scaled to a peak of ``multisine_fraction * amplitude_pa`` per axis. It is held out
   of the fit: the validation error;
5. ``settle_s`` at the bias.

**Model fitted.** The controller's own (:mod:`pam_controller.core.bending_model`): one
Prandtl-Ishlinskii operator on each axis's differential pressure, ``h = PI[dp]``, then
``bend = b0 + K h`` with a bend offset ``b0`` per axis and ``K = [[s_alpha, c_ag], [c_ga,
s_gamma]]`` (a gain per axis and the cross-coupling), with the parameters that
``config/pam_controller.yaml`` exposes (:data:`IDENTIFIED_KEYS`): the common gain, the share of
the gain in the plays, the density decay of the play weights, the largest play threshold, the
two offsets, the two gain scales (``s_alpha s_gamma = 1``: the common gain is their geometric
mean) and the two couplings; the number of plays is kept (thresholds ``r_max i / n``). Bounded
least squares (``scipy.optimize.least_squares``, trust region reflective) on the bend residuals
of the sweeps, both axes stacked; the play states are run over the whole record from the
vented (virgin) start, as the controller runs them. The initial guess is the nominal model with
the offsets at the nominal model's mean residual per axis. The largest threshold is searched
on a geometric grid first (the residual is only piecewise smooth in it), then all are refined
together. The multisine stays held out.

Not representable by the controller's model, and reported as a residual rather than fitted:
the lag of the bend behind the pressure (:func:`fit_lag` measures it on the sweeps for the
report; the controller has no rate-dependent term), the dead zone (the offset is right around
the bias, not for vented chambers) and the shape of the plant's own loops.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pam_controller.core.bending_model import BendingModelConfig
from pam_controller.core.hysteresis import HysteresisConfig
from pam_controller.errors import PamError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Segment labels of an excitation (``ExcitationSchedule.segment``).
SEGMENTS: tuple[str, ...] = ('rest', 'settle', 'sweep_alpha', 'sweep_gamma', 'multisine')
REST, SETTLE, SWEEP_ALPHA, SWEEP_GAMMA, MULTISINE = range(len(SEGMENTS))

#: Parameters of ``config/pam_controller.yaml`` the fit sets (the others are kept).
IDENTIFIED_KEYS: tuple[str, ...] = (
    'hysteresis_gain_rad_per_pa', 'hysteresis_fraction', 'hysteresis_density_decay',
    'hysteresis_max_threshold_pa', 'bend_offset_alpha_rad', 'bend_offset_gamma_rad',
    'gain_scale_alpha', 'gain_scale_gamma', 'coupling_alpha_from_gamma',
    'coupling_gamma_from_alpha')


class IdentificationError(PamError, ValueError):
    """The data cannot identify the model: missing, too short, too small or saturated."""


@dataclass(frozen=True)
class ExcitationConfig:
    """The scripted bench excitation (module docstring), in differential pressure."""

    amplitude_pa: float = 200e3
    """Largest differential pressure of the sweeps, Pa: 0.8 x (pi/2) / (2 pi 1e-6 rad/Pa), the
    nominal gain, so a plant 20 % more compliant than nominal (the top of the plant's sampled
    range, ``docs/plant.md``) still stays within the 90 deg stroke (paper IV-B).
    In (0, 400e3]."""
    levels: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0)
    """Amplitudes of the sweep cycles, as shares of ``amplitude_pa``, increasing; each in
    (0, 1]."""
    sweep_rate_pa_s: float = 25e3
    """Slope of the triangular sweeps, Pa/s: slow against the plant's lag (module docstring)
    and far below the controller's 600 kPa/s slew limit. In (0, 1e6]."""
    multisine_f0_hz: float = 0.05
    """Fundamental of the multisine, Hz: a 20 s period. In (0, 10]."""
    multisine_max_hz: float = 0.8
    """Highest harmonic of the multisine, Hz (estimate of the operator's bandwidth on the bend:
    McRuer & Jex 1967 put a human's crossover near 1 Hz for this kind of task). >= 2 f0."""
    multisine_periods: int = 2
    """Periods of the multisine; 0 leaves it out (no validation error). In [0, 20]."""
    multisine_fraction: float = 0.7
    """Peak of the multisine per axis, share of ``amplitude_pa``. In (0, 1]."""
    rest_s: float = 2.0
    """Vented at the start, s (the base orientation). In (0, 60]."""
    settle_s: float = 1.0
    """At the bias after the rest and at the end, s. In [0, 60]."""

    def __post_init__(self) -> None:
        checks = (('amplitude_pa', 0.0, 400e3), ('sweep_rate_pa_s', 0.0, 1e6),
                  ('multisine_f0_hz', 0.0, 10.0), ('multisine_fraction', 0.0, 1.0),
                  ('rest_s', 0.0, 60.0))
        for name, low, high in checks:
            value = getattr(self, name)
            if not (math.isfinite(value) and low < value <= high):
                raise ValueError(f'{name} must be in ({low}, {high}], found {value!r}')
        if not (math.isfinite(self.settle_s) and 0.0 <= self.settle_s <= 60.0):
            raise ValueError(f'settle_s must be in [0, 60], found {self.settle_s!r}')
        levels = np.asarray(self.levels, dtype=np.float64)
        if levels.size < 1 or not (np.all((levels > 0.0) & (levels <= 1.0))
                                   and np.all(np.diff(levels) > 0.0)):
            raise ValueError(f'levels must be increasing shares in (0, 1], found {self.levels!r}')
        if not (math.isfinite(self.multisine_max_hz)
                and self.multisine_max_hz >= 2.0 * self.multisine_f0_hz):
            raise ValueError(f'multisine_max_hz must be >= 2 * multisine_f0_hz = '
                             f'{2.0 * self.multisine_f0_hz}, found {self.multisine_max_hz!r}')
        if not (0 <= self.multisine_periods <= 20):
            raise ValueError(f'multisine_periods must be in [0, 20], found '
                             f'{self.multisine_periods!r}')

    @property
    def duration_s(self) -> float:
        """Length of the whole excitation, s."""
        sweeps = 2 * sum(4.0 * lv * self.amplitude_pa for lv in self.levels)
        return (self.rest_s + 2.0 * self.settle_s + sweeps / self.sweep_rate_pa_s
                + self.multisine_periods / self.multisine_f0_hz)


SHORT_EXCITATION = ExcitationConfig(levels=(0.5, 1.0), sweep_rate_pa_s=100e3,
                                    multisine_periods=1, rest_s=1.0, settle_s=0.5)
"""A short excitation (about 37 s of rig time) for tests and quick checks: two sweep
amplitudes at 100 kPa/s, one multisine period."""


@dataclass(frozen=True)
class ExcitationSchedule:
    """The excitation sampled at a fixed step."""

    t: FloatArray
    """(T,) times from the start, s."""
    dp: FloatArray
    """(T, 2) differential pressures ``[alpha, gamma]``, Pa (0 during the rest)."""
    segment: IntArray
    """(T,) index into :data:`SEGMENTS`."""

    def at(self, time_s: float) -> tuple[FloatArray, int]:
        """The differential pressure and segment at ``time_s`` (held after the end)."""
        i = int(np.clip(np.searchsorted(self.t, time_s, side='right') - 1, 0, self.t.size - 1))
        return self.dp[i].copy(), int(self.segment[i])


def _triangle(amplitude: float, rate: float, dt: float) -> FloatArray:
    """One cycle ``0 -> +A -> -A -> 0`` at slope ``rate``, sampled every ``dt`` (end excluded)."""
    period = 4.0 * amplitude / rate
    t = np.arange(0.0, period - 1e-12, dt)
    phase = t / period  # 0..1
    return amplitude * np.where(phase < 0.25, 4.0 * phase,
                                np.where(phase < 0.75, 2.0 - 4.0 * phase, 4.0 * phase - 4.0))


def multisine(config: ExcitationConfig, t: ArrayLike) -> FloatArray:
    """The multisine at times ``t`` (s from its start): (T, 2) differential pressures, Pa."""
    tt = np.asarray(t, dtype=np.float64)
    f0 = config.multisine_f0_hz
    harmonics = np.arange(1, int(config.multisine_max_hz / f0 + 1e-9) + 1)
    out = np.zeros((tt.size, 2))
    grid = np.arange(0.0, 1.0 / f0, 1.0 / (f0 * 2000.0))
    for axis in range(2):
        ks = harmonics[harmonics % 2 == (1 - axis)]  # alpha: odd, gamma: even
        m = ks.size
        phases = -np.pi * np.arange(1, m + 1) * np.arange(m) / m  # Schroeder 1970
        peak = np.max(np.abs(np.sin(2 * np.pi * f0 * grid[:, None] * ks + phases).sum(axis=1)))
        shape = np.sin(2 * np.pi * f0 * tt[:, None] * ks + phases).sum(axis=1)
        out[:, axis] = config.multisine_fraction * config.amplitude_pa * shape / peak
    return out


def excitation_schedule(config: ExcitationConfig, dt: float) -> ExcitationSchedule:
    """The excitation (module docstring) sampled every ``dt`` s (the command rate)."""
    if not (math.isfinite(dt) and 0.0 < dt <= 1.0):
        raise ValueError(f'dt must be in (0, 1] s, found {dt!r}')
    parts: list[tuple[FloatArray, int]] = []

    def hold(seconds: float, seg: int) -> None:
        n = round(seconds / dt)
        parts.append((np.zeros((n, 2)), seg))

    hold(config.rest_s, REST)
    hold(config.settle_s, SETTLE)
    for axis, seg in ((0, SWEEP_ALPHA), (1, SWEEP_GAMMA)):
        for level in config.levels:
            tri = _triangle(level * config.amplitude_pa, config.sweep_rate_pa_s, dt)
            dp = np.zeros((tri.size, 2))
            dp[:, axis] = tri
            parts.append((dp, seg))
    if config.multisine_periods:
        n = round(config.multisine_periods / (config.multisine_f0_hz * dt))
        parts.append((multisine(config, np.arange(n) * dt), MULTISINE))
    hold(config.settle_s, SETTLE)
    dp = np.concatenate([p for p, _ in parts]).astype(np.float64)
    segment = np.concatenate([np.full(len(p), s, dtype=np.int64) for p, s in parts])
    return ExcitationSchedule(t=(np.arange(dp.shape[0]) * dt).astype(np.float64), dp=dp,
                              segment=segment)


# ---------------------------------------------------------------------- bend from the EM pose
def _log_rotation(r: FloatArray) -> FloatArray:
    """Rotation vectors of (..., 3, 3) rotations (scipy's ``as_rotvec``)."""
    from scipy.spatial.transform import Rotation

    shape = r.shape[:-2]
    return Rotation.from_matrix(r.reshape(-1, 3, 3)).as_rotvec().reshape(*shape, 3)


def base_rotation(rotations: ArrayLike) -> FloatArray:
    """The mean (3, 3) orientation of EM samples (N, 3, 3) taken with every chamber vented.

    Raises:
        IdentificationError: no sample.
    """
    from scipy.spatial.transform import Rotation

    r = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    if r.shape[0] == 0:
        raise IdentificationError('expected EM samples with every chamber vented (the base '
                                  'orientation), found none')
    return Rotation.from_matrix(r).mean().as_matrix()


def bend_from_rotations(base: ArrayLike, tips: ArrayLike) -> FloatArray:
    """``[alpha, gamma]`` (rad) of tip orientations (T, 3, 3) relative to the clamped ``base``.

    The x and z components of ``log(base^T tip)`` (module docstring). For the phantom's arc,
    a chain of equal steps ``Rx(a) Rz(g)``, this is exact up to ``O(|bend|^3 / N^2)``.
    """
    b = np.asarray(base, dtype=np.float64).reshape(3, 3)
    r = np.asarray(tips, dtype=np.float64).reshape(-1, 3, 3)
    rv = _log_rotation(np.einsum('ji,njk->nik', b, r))
    return rv[:, [0, 2]]


# ---------------------------------------------------------------------- data
@dataclass(frozen=True)
class IdentificationData:
    """Measured differential pressures and bends on one time base."""

    t: FloatArray
    """(T,) times, s (the pressure samples')."""
    dp: FloatArray
    """(T, 2) measured differential pressures ``[p0 - p1, p2 - p3]``, Pa."""
    bend: FloatArray
    """(T, 2) bends ``[alpha, gamma]`` from the EM pose, rad (interpolated to ``t``)."""
    fit: NDArray[np.bool_]
    """(T,) samples the fit uses (the sweeps)."""
    validation: NDArray[np.bool_]
    """(T,) held-out samples (the multisine); may be all False."""


def align(pressure_t: ArrayLike, pressures: ArrayLike, pose_t: ArrayLike,
          rotations: ArrayLike, *, vent_pa: float = 5e3,
          schedule: ExcitationSchedule | None = None,
          start_t: float | None = None) -> IdentificationData:
    """Measured pressures (T, 4) and EM orientations (K, 3, 3) -> :class:`IdentificationData`.

    The base orientation is the mean of the EM samples taken before the first pressure sample
    above ``vent_pa`` (every chamber vented). The bend is interpolated linearly to the pressure
    samples' times; samples outside the EM record are dropped. With a ``schedule`` (and
    ``start_t``, the time of its start on the same clock) the sweeps are the fit samples and
    the multisine the validation; without one, the samples are split by the structure of the
    measured pressures: both axes moving at once is the multisine, else a sweep.

    Raises:
        IdentificationError: no pressures, no EM poses, no vented start, no pressurised part.
    """
    pt = np.asarray(pressure_t, dtype=np.float64).reshape(-1)
    p = np.asarray(pressures, dtype=np.float64).reshape(-1, 4)
    et = np.asarray(pose_t, dtype=np.float64).reshape(-1)
    rot = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    if pt.size == 0 or p.shape[0] != pt.size:
        raise IdentificationError(f'expected measured pressures (pam/pressures), found '
                                  f'{pt.size} samples')
    if et.size < 2 or rot.shape[0] != et.size:
        raise IdentificationError(f'expected EM tip poses (em_tracker/tip_pose), found '
                                  f'{et.size} samples')
    order = np.argsort(pt, kind='stable')
    pt, p = pt[order], p[order]
    order = np.argsort(et, kind='stable')
    et, rot = et[order], rot[order]
    pressurised = np.flatnonzero(np.max(p, axis=1) > vent_pa)
    if pressurised.size == 0:
        raise IdentificationError(f'expected pressurised chambers (above {vent_pa / 1e3:g} kPa), '
                                  'found the bank vented throughout')
    t_on = pt[pressurised[0]]
    vented = et < t_on
    if not np.any(vented):
        raise IdentificationError('expected EM poses while every chamber is vented before the '
                                  'excitation (the base orientation), found none')
    base = base_rotation(rot[vented])
    bend_em = bend_from_rotations(base, rot)
    keep = (pt >= max(t_on, et[0])) & (pt <= et[-1])
    # every pressure sample from the first pressurised one on (the plays start virgin there)
    t = pt[keep]
    dp = np.stack([p[keep, 0] - p[keep, 1], p[keep, 2] - p[keep, 3]], axis=1)
    bend = np.stack([np.interp(t, et, bend_em[:, 0]), np.interp(t, et, bend_em[:, 1])], axis=1)
    if schedule is not None:
        origin = t_on if start_t is None else start_t
        idx = np.clip(np.searchsorted(schedule.t, t - origin, side='right') - 1, 0,
                      schedule.t.size - 1)
        seg = schedule.segment[idx]
        fit = (seg == SWEEP_ALPHA) | (seg == SWEEP_GAMMA)
        validation = seg == MULTISINE
    else:
        fit, validation = _split_by_structure(dp)
    return IdentificationData(t=t, dp=dp, bend=bend, fit=fit, validation=validation)


def _split_by_structure(dp: FloatArray, still_pa: float = 5e3) -> tuple[NDArray[np.bool_],
                                                                         NDArray[np.bool_]]:
    """Sweeps (one axis away from zero) vs multisine (both): a bag without its schedule."""
    both = np.all(np.abs(dp) > still_pa, axis=1)
    # the multisine is one block at the end: from the first of a long run of "both" samples
    run = np.convolve(both.astype(float), np.ones(20) / 20.0, mode='same') > 0.9
    start = int(np.argmax(run)) if np.any(run) else dp.shape[0]
    validation = np.zeros(dp.shape[0], dtype=bool)
    validation[start:] = True
    return ~validation, validation


# ---------------------------------------------------------------------- model and fit
def play_states(dp: ArrayLike, thresholds: ArrayLike) -> FloatArray:
    """Play operator outputs (T, channels, n) of inputs (T, channels), virgin start."""
    u = np.asarray(dp, dtype=np.float64)
    r = np.asarray(thresholds, dtype=np.float64)
    out = np.empty((*u.shape, r.size))
    z = np.zeros((u.shape[1], r.size))
    for k in range(u.shape[0]):
        uk = u[k][:, None]
        z = np.maximum(uk - r, np.minimum(uk + r, z))
        out[k] = z
    return out


def predict(config: BendingModelConfig | HysteresisConfig, dp: ArrayLike) -> FloatArray:
    """The model's bend (T, 2) for differential pressures (T, 2) from a virgin start (the
    controller's estimate path, :meth:`BendingModel.bend_from_pressures`, run on a record).
    A bare :class:`HysteresisConfig` is the nominal per-axis model (``b0 = 0``, ``K = I``)."""
    model = config if isinstance(config, BendingModelConfig) \
        else BendingModelConfig(hysteresis=config)
    hyst = model.hysteresis
    u = np.asarray(dp, dtype=np.float64)
    w0, w = hyst.weights()
    h = w0 * u + play_states(u, hyst.thresholds()) @ w
    return np.asarray(model.bend_offset_rad) + h @ model.axis_matrix.T


def rms(residual: ArrayLike) -> float:
    """Root mean square over every element (NaN for none)."""
    r = np.asarray(residual, dtype=np.float64)
    return float(np.sqrt(np.mean(r * r))) if r.size else float('nan')


@dataclass(frozen=True)
class FitBounds:
    """Bounds of the fitted parameters (within the node's declared ranges)."""

    gain: tuple[float, float] = (2 * math.pi * 1e-6 / 5.0, 2 * math.pi * 1e-6 * 5.0)
    """rad/Pa: a fifth to five times the nominal gain."""
    fraction: tuple[float, float] = (0.0, 0.95)
    """The node's range of ``hysteresis_fraction``."""
    decay: tuple[float, float] = (0.0, 20.0)
    """The node's range of ``hysteresis_density_decay``."""
    max_threshold: tuple[float, float] = (5e3, 400e3)
    """Pa; the node allows [1, 400e3]; below 5 kPa a play is within the regulators' noise."""
    offset: tuple[float, float] = (-0.5, 0.5)
    """rad, each axis: the node's range of ``bend_offset_*_rad``."""
    gain_scale: tuple[float, float] = (0.5, 2.0)
    """``s_alpha`` (``s_gamma = 1 / s_alpha``): the node's range of ``gain_scale_*``."""
    coupling: tuple[float, float] = (-0.5, 0.5)
    """Each coupling: the node's range of ``coupling_*`` (with ``s_alpha s_gamma = 1`` the
    product of the two is at most 0.25, so ``det K >= 0.75``)."""


@dataclass(frozen=True)
class FitResult:
    """An identified bending model and its errors."""

    config: BendingModelConfig
    """The identified model (the play count of the nominal one; its pressure limits)."""
    nominal: BendingModelConfig
    """The model it started from (the controller's current one)."""
    errors: dict[str, dict[str, float]] = field(default_factory=dict)
    """RMS bend error, rad: ``errors[model][part]``, model ``nominal`` / ``identified``, part
    ``fit`` / ``validation`` / ``all``."""
    cost_evaluations: int = 0
    """Model evaluations the least squares made."""
    lag_s: float = float('nan')
    """First-order lag of the bend behind the identified model, s, fitted on the sweeps
    (:func:`fit_lag`): reported, not representable by the controller's model."""
    lag_errors: dict[str, float] = field(default_factory=dict)
    """RMS bend error (rad) of the identified model followed by that lag, per part: what a lag
    term would add (not the controller's model)."""

    @property
    def improvement(self) -> float:
        """Identified over nominal RMS error on every sample (< 1: better)."""
        return self.errors['identified']['all'] / self.errors['nominal']['all']


MIN_SAMPLES = 100
"""Fewest fit samples accepted (5 s at the controller's 20 Hz in the session)."""
MIN_SPAN_PA = 40e3
"""Smallest differential-pressure span per axis in the fit samples, Pa: a fifth of the default
stroke; below it the gain is not identifiable against the 0.005 rad EM angle noise."""
SATURATED_SHARE = 0.05
"""Largest share of fit samples allowed at a pressure limit or at the stroke's end."""


def check_excitation(data: IdentificationData, model: BendingModelConfig,
                     max_bend_rad: float = math.pi / 2) -> None:
    """Refuse data that cannot identify the model (one clear line).

    Raises:
        IdentificationError: too few samples, too small a span on an axis, or more than
            :data:`SATURATED_SHARE` of the samples at a pressure limit or at the stroke's end.
    """
    n = int(np.count_nonzero(data.fit))
    if n < MIN_SAMPLES:
        raise IdentificationError(f'expected at least {MIN_SAMPLES} samples of sweeps, found {n}'
                                  ' (too short an excitation)')
    dp = data.dp[data.fit]
    for axis, name in enumerate(('alpha', 'gamma')):
        span = float(np.ptp(dp[:, axis]))
        if span < MIN_SPAN_PA:
            raise IdentificationError(
                f'expected a differential-pressure span of at least {MIN_SPAN_PA / 1e3:g} kPa on '
                f'{name}, found {span / 1e3:.1f} kPa (too small an excitation)')
    lim = model.max_differential_pa
    at_limit = np.any(np.abs(dp) >= lim - 1e3, axis=1)
    at_stroke = np.hypot(data.bend[data.fit, 0], data.bend[data.fit, 1]) >= 0.98 * max_bend_rad
    share = float(np.mean(at_limit | at_stroke))
    if share > SATURATED_SHARE:
        raise IdentificationError(
            f'expected at most {SATURATED_SHARE:.0%} of the samples at the pressure limits '
            f'(+-{lim / 1e3:g} kPa) or the stroke end ({max_bend_rad:.3f} rad), found '
            f'{share:.0%} (a saturated excitation: lower the amplitude)')


def _weights(gain: float, fraction: float, decay: float, n: int) -> FloatArray:
    """``[w0, w_1..w_n]`` as :meth:`HysteresisConfig.weights` gives them."""
    i = np.arange(1, n + 1, dtype=np.float64) / n
    density = np.exp(-decay * i)
    return np.concatenate([[gain * (1.0 - fraction)], gain * fraction * density / density.sum()])


#: Order of the fitted vector: gain, fraction, decay, s_alpha, c_ag, c_ga, b_alpha, b_gamma
#: (and the largest threshold last in the refinement).
_N_FIT = 8


def _model_of(nominal: BendingModelConfig, x: ArrayLike, r_max: float) -> BendingModelConfig:
    """The :class:`BendingModelConfig` of a fitted vector (order of :data:`_N_FIT`)."""
    g, f, d, sa, cag, cga, ba, bg = (float(v) for v in np.asarray(x)[:_N_FIT])
    hyst = replace(nominal.hysteresis, gain=g, hysteresis_fraction=f, density_decay=d,
                   max_threshold=float(r_max))
    return replace(nominal, hysteresis=hyst, bend_offset_rad=(ba, bg), gain_scale=(sa, 1.0 / sa),
                   coupling=(cag, cga))


def fit_bending_model(data: IdentificationData, nominal: BendingModelConfig | None = None, *,
                      bounds: FitBounds | None = None, grid: int = 12) -> FitResult:
    """Fit the controller's bending model to ``data`` (module docstring).

    Args:
        data: the aligned record (:func:`align`).
        nominal: the controller's current model (default: the nominal one); its play count and
            pressure limits are kept and it is the starting point.
        bounds: parameter bounds.
        grid: points of the geometric grid of the largest threshold.

    Returns:
        The identified model with the nominal and identified RMS errors, and the lag
        (:func:`fit_lag`) for the report.
    """
    from scipy.optimize import least_squares

    nom = nominal if nominal is not None else BendingModelConfig()
    bnd = bounds if bounds is not None else FitBounds()
    hyst = nom.hysteresis
    n = hyst.play_count
    fit = data.fit
    target = data.bend[fit]
    u_fit = data.dp[fit]
    cache: dict[float, FloatArray] = {}
    evaluations = [0]

    def features(r_max: float) -> FloatArray:
        """(F, 2, n + 1): the input and the plays on the fit samples, per axis."""
        key = float(r_max)
        if key not in cache:
            if len(cache) > 64:
                cache.clear()
            plays = play_states(data.dp, key * np.arange(1, n + 1) / n)[fit]  # (F, 2, n)
            cache[key] = np.concatenate([u_fit[..., None], plays], axis=2)
        return cache[key]

    def residual(x: FloatArray, r_max: float | None = None) -> FloatArray:
        evaluations[0] += 1
        g, f, d, sa, cag, cga, ba, bg = x[:_N_FIT]
        h = features(x[_N_FIT] if r_max is None else r_max) @ _weights(g, f, d, n)  # (F, 2)
        alpha = ba + sa * h[:, 0] + cag * h[:, 1]
        gamma = bg + cga * h[:, 0] + h[:, 1] / sa
        return np.concatenate([alpha - target[:, 0], gamma - target[:, 1]])

    lo = np.array([bnd.gain[0], bnd.fraction[0], bnd.decay[0], bnd.gain_scale[0],
                   bnd.coupling[0], bnd.coupling[0], bnd.offset[0], bnd.offset[0]])
    hi = np.array([bnd.gain[1], bnd.fraction[1], bnd.decay[1], bnd.gain_scale[1],
                   bnd.coupling[1], bnd.coupling[1], bnd.offset[1], bnd.offset[1]])
    # Start: the nominal model, decoupled, the offsets at its mean residual per axis.
    start_offset = np.mean(target - predict(nom, data.dp)[fit], axis=0) \
        + np.asarray(nom.bend_offset_rad)
    sa0 = math.sqrt(nom.gain_scale[0] / nom.gain_scale[1])
    x0 = np.clip([hyst.gain * math.sqrt(nom.gain_scale[0] * nom.gain_scale[1]),
                  hyst.hysteresis_fraction, hyst.density_decay, sa0, *nom.coupling,
                  *start_offset], lo, hi)
    scale = np.array([hyst.gain, 0.1, 1.0, 0.05, 0.02, 0.02, 0.05, 0.05])
    best: tuple[float, FloatArray, float] | None = None
    for r_max in np.geomspace(bnd.max_threshold[0], bnd.max_threshold[1], grid):
        sol = least_squares(residual, x0, bounds=(lo, hi), x_scale=scale, method='trf',
                            kwargs={'r_max': float(r_max)})
        if best is None or sol.cost < best[0]:
            best = (float(sol.cost), sol.x, float(r_max))
    assert best is not None
    lo9 = np.append(lo, bnd.max_threshold[0])
    hi9 = np.append(hi, bnd.max_threshold[1])
    x9 = np.clip(np.append(best[1], best[2]), lo9, hi9)
    step = np.array([1e-4, 1e-3, 1e-3, 1e-4, 1e-3, 1e-3, 1e-3, 1e-3, 1e-2])
    sol = least_squares(residual, x9, bounds=(lo9, hi9), x_scale=np.append(scale, best[2]),
                        method='trf', diff_step=step)
    x = sol.x if sol.cost <= best[0] else np.append(best[1], best[2])
    identified = _model_of(nom, x, x[_N_FIT])
    lag, lag_errors = fit_lag(identified, data)
    return FitResult(config=identified, nominal=nom,
                     errors={'nominal': model_errors(nom, data),
                             'identified': model_errors(identified, data)},
                     cost_evaluations=evaluations[0], lag_s=lag, lag_errors=lag_errors)


def first_order_lag(bend: ArrayLike, t: ArrayLike, tau: float) -> FloatArray:
    """``bend`` (T, 2) through ``tau dy/dt = bend - y`` (exact for a bend held between the
    samples at times ``t``), starting at ``y = bend[0]``."""
    b = np.asarray(bend, dtype=np.float64)
    if tau <= 0.0:
        return b.copy()
    tt = np.asarray(t, dtype=np.float64)
    keep = np.exp(-np.diff(tt, prepend=tt[0]) / tau)
    out = np.empty_like(b)
    out[0] = b[0]
    for k in range(1, b.shape[0]):
        out[k] = b[k] + keep[k] * (out[k - 1] - b[k])
    return out


def fit_lag(config: BendingModelConfig, data: IdentificationData,
            max_lag_s: float = 1.0) -> tuple[float, dict[str, float]]:
    """The first-order lag (s) that best follows ``config``'s bend on the sweeps, and the RMS
    errors (rad) per part with it. For the report: the controller has no lag term."""
    from scipy.optimize import minimize_scalar

    static = predict(config, data.dp)

    def cost(tau: float) -> float:
        return rms((first_order_lag(static, data.t, tau) - data.bend)[data.fit])

    sol = minimize_scalar(cost, bounds=(0.0, max_lag_s), method='bounded',
                          options={'xatol': 1e-3})
    tau = float(sol.x)
    err = first_order_lag(static, data.t, tau) - data.bend
    return tau, {'fit': rms(err[data.fit]), 'validation': rms(err[data.validation]),
                 'all': rms(err)}


def model_errors(config: BendingModelConfig | HysteresisConfig,
                 data: IdentificationData) -> dict[str, float]:
    """RMS bend error (rad) of ``config`` on ``data``: ``fit``, ``validation``, ``all``."""
    err = predict(config, data.dp) - data.bend
    return {'fit': rms(err[data.fit]), 'validation': rms(err[data.validation]),
            'all': rms(err)}


def identified_parameters(config: BendingModelConfig) -> dict[str, float]:
    """The :data:`IDENTIFIED_KEYS` of ``pam_controller.yaml`` for an identified model."""
    h = config.hysteresis
    return {'hysteresis_gain_rad_per_pa': float(h.gain),
            'hysteresis_fraction': float(h.hysteresis_fraction),
            'hysteresis_density_decay': float(h.density_decay),
            'hysteresis_max_threshold_pa': float(h.max_threshold),
            'bend_offset_alpha_rad': float(config.bend_offset_rad[0]),
            'bend_offset_gamma_rad': float(config.bend_offset_rad[1]),
            'gain_scale_alpha': float(config.gain_scale[0]),
            'gain_scale_gamma': float(config.gain_scale[1]),
            'coupling_alpha_from_gamma': float(config.coupling[0]),
            'coupling_gamma_from_alpha': float(config.coupling[1])}

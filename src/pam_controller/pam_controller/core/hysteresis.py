"""Prandtl-Ishlinskii (PI) hysteresis operator, exact inverse included.

The PI model is a weighted sum of backlash ("play") operators plus a linear term::

    y(t) = w0 * u(t) + sum_i w_i * z_i(t),
    z_i(t) = max(u(t) - r_i, min(u(t) + r_i, z_i(t-1)))        (play operator, threshold r_i)

With ``w0 > 0`` and ``w_i >= 0`` the output is a continuous, strictly increasing, piecewise-linear
function of the new input for any frozen play state, so the input that produces a wanted output
(:meth:`PrandtlIshlinskii.solve`) is computed exactly from the breakpoints ``z_i +- r_i``.
The model is rate independent: only the sequence of input extrema matters, loops close after
one cycle, and loading and unloading branches differ by ``2 * sum_i w_i * min(r_i, ...)``.

References: M. Brokate, J. Sprekels, "Hysteresis and Phase Transitions" (1996) for the operator;
K. Kuhnen, "Modeling, identification and compensation of complex hysteretic nonlinearities"
(Eur. J. Control, 2003) for its use as a compensator of actuators.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class HysteresisConfig:
    """Parameters of one PI operator (shared by every channel it drives)."""

    gain: float = 2.0 * math.pi * 1e-6
    """Total slope of the model in output units per input unit (here rad per Pa of
    differential pressure): the slope of every branch once all plays move with the input,
    ``w0 + sum_i w_i``. Default: 1.2 x (pi/2) / 300 kPa, an estimate (see bending_model)."""

    hysteresis_fraction: float = 0.5
    """Share of ``gain`` carried by the play operators (0 = no hysteresis), in [0, 0.95]."""

    play_count: int = 8
    """Number of play operators, in [1, 64]."""

    max_threshold: float = 100e3
    """Largest play threshold ``r_n`` in input units (Pa); thresholds are ``r_max * i / n``.
    Must be > 0."""

    density_decay: float = 1.0
    """Weights fall as ``exp(-density_decay * r_i / r_max)`` (a decreasing density, as
    identified for pneumatic actuators); 0 gives equal weights. In [0, 20]."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gain) and self.gain > 0.0):
            raise ValueError(f'gain must be a finite number > 0, found {self.gain}')
        if not (0.0 <= self.hysteresis_fraction <= 0.95):
            raise ValueError(
                f'hysteresis_fraction must be in [0, 0.95], found {self.hysteresis_fraction}')
        if not (1 <= self.play_count <= 64):
            raise ValueError(f'play_count must be in [1, 64], found {self.play_count}')
        if not (math.isfinite(self.max_threshold) and self.max_threshold > 0.0):
            raise ValueError(
                f'max_threshold must be a finite number > 0, found {self.max_threshold}')
        if not (0.0 <= self.density_decay <= 20.0):
            raise ValueError(f'density_decay must be in [0, 20], found {self.density_decay}')

    def thresholds(self) -> FloatArray:
        """Play thresholds ``r_1 .. r_n`` (strictly positive, increasing)."""
        n = self.play_count
        return self.max_threshold * np.arange(1, n + 1, dtype=np.float64) / n

    def weights(self) -> tuple[float, FloatArray]:
        """``(w0, w)``: the linear weight and the play weights; ``w0 + sum(w) == gain``."""
        r = self.thresholds()
        density = np.exp(-self.density_decay * r / self.max_threshold)
        w = self.gain * self.hysteresis_fraction * density / density.sum()
        return self.gain * (1.0 - self.hysteresis_fraction), w

    def major_loop_width(self) -> float:
        """Width of the loop (output units) at zero input for a symmetric input swing that
        exceeds ``2 * max_threshold``: ``2 * sum_i w_i r_i``."""
        _, w = self.weights()
        return float(2.0 * np.dot(w, self.thresholds()))


class PrandtlIshlinskii:
    """A bank of independent PI operators (one per channel) with the same parameters.

    Args:
        config: the operator parameters.
        channels: number of independent channels (e.g. 2: the alpha and gamma pairs).
    """

    def __init__(self, config: HysteresisConfig, channels: int = 1) -> None:
        if channels < 1:
            raise ValueError(f'channels must be >= 1, found {channels}')
        self.config = config
        self.channels = channels
        self._r = config.thresholds()
        w0, w = config.weights()
        self._w0 = w0
        self._w = w
        self._z = np.zeros((channels, config.play_count))

    @property
    def state(self) -> FloatArray:
        """Copy of the play states, shape ``(channels, play_count)``."""
        return self._z.copy()

    def reset(self) -> None:
        """Back to the virgin (demagnetised) state: every play at 0."""
        self._z[:] = 0.0

    def _as_channels(self, values: ArrayLike, name: str) -> FloatArray:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
        if arr.shape != (self.channels,):
            raise ValueError(
                f'{name} must have {self.channels} values, found shape {np.shape(values)}')
        if not np.isfinite(arr).all():
            raise ValueError(f'{name} must be finite, found {arr.tolist()}')
        return arr

    def _plays(self, u: FloatArray, z: FloatArray) -> FloatArray:
        return np.maximum(u[..., None] - self._r, np.minimum(u[..., None] + self._r, z))

    def output_for(self, u: ArrayLike) -> FloatArray:
        """Output the model would give for input ``u`` without changing its state."""
        uu = self._as_channels(u, 'u')
        return self._w0 * uu + self._plays(uu, self._z) @ self._w

    def apply(self, u: ArrayLike) -> FloatArray:
        """Feed input ``u`` (one value per channel), update the state, return the output."""
        uu = self._as_channels(u, 'u')
        self._z = self._plays(uu, self._z)
        return self._w0 * uu + self._z @ self._w

    def solve(self, y: ArrayLike) -> FloatArray:
        """Input that gives output ``y`` from the current state (exact; state unchanged)."""
        yy = self._as_channels(y, 'y')
        out = np.empty(self.channels)
        slope = self._w0 + float(self._w.sum())
        for c in range(self.channels):
            z = self._z[c]
            knots = np.sort(np.concatenate([z - self._r, z + self._r]))
            plays = np.maximum(knots[:, None] - self._r, np.minimum(knots[:, None] + self._r, z))
            y_knots = self._w0 * knots + plays @ self._w
            if yy[c] <= y_knots[0]:
                out[c] = knots[0] + (yy[c] - y_knots[0]) / slope
            elif yy[c] >= y_knots[-1]:
                out[c] = knots[-1] + (yy[c] - y_knots[-1]) / slope
            else:
                out[c] = np.interp(yy[c], y_knots, knots)
        return out

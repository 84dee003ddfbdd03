"""Heartbeat: the periodic motion of the aortic root that drives the deformable wall.

The annulus ring of the anatomy is moved as a rigid translation ``d(t)`` (the wall particles of
the ring are kinematic); the motion reaches the rest of the aorta only through the PBD
constraints (stretch, bending, tethering), so the root moves most and the arch little.

``d(t) = s(phase(t)) * (-axial_amplitude * root_axis + inplane_amplitude * e_inplane)``

* ``root_axis`` points from the annulus into the ascending aorta, so ``-root_axis`` is the
  systolic, downward (towards the apex) motion of the root.
  Default amplitude 10 mm: Plonek et al. 2018, "Aortic root motion in patients with aortic
  stenosis...", BMC Cardiovasc Disord, doi:10.1186/s12872-018-0891-4, measured 11.6 +- 2.9 mm
  (range 3-19 mm, smaller with age) of systolic axial excursion.
* ``e_inplane`` is a unit vector in the annulus plane: the phantom ``+x`` axis projected onto
  the plane, rotated by ``inplane_angle`` about ``root_axis``. Default amplitude 5 mm: Wei et al.
  2019, BioMed Eng OnLine, doi:10.1186/s12938-019-0632-7, 5.5 +- 1.7 mm in-plane motion.
* Heart rate default 70 bpm (clinical convention, 60-100 bpm).

The paper calibrated its heartbeat on the mean annulus displacement of 60 patients with aortic
stenosis; those data are not public, hence these literature values, both amplitudes parameters.

Waveform ``s`` (dimensionless, 0 = end-diastole = rest shape, 1 = end-systole), with the cycle
phase ``phi = frac(t * rate / 60 + phase_offset)``:

* systole, ``0 <= phi < systole_fraction``: raised-cosine descent, ``(1 - cos(pi phi / f_s)) / 2``;
* early diastole, the next ``return_fraction``: raised-cosine return to 0;
* diastasis, the rest of the cycle: at rest.

Default fractions 1/3 (systole) and 1/3 (rapid return) of the cycle (a textbook ejection time of
~0.3 s at 70 bpm; estimate). ``s`` is C1-continuous, so velocities are continuous.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

__all__ = ["Heartbeat", "HeartbeatConfig", "waveform"]


@dataclass(frozen=True)
class HeartbeatConfig:
    """Periodic annulus motion (all lengths in m, times in s)."""

    axial_amplitude: float = 0.010
    """Peak systolic displacement along ``-root_axis``, m (10 mm; Plonek 2018: 11.6 +- 2.9 mm);
    in [0, 0.03]."""
    inplane_amplitude: float = 0.005
    """Peak systolic displacement in the annulus plane, m (5 mm; Wei 2019: 5.5 +- 1.7 mm);
    in [0, 0.02]."""
    inplane_angle: float = 0.0
    """Direction of the in-plane motion, rad about ``root_axis`` from the projection of the
    phantom +x axis onto the annulus plane; in [-pi, pi]."""
    heart_rate: float = 70.0
    """Heart rate, beats per minute (70; clinical convention); in [20, 240]."""
    systole_fraction: float = 1.0 / 3.0
    """Fraction of the cycle taken by the systolic descent (estimate); in (0, 1)."""
    return_fraction: float = 1.0 / 3.0
    """Fraction of the cycle taken by the early-diastolic return (estimate); in (0, 1),
    ``systole_fraction + return_fraction <= 1``."""
    phase_offset: float = 0.0
    """Cycle phase at t = 0, in cycles; in [0, 1). 0 starts at end-diastole (rest shape)."""
    enabled: bool = True
    """False freezes the annulus at its rest position (no heartbeat)."""
    heart_borne_radius: float = 0.040
    """Fixed vertices (``Anatomy.fixed_vertices``) within this distance of the annulus centre,
    m, are released (free wall particles, tethered like the rest): the coronary-stub ends,
    since the coronary arteries lie on the heart and follow the root. Holding them 25 mm from a
    root that moves 11 mm strained the sinus wall by up to 50 %; moving them rigidly with the
    annulus tore the 6 mm stubs instead. The supra-aortic stubs (~85 mm and more away) stay
    fixed. 0 holds every fixed vertex; in [0, 0.2]."""

    def __post_init__(self) -> None:
        for name, low, high in (
            ("axial_amplitude", 0.0, 0.03), ("inplane_amplitude", 0.0, 0.02),
            ("inplane_angle", -math.pi, math.pi), ("heart_rate", 20.0, 240.0),
            ("heart_borne_radius", 0.0, 0.2),
        ):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and low <= value <= high):
                raise ValueError(f"{name} must be in [{low}, {high}], found {value!r}")
        for name in ("systole_fraction", "return_fraction"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0.0 < value < 1.0):
                raise ValueError(f"{name} must be in (0, 1), found {value!r}")
        if self.systole_fraction + self.return_fraction > 1.0 + 1e-12:
            raise ValueError(
                "systole_fraction + return_fraction must be <= 1, found "
                f"{self.systole_fraction} + {self.return_fraction}")
        if not (isinstance(self.phase_offset, (int, float)) and 0.0 <= self.phase_offset < 1.0):
            raise ValueError(f"phase_offset must be in [0, 1), found {self.phase_offset!r}")
        if not isinstance(self.enabled, bool):
            raise ValueError(f"enabled must be a bool, found {self.enabled!r}")

    @property
    def period(self) -> float:
        """Cardiac cycle length, s."""
        return 60.0 / self.heart_rate


def waveform(phase: np.ndarray | float, systole_fraction: float, return_fraction: float
             ) -> np.ndarray:
    """Normalised displacement s in [0, 1] at cycle phase(s) ``phase`` (any real, mod 1)."""
    phi = np.mod(np.asarray(phase, dtype=float), 1.0)
    fs = systole_fraction
    fr = return_fraction
    rise = 0.5 * (1.0 - np.cos(np.pi * np.clip(phi / fs, 0.0, 1.0)))
    fall = 0.5 * (1.0 + np.cos(np.pi * np.clip((phi - fs) / fr, 0.0, 1.0)))
    return np.where(phi < fs, rise, np.where(phi < fs + fr, fall, 0.0))


class Heartbeat:
    """Annulus displacement of one anatomy over time.

    Args:
        root_axis: (3,) unit vector from the annulus into the ascending aorta.
        config: the motion parameters.
    """

    def __init__(self, root_axis: np.ndarray, config: HeartbeatConfig | None = None):
        self.config = config if config is not None else HeartbeatConfig()
        axis = np.asarray(root_axis, dtype=float).reshape(3)
        norm = float(np.linalg.norm(axis))
        if not (np.isfinite(norm) and norm > 0):
            raise ValueError(f"root_axis must be a non-zero finite 3-vector, found {axis}")
        axis = axis / norm
        ref = np.array([1.0, 0.0, 0.0])
        if abs(float(axis @ ref)) > 0.9:  # +x nearly along the axis: fall back to +y
            ref = np.array([0.0, 1.0, 0.0])
        e0 = ref - (ref @ axis) * axis
        e0 /= np.linalg.norm(e0)
        e1 = np.cross(axis, e0)
        ang = self.config.inplane_angle
        self.root_axis = axis
        self.inplane_direction = math.cos(ang) * e0 + math.sin(ang) * e1
        self._peak = (-self.config.axial_amplitude * axis
                      + self.config.inplane_amplitude * self.inplane_direction)

    @property
    def peak_displacement(self) -> np.ndarray:
        """(3,) the end-systolic displacement of the annulus, m."""
        return self._peak.copy()

    def shape(self, t: float) -> float:
        """Normalised waveform value s(t) in [0, 1] (0 when the heartbeat is disabled)."""
        c = self.config
        if not c.enabled:
            return 0.0
        # :func:`waveform` for one scalar, in plain floats (numpy costs ~10 us per call here)
        phi = (t / c.period + c.phase_offset) % 1.0
        fs = c.systole_fraction
        fr = c.return_fraction
        if phi < fs:
            return 0.5 * (1.0 - math.cos(math.pi * min(max(phi / fs, 0.0), 1.0)))
        if phi < fs + fr:
            return 0.5 * (1.0 + math.cos(math.pi * min(max((phi - fs) / fr, 0.0), 1.0)))
        return 0.0

    def displacement(self, t: float) -> np.ndarray:
        """(3,) annulus displacement from its rest position at time t (s), m."""
        return self.shape(t) * self._peak

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

**The authors' profile** (``profile='paper_code'``, the ``paper_code`` option set;
``docs/fidelity.md``, "Numbers the option set needs" 5): a 0.74 s cycle of piecewise-constant
axial speeds over 8 windows (:data:`PAPER_CODE_WINDOWS_S`, :data:`PAPER_CODE_SPEEDS_MM_S`),
which is a piecewise-linear *position* of their pusher through :func:`paper_code_breakpoints`
(0 at the cycle start, +5.24 mm at 0.30 s, -1.40 mm just before 0.74 s, then back to 0). The
position is sampled at each time asked for (phases of 0.04 s are shorter than a 0.1 s env
step, so integrating the speeds per step would skip them). Their pusher, the ``Cylinder`` of
their scene, sits below the aortic root and moves along its local ``+y``, which points up the
ascending aorta (within 15 deg of their centreline there; ``shared/design/AUTHORS_SCENE.md``,
``docs/fidelity.md``); it pushes the soft root but cannot pull it. So the annulus moves along
``+root_axis`` (into the ascending aorta) by ``max(d(t), 0)``: it rides the pusher up to
+5.24 mm and back, and rests while the pusher is below its rest position (0.60-0.74 s); the
pusher's jump back to 0 at the cycle end does not move the wall. Axial only; ``heart_rate``, the
amplitudes and the fractions are not used.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
import math

import numpy as np

__all__ = ["PAPER_CODE_HEARTBEAT", "Heartbeat", "HeartbeatConfig", "paper_code_breakpoints",
           "paper_code_position", "waveform"]

#: Heartbeat profiles (:attr:`HeartbeatConfig.profile`).
PROFILES = ("raised_cosine", "paper_code")
#: The authors' phase windows, s: frame counts 0/5/13/15/21/25/28/35/37 at 0.02 s per frame.
PAPER_CODE_WINDOWS_S = (0.0, 0.10, 0.26, 0.30, 0.42, 0.50, 0.56, 0.70, 0.74)
#: The authors' axial speed in each window, mm/s (``HeartBeat.cs``).
PAPER_CODE_SPEEDS_MM_S = (12.76720774, 12.92516407, 47.33635408, -19.250626, -11.31518658,
                          -22.83593966, -18.28874613, 12.76720774)


def paper_code_breakpoints() -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``(times s, positions m)`` of the authors' profile: the speeds integrated over their
    windows, from 0 at ``t = 0`` to the value just before the cycle ends at 0.74 s."""
    pos = [0.0]
    for k, v in enumerate(PAPER_CODE_SPEEDS_MM_S):
        span = PAPER_CODE_WINDOWS_S[k + 1] - PAPER_CODE_WINDOWS_S[k]
        pos.append(pos[-1] + 1e-3 * v * span)
    return PAPER_CODE_WINDOWS_S, tuple(pos)


_PC_TIMES, _PC_POS = paper_code_breakpoints()
#: Cycle length of the authors' profile, s.
PAPER_CODE_PERIOD = _PC_TIMES[-1]
#: Largest axial position of the authors' profile, m (+5.24 mm at 0.30 s).
PAPER_CODE_PEAK = max(_PC_POS)


def paper_code_position(t: float) -> float:
    """Axial position (m, along the authors' ``+y``) of the authors' pusher at time ``t`` s:
    linear between :func:`paper_code_breakpoints`, periodic, 0 at every cycle start (the wall
    follows ``max(position, 0)``: :meth:`Heartbeat.shape`)."""
    tau = t % PAPER_CODE_PERIOD
    k = bisect.bisect_right(_PC_TIMES, tau) - 1
    k = min(max(k, 0), len(_PC_TIMES) - 2)
    frac = (tau - _PC_TIMES[k]) / (_PC_TIMES[k + 1] - _PC_TIMES[k])
    return _PC_POS[k] + frac * (_PC_POS[k + 1] - _PC_POS[k])


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
    profile: str = "raised_cosine"
    """``raised_cosine`` (ours, the waveform above with the amplitudes and rate of this
    config) or ``paper_code`` (the authors' 0.74 s axial profile; module docstring)."""

    def __post_init__(self) -> None:
        if self.profile not in PROFILES:
            raise ValueError(f"profile must be one of {PROFILES}, found {self.profile!r}")
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
        """Cardiac cycle length, s (0.74 s for the ``paper_code`` profile)."""
        if self.profile == "paper_code":
            return PAPER_CODE_PERIOD
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
        if self.config.profile == "paper_code":  # axial only, their pusher's +y = +root_axis
            self._peak = PAPER_CODE_PEAK * axis
        else:
            self._peak = (-self.config.axial_amplitude * axis
                          + self.config.inplane_amplitude * self.inplane_direction)

    @property
    def peak_displacement(self) -> np.ndarray:
        """(3,) the end-systolic displacement of the annulus, m."""
        return self._peak.copy()

    def shape(self, t: float) -> float:
        """Normalised waveform value s(t) in [0, 1]; for ``paper_code`` the pusher's axial
        position over its peak where it is above rest, else 0 (a one-sided push: module
        docstring); 0 when the heartbeat is disabled."""
        c = self.config
        if not c.enabled:
            return 0.0
        if c.profile == "paper_code":
            pos = paper_code_position(t + c.phase_offset * PAPER_CODE_PERIOD)
            return max(pos, 0.0) / PAPER_CODE_PEAK
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


#: The authors' heartbeat (the ``paper_code`` option set of :mod:`cgail_sim.config`).
PAPER_CODE_HEARTBEAT = HeartbeatConfig(profile="paper_code")

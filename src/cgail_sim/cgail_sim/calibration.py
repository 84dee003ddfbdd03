"""Calibrate the PBD wall stiffness to a stress-strain curve (the paper used PSO).

Virtual experiment: a uniaxial tensile test on a strip of the PBD wall material. The strip is a
flat triangular lattice (near-equilateral triangles, like the remeshed anatomy), one short edge
clamped, the other pulled to an engineering strain ``eps`` along the strip; the long edges are
free (the strip narrows). The quasi-static equilibrium is found with the wall's own solver
(:func:`cgail_sim.pbd.solve_vbd`, tethers and bending off: they model the surrounding
tissue and a regulariser, not the material), and the nominal stress is the reaction force on the
pulled edge (from :func:`cgail_sim.pbd.internal_forces`) over the undeformed cross
section ``width * thickness``.

Target (``FungCurve``): ``sigma(eps) = E / b (exp(b eps) - 1)``, which starts with slope E and
stiffens. The default passes through E = 0.5 MPa at small strain (estimate, Moens-Korteweg; see
ANATOMY.md) and 80 kPa at a circumferential stretch of 1.08 (Jadidi et al. 2020, biaxial tests of
76 human aortas, PMC6982607), giving b ~ 15.7.

Fit: :func:`calibrate` searches the PBD parameters ``(youngs_modulus, stiffening)`` that make
the simulated strip follow the target, minimising the mean squared relative stress error with
``scipy.optimize.differential_evolution`` (a population method, the closest scipy relative of
particle swarm optimisation), seeded, so the result is reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import itertools
import math

import numpy as np
from scipy.optimize import brentq, differential_evolution

from cgail_sim.pbd import (
    build_topology,
    internal_forces,
    PBDConfig,
    solve_vbd,
)

__all__ = ["CalibrationResult", "FungCurve", "StripTest", "calibrate", "strip_stress"]


@dataclass(frozen=True)
class FungCurve:
    """Exponential (Fung-type) uniaxial stress-strain curve ``sigma = E / b (exp(b eps) - 1)``."""

    youngs_modulus: float = 0.5e6
    """Small-strain slope E, Pa; > 0."""
    stiffening: float = 15.7
    """Exponent b (dimensionless); >= 0 (0 = linear)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.youngs_modulus) and self.youngs_modulus > 0):
            raise ValueError(f"youngs_modulus must be > 0 Pa, found {self.youngs_modulus!r}")
        if not (math.isfinite(self.stiffening) and self.stiffening >= 0):
            raise ValueError(f"stiffening must be >= 0, found {self.stiffening!r}")

    @classmethod
    def through(cls, youngs_modulus: float = 0.5e6, stretch: float = 1.08,
                stress: float = 80e3) -> FungCurve:
        """The curve with slope ``youngs_modulus`` at 0 that passes through (stretch, stress).

        Defaults: 0.5 MPa and 80 kPa at 1.08 (Jadidi 2020). The point must lie above the
        linear curve (``stress > E (stretch - 1)``), or no stiffening curve passes through it.
        """
        eps = stretch - 1.0
        if not (eps > 0 and stress > 0 and youngs_modulus > 0):
            raise ValueError(f"expected stretch > 1, stress > 0, E > 0, found stretch={stretch}, "
                             f"stress={stress}, E={youngs_modulus}")
        if stress <= youngs_modulus * eps:
            raise ValueError(
                f"stress must exceed the linear value E (stretch - 1) = "
                f"{youngs_modulus * eps:.6g} Pa for a stiffening curve, found {stress}")

        def gap(b: float) -> float:
            return youngs_modulus / b * math.expm1(b * eps) - stress

        b = brentq(gap, 1e-9, 200.0 / eps)
        return cls(youngs_modulus=youngs_modulus, stiffening=float(b))

    def stress(self, strain: np.ndarray | float) -> np.ndarray:
        """Nominal stress, Pa, at engineering strain(s)."""
        eps = np.asarray(strain, dtype=float)
        if self.stiffening == 0.0:
            return self.youngs_modulus * eps
        return self.youngs_modulus / self.stiffening * np.expm1(self.stiffening * eps)


@dataclass(frozen=True)
class StripTest:
    """Geometry and solver effort of the virtual uniaxial test."""

    length: float = 0.040
    """Strip length along the pull, m; > 0."""
    width: float = 0.010
    """Strip width, m; > 0."""
    spacing: float = 0.004
    """Lattice spacing (edge length), m, like the anatomy mesh; > 0."""
    sweeps: int = 200
    """Gauss-Seidel sweeps per strain level (exact stiffening law, Newton tangent)."""

    def __post_init__(self) -> None:
        for name in ("length", "width", "spacing"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0 m, found {v!r}")
        if self.spacing > min(self.length, self.width):
            raise ValueError(f"spacing must be <= min(length, width), found {self.spacing}")
        if not (isinstance(self.sweeps, int) and self.sweeps >= 1):
            raise ValueError(f"sweeps must be an int >= 1, found {self.sweeps!r}")


def _strip_mesh(test: StripTest) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangular lattice strip in the xy plane: vertices, faces, left-edge and right-edge ids.

    Even rows have nodes at ``i dx``; odd rows are shifted by ``dx / 2`` and closed by nodes on
    both ends, so the short edges are straight. Neighbouring rows are zipped into triangles.
    """
    nx = max(round(test.length / test.spacing), 1)
    ny = max(round(test.width / (test.spacing * math.sqrt(3.0) / 2.0)), 1)
    dx = test.length / nx
    dy = test.width / ny
    rows = []
    verts: list[tuple[float, float, float]] = []
    for j in range(ny + 1):
        if j % 2 == 0:
            xs = [i * dx for i in range(nx + 1)]
        else:
            xs = [0.0] + [(i + 0.5) * dx for i in range(nx)] + [test.length]
        rows.append(list(range(len(verts), len(verts) + len(xs))))
        verts.extend((x, j * dy, 0.0) for x in xs)
    faces = []
    for lo, hi in itertools.pairwise(rows):
        a, b = 0, 0
        while a < len(lo) - 1 or b < len(hi) - 1:
            adv_lo = b == len(hi) - 1 or (
                a < len(lo) - 1 and verts[lo[a + 1]][0] <= verts[hi[b + 1]][0])
            if adv_lo:
                faces.append((lo[a], lo[a + 1], hi[b]))
                a += 1
            else:
                faces.append((lo[a], hi[b + 1], hi[b]))
                b += 1
    v = np.array(verts)
    left = np.flatnonzero(v[:, 0] <= 1e-12)
    right = np.flatnonzero(v[:, 0] >= test.length - 1e-12)
    return v, np.array(faces, dtype=np.int64), left, right


def strip_stress(config: PBDConfig, strains: np.ndarray, test: StripTest | None = None
                 ) -> np.ndarray:
    """Nominal stress, Pa, of the PBD material in the virtual uniaxial test at each strain.

    Args:
        config: material parameters (youngs_modulus, stiffening, thickness are used).
        strains: increasing engineering strains (> 0) to load to, in order (continuation).
        test: strip geometry and solver effort.
    """
    test = test if test is not None else StripTest()
    eps_all = np.asarray(strains, dtype=float)
    if eps_all.ndim != 1 or eps_all.size == 0 or np.any(eps_all <= 0) \
            or np.any(np.diff(eps_all) <= 0):
        raise ValueError(f"strains must be a non-empty increasing array of values > 0, "
                         f"found {strains!r}")
    material = replace(config, tether_stiffness=0.0, bending_ratio=0.0)
    v, f, left, right = _strip_mesh(test)
    topo = build_topology(v, f, left, right, material)
    n = len(v)
    x = v.copy()
    factor = np.ones(len(topo.edges))  # unused: the exact law is evaluated in the sweep
    e = np.zeros(0, np.int64)
    z = np.zeros((1, 3))
    no_faces = np.zeros((1, 3), np.int64)
    out = np.empty(eps_all.size)
    dt = 1.0  # quasi-static: the inertia term m / dt^2 is negligible
    for k, eps in enumerate(eps_all):
        # Affine start (continuation from the previous level for the lateral contraction).
        x[:, 0] = v[:, 0] * (1.0 + eps)
        x[right, 0] = test.length * (1.0 + eps)
        x[left, 0] = 0.0
        solve_vbd(x, topo.inv_mass, topo.mass, topo.rest, topo.adj_ptr, topo.adj_other,
                  topo.adj_k, topo.adj_rest, topo.adj_edge, factor, topo.tether_k,
                  topo.vertex_order, dt, test.sweeps, no_faces, no_faces, z, z, z, e, e, z, 0.0,
                  np.zeros((n, 3)), np.zeros(n, np.int8), float(material.stiffening))
        forces = internal_forces(x, topo.rest, topo.edges, topo.edge_rest, topo.edge_k,
                                 material.stiffening, topo.hinges, topo.hinge_rest,
                                 topo.hinge_k, topo.tether_k)
        reaction = -forces[right, 0].sum()  # force needed to hold the pulled edge
        out[k] = reaction / (test.width * material.thickness)
    return out


@dataclass(frozen=True)
class CalibrationResult:
    """Outcome of :func:`calibrate`."""

    config: PBDConfig
    """The input config with the fitted ``youngs_modulus`` and ``stiffening``."""
    strains: np.ndarray
    """Strains the fit used."""
    target_stress: np.ndarray
    """Target stresses at those strains, Pa."""
    fitted_stress: np.ndarray
    """Simulated strip stresses with the fitted config, Pa."""
    rms_relative_error: float
    """Root-mean-square of (fitted - target) / target."""


def calibrate(target: FungCurve | None = None, base: PBDConfig | None = None,
              strains: np.ndarray | None = None, test: StripTest | None = None,
              modulus_bounds: tuple[float, float] = (0.05e6, 5e6),
              stiffening_bounds: tuple[float, float] = (0.0, 40.0), seed: int = 0,
              maxiter: int = 30, popsize: int = 8,
              target_stress: np.ndarray | None = None) -> CalibrationResult:
    """Fit ``youngs_modulus`` and ``stiffening`` of the PBD wall to a stress-strain curve.

    Args:
        target: the curve to reproduce (default: E = 0.5 MPa, 80 kPa at stretch 1.08).
        base: the config whose other fields are kept (default: ``PBDConfig()``).
        strains: strains to match (default: 1 % to 12 %, the physiological range and beyond).
        test: the virtual strip test.
        modulus_bounds, stiffening_bounds: search box of the two parameters.
        seed: seed of the differential evolution (reproducible result).
        maxiter, popsize: differential-evolution effort.
        target_stress: measured stresses, Pa, at ``strains`` (e.g. a tensile test of a
            patient's tissue); when given they replace ``target``.
    """
    target = target if target is not None else FungCurve.through()
    base = base if base is not None else PBDConfig()
    test = test if test is not None else StripTest()
    eps = np.asarray(strains if strains is not None else np.linspace(0.01, 0.12, 6), float)
    goal = target.stress(eps) if target_stress is None else np.asarray(target_stress, float)
    if goal.shape != eps.shape or not np.all(np.isfinite(goal)) or np.any(goal <= 0):
        raise ValueError(f"target stresses must be {eps.shape} positive finite values, "
                         f"found {goal!r}")

    def loss(p: np.ndarray) -> float:
        cfg = replace(base, youngs_modulus=float(p[0]) * 1e6, stiffening=float(p[1]))
        sim = strip_stress(cfg, eps, test)
        return float(np.mean(((sim - goal) / goal) ** 2))

    bounds = [(modulus_bounds[0] / 1e6, modulus_bounds[1] / 1e6), stiffening_bounds]
    res = differential_evolution(loss, bounds, seed=seed, maxiter=maxiter, popsize=popsize,
                                 tol=1e-8, polish=True)
    cfg = replace(base, youngs_modulus=float(res.x[0]) * 1e6, stiffening=float(res.x[1]))
    fitted = strip_stress(cfg, eps, test)
    rms = float(np.sqrt(np.mean(((fitted - goal) / goal) ** 2)))
    return CalibrationResult(config=cfg, strains=eps, target_stress=goal, fitted_stress=fitted,
                             rms_relative_error=rms)

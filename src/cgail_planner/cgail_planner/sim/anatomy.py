"""Parametric adult aorta for the simulator (first version: swept tube, no branches yet).

Frame ``phantom`` (SI units, metres): right-handed, x towards the patient's left, y posterior,
z cranial (DICOM LPS). The annulus centre is the origin. The descending aorta runs along -z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

__all__ = ["Anatomy", "AnatomyError", "AnatomyParams", "build_anatomy", "ANATOMY_NAMES"]


class AnatomyError(ValueError):
    """Raised for an invalid anatomy (bad parameters, broken mesh, missing landmarks)."""


@dataclass(frozen=True)
class AnatomyParams:
    """Shape parameters of the parametric aorta (all lengths in metres)."""

    annulus_diameter: float = 0.023
    """Aortic annulus inner diameter (23 mm; Davis 2014)."""
    sinus_diameter: float = 0.031
    """Sinus of Valsalva diameter, twice the maximal radial extent of a sinus (31 mm; Hager 2002)."""
    stj_diameter: float = 0.025
    """Sinotubular junction diameter (25 mm; Davis 2014)."""
    stj_height: float = 0.020
    """Sinotubular junction height above the annulus (20 mm; Monaldi 2019)."""
    ascending_diameter: float = 0.031
    """Mid-ascending diameter (31 mm; Hager 2002, Wolak 2008)."""
    descending_diameter: float = 0.0243
    """Descending aorta diameter at the open (caudal) end (24.3 mm at the diaphragm; Hager 2002)."""
    ascending_length: float = 0.050
    """Length of the straight ascending segment from the annulus to the arch start (estimate)."""
    descending_length: float = 0.120
    """Length of the descending segment below the arch end (model choice)."""
    arch_width: float = 0.072
    """Horizontal distance between ascending and descending centrelines (72 mm; estimate)."""
    arch_height: float = 0.045
    """Height of the arch centreline above the arch start (estimate)."""

    def __post_init__(self) -> None:
        ranges: dict[str, tuple[float, float]] = {
            "annulus_diameter": (0.015, 0.035),
            "sinus_diameter": (0.020, 0.050),
            "stj_diameter": (0.015, 0.040),
            "stj_height": (0.010, 0.035),
            "ascending_diameter": (0.018, 0.050),
            "descending_diameter": (0.012, 0.040),
            "ascending_length": (0.030, 0.120),
            "descending_length": (0.040, 0.300),
            "arch_width": (0.040, 0.120),
            "arch_height": (0.020, 0.120),
        }
        for name, (lo, hi) in ranges.items():
            value = getattr(self, name)
            if not (lo <= value <= hi):
                raise AnatomyError(f"{name} must be in [{lo}, {hi}] m, found {value}")


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=float) / float(np.linalg.norm(v))


@dataclass(frozen=True)
class Anatomy:
    """A watertight lumen surface plus the landmarks the simulator needs (see sim_iface)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    wall_face_mask: np.ndarray
    exit_point: np.ndarray
    exit_normal: np.ndarray
    fixed_vertices: np.ndarray
    annulus_vertices: np.ndarray
    annulus_center: np.ndarray
    root_axis: np.ndarray
    ostia: dict[str, np.ndarray]
    ostium_vertices: dict[str, int]
    start_point: np.ndarray
    start_direction: np.ndarray
    _mesh: Any = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        object.__setattr__(self, "_mesh", mesh)

    @property
    def mesh(self) -> trimesh.Trimesh:
        """The rest-shape surface as a trimesh object (shared, do not modify)."""
        return self._mesh

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Return a (P,) bool array: True where a point lies inside the lumen."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.asarray(self._mesh.contains(pts), dtype=bool)


def _tube_first_version(p: AnatomyParams, name: str) -> Anatomy:
    a = _unit(np.array([-0.3, -0.3, 1.0]))
    d = _unit(np.array([0.5, 0.866, 0.0]))
    z = np.array([0.0, 0.0, 1.0])
    pts = [a * s for s in np.linspace(0.0, p.ascending_length, 14)]
    start = a * p.ascending_length
    half_w = p.arch_width / 2
    for th in np.linspace(0.0, math.pi, 30)[1:]:
        pts.append(start + half_w * (1 - math.cos(th)) * d + p.arch_height * math.sin(th) * z)
    end = start + p.arch_width * d
    for s in np.linspace(0.0, p.descending_length, 30)[1:]:
        pts.append(end - s * z)
    spine = np.array(pts)
    seg = np.linalg.norm(np.diff(spine, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    radius = np.interp(
        arc,
        [0.0, p.stj_height / 2, p.stj_height, 0.035, arc[-1]],
        [p.annulus_diameter / 2, p.sinus_diameter / 2, p.stj_diameter / 2,
         p.ascending_diameter / 2, p.descending_diameter / 2],
    )
    tang = np.gradient(spine, axis=0)
    tang /= np.linalg.norm(tang, axis=1)[:, None]
    n0 = _unit(np.cross(tang[0], [1.0, 0.0, 0.0]))
    normals = [n0]
    for i in range(1, len(spine)):
        n = normals[-1] - np.dot(normals[-1], tang[i]) * tang[i]
        normals.append(_unit(n))
    nrm = np.array(normals)
    bin_ = np.cross(tang, nrm)
    n_around = 24
    phi = np.linspace(0.0, 2 * math.pi, n_around, endpoint=False)
    ring = (spine[:, None, :] + radius[:, None, None] * (
        np.cos(phi)[None, :, None] * nrm[:, None, :] + np.sin(phi)[None, :, None] * bin_[:, None, :]))
    verts = ring.reshape(-1, 3)
    faces = []
    n_rings = len(spine)
    for i in range(n_rings - 1):
        for j in range(n_around):
            a0 = i * n_around + j
            a1 = i * n_around + (j + 1) % n_around
            b0 = a0 + n_around
            b1 = a1 + n_around
            faces += [[a0, a1, b1], [a0, b1, b0]]
    c0 = len(verts)
    c1 = c0 + 1
    verts = np.vstack([verts, spine[0], spine[-1]])
    for j in range(n_around):
        faces.append([c0, (j + 1) % n_around, j])
        last = (n_rings - 1) * n_around
        faces.append([c1, last + j, last + (j + 1) % n_around])
    faces_arr = np.array(faces, dtype=np.int64)
    mesh = trimesh.Trimesh(verts, faces_arr, process=False)
    if mesh.volume < 0:
        faces_arr = faces_arr[:, ::-1].copy()
    wall = np.ones(len(faces_arr), dtype=bool)
    wall[-n_around:] = False
    wall[-2 * n_around::2] = True
    wall[-2 * n_around + 1::2] = False
    last = (n_rings - 1) * n_around
    fixed = np.concatenate([np.arange(last, last + n_around), [c1]]).astype(np.int64)
    ann = np.concatenate([np.arange(n_around), [c0]]).astype(np.int64)
    # Ostia: right anterior-ish, left at +123 deg.
    ostia = {}
    ostium_vertices = {}
    i_l = int(np.argmin(np.abs(arc - 0.0144)))
    i_r = int(np.argmin(np.abs(arc - 0.0172)))
    for key, i, j in (("right", i_r, 18), ("left", i_l, 2)):
        ostia[key] = ring[i, j].copy()
        ostium_vertices[key] = int(i * n_around + j)
    i_s = int(np.argmin(np.abs(arc - (arc[-1] - 0.02))))
    return Anatomy(
        name=name,
        vertices=verts,
        faces=faces_arr,
        wall_face_mask=wall,
        exit_point=spine[-1].copy(),
        exit_normal=-z,
        fixed_vertices=fixed,
        annulus_vertices=ann,
        annulus_center=spine[0].copy(),
        root_axis=a,
        ostia=ostia,
        ostium_vertices=ostium_vertices,
        start_point=spine[i_s].copy(),
        start_direction=z.copy(),
    )


_PARAMS: dict[str, AnatomyParams] = {
    "default": AnatomyParams(),
    "elongated": AnatomyParams(
        ascending_length=0.065, arch_width=0.063, arch_height=0.060, ascending_diameter=0.035
    ),
}
ANATOMY_NAMES: tuple[str, ...] = tuple(_PARAMS)
_CACHE: dict[str, Anatomy] = {}


def build_anatomy(name: str = "default") -> Anatomy:
    """Build (or return the cached) built-in anatomy ``name``."""
    if name not in _PARAMS:
        raise AnatomyError(f"anatomy must be one of {sorted(_PARAMS)}, found {name!r}")
    if name not in _CACHE:
        _CACHE[name] = _tube_first_version(_PARAMS[name], name)
    return _CACHE[name]

"""Parametric adult aorta for the simulator, and user meshes as anatomies.

Frame ``phantom`` (SI units, metres), right-handed DICOM LPS axes: x towards the patient's
LEFT, y POSTERIOR, z CRANIAL. The annulus centre is the origin; the descending aorta runs along
-z below the arch.

How the built-in aorta is made (all in :func:`build_anatomy`):

1. A centreline ("spine"): a straight ascending segment along the root axis (tilted towards
   the patient's right and anterior), a half-ellipse arch in a vertical plane rotated from the
   coronal plane towards posterior-left, and a straight descending segment along -z; the
   corners are smoothed with a Gaussian filter along the arc length.
2. An implicit field, negative in the lumen: spheres swept along the spine with a diameter
   profile through the landmark diameters below, a lobed root (three sinuses of Valsalva),
   three supra-aortic branch stubs and two coronary stubs, merged with a smooth minimum
   (fillets at the junctions).
3. Marching tetrahedra on a 3 mm grid (thin stubs inflated so they appear), then isotropic
   remeshing with projection onto the true field: ~3.7 mm edges, ~1.2 mm around the coronary
   ostia; ~2,450 vertices for "default", ~2,800 for "elongated". A cold build takes ~4 s CPU,
   so results are cached in memory and on disk (keyed by the parameters, the generator's
   source and numpy's SIMD level, :mod:`cgail_sim.disk_cache`: the remeshing
   amplifies the last-bit differences of numpy's SIMD ufuncs into a slightly different mesh
   on another CPU; :attr:`Anatomy.content_hash` identifies the mesh one got).
4. The open ends (descending end, branch-stub ends, coronary-stub ends) are cut flat and
   closed with cap faces (``wall_face_mask`` False, vertices in ``fixed_vertices``); the root is
   closed at the annulus by a flat valve plane that counts as WALL (``annulus_vertices``).

Default dimensions (inner lumen), from ``design/ANATOMY.md``:

=========================================  ==========  ===========================================
annulus diameter                           23 mm       Davis 2014; Tops 2008
sinus of Valsalva diameter                 31 mm       Hager 2002
sinotubular junction diameter / height     25 / 20 mm  Davis 2014; Monaldi Arch Chest Dis 2019
mid-ascending diameter                     31 mm       Hager 2002; Wolak 2008
proximal arch diameter                     29 mm       Hager 2002
transverse arch, proximal / distal         27.7 / 26.1 Hager 2002
isthmus / descending (diaphragm)           24.7 / 24.3 Hager 2002
left / right coronary ostium height        14.4 / 17.2 Tops 2008; Stolzmann 2009
angle between the ostia                    123 deg     Almuwaqqat 2012
ostium width left / right                  4.6 / 3.7   autopsy series (125 hearts)
annulus -> brachiocephalic (centreline)    90 mm       Frontiers Cardiovasc Med 2022
branch diameters BCT / LCCA / LSA          12.5 / 8.3 / 10.4 mm  CTA study of 217 arches
branch spacing BCT->LCCA / LCCA->LSA       15 / 17 mm  Chiu 2012
branch take-off angles                     45/26/29 deg  CT arch mapping, 118 patients
arch width / height                        72 / 45 mm  ESTIMATE (public synthetic aortas; see
                                                       ``AnatomyParams.arch_height``)
=========================================  ==========  ===========================================

The second built-in anatomy, "elongated", is the unfolded aorta of an older / hypertensive
patient: ascending length 50 -> 68 mm, ascending diameter 31 -> 35 mm, sinus diameter
31 -> 34 mm, STJ diameter 25 -> 26.5 mm, root tilt 25 -> 15 deg, arch width 72 -> 62 mm
(narrower), arch height 45 -> 62 mm (deeper), annulus-to-BCT 90 -> 112 mm, LCCA-LSA spacing
17 -> 19 mm, BCT take-off 45 -> 30 deg; everything else as the default.

Modelling choices that are NOT from a source (estimates): the ascending length (50 mm from the
annulus to the arch start), the arch plane rotation (60 deg from coronal), the root tilt
(25 deg towards right-anterior), the sinus bulge shape, the branch-stub length (25 mm beyond the
wall), the coronary-stub length (6 mm), the descending length (120 mm below the arch), the
optional bend of the descending aorta above its open end (``descending_bend``: off in both
built-in anatomies; a tortuous descending aorta for tests and populations), and
the interpretation of the branch take-off angle as the angle from the cranial axis within the
arch plane (BCT leaning right, LCCA and LSA leaning left).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import functools
import hashlib
import itertools
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree
import trimesh

from cgail_sim import disk_cache, exits, mesh_io
from cgail_sim.mesh_io import AnatomyError, MeshLoadError

__all__ = [
    "ANATOMY_NAMES",
    "Anatomy",
    "AnatomyError",
    "AnatomyParams",
    "AortaGeometry",
    "MeshLoadError",
    "anatomy_params",
    "build_anatomy",
    "build_anatomy_from_params",
    "load_anatomy_mesh",
    "save_anatomy_mesh",
]

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class AnatomyParams:
    """Shape parameters of the parametric aorta. Lengths in m, angles in rad.

    Defaults are the ANATOMY.md values (inner lumen diameters); see the module docstring for
    sources. Each field is validated in ``__post_init__``.
    """

    annulus_diameter: float = 0.023
    """Aortic annulus diameter (23 mm; Davis 2014, Tops 2008). Range 15-35 mm."""
    sinus_diameter: float = 0.031
    """Sinus of Valsalva diameter = twice the largest radial extent of a sinus from the root
    axis (31 mm; Hager 2002). Range 20-50 mm; must exceed the annulus and STJ diameters."""
    stj_diameter: float = 0.025
    """Sinotubular junction diameter (25 mm; Davis 2014). Range 15-40 mm."""
    stj_height: float = 0.020
    """Sinotubular junction height above the annulus (20 mm; Monaldi 2019). Range 12-35 mm."""
    ascending_diameter: float = 0.031
    """Mid-ascending diameter (31 mm; Hager 2002, Wolak 2008). Range 18-50 mm."""
    proximal_arch_diameter: float = 0.029
    """Proximal arch diameter, before the brachiocephalic trunk (29 mm; Hager 2002)."""
    arch_proximal_diameter: float = 0.0277
    """Transverse arch diameter between BCT and LCCA (27.7 mm; Hager 2002)."""
    arch_distal_diameter: float = 0.0261
    """Transverse arch diameter at the left subclavian (26.1 mm; Hager 2002)."""
    isthmus_diameter: float = 0.0247
    """Isthmus diameter, 20 mm distal to the LSA (24.7 mm; Hager 2002)."""
    descending_diameter: float = 0.0243
    """Descending diameter at the open caudal end (24.3 mm at the diaphragm; Hager 2002)."""
    ascending_length: float = 0.050
    """Length of the straight ascending segment from the annulus to the arch start along the
    root axis (estimate). Range 35-120 mm."""
    root_tilt: float = 25.0 * _DEG
    """Tilt of the root axis from cranial towards the patient's right-anterior (estimate for
    the default; in patients this is the "aortic angle" of the annulus plane against the
    horizontal, 49.4 +- 9.4 deg, range 18-90, Int J Cardiol 2021). Range 0-60 deg: beyond
    ~60 deg this generator's root frame (the right coronary sinus faces the anterior direction
    projected onto the annulus plane) turns the right ostium to the patient's left of the left
    one, the straight ascending segment meets the arch in a corner of < 12 mm bend radius, and
    the descending aorta swings behind the annulus (the annulus cut then fails unless the arch
    widens). Steeper roots need a curved ascending aorta in the generator."""
    arch_width: float = 0.072
    """Horizontal distance between the ascending and descending centrelines (72 mm; estimate
    from public synthetic aortas, Redheuil 2011 range 63-82). Range 40-120 mm."""
    arch_height: float = 0.045
    """Height of the arch-top centreline above the arch start (estimate). Redheuil's 'arch
    height' (~61 mm) is measured from the lower right-pulmonary-artery level, so it corresponds
    to roughly this value plus 15 mm. Range 20-120 mm."""
    arch_rotation: float = 60.0 * _DEG
    """Rotation of the arch plane from the coronal plane towards posterior (the descending aorta
    lies posterior-left of the ascending; estimate). Range 0-90 deg."""
    descending_length: float = 0.120
    """Length of the descending segment below the arch end (model choice). Range 50-300 mm."""
    descending_bend: float = 0.0
    """Angle the descending aorta turns through above its open end, towards the patient's
    right-anterior (towards the aortic hiatus, as an older, tortuous descending aorta does;
    model choice, 0 = straight, as in both built-in anatomies). Range 0-60 deg."""
    descending_bend_length: float = 0.060
    """Arc length of that bend, ending at the open descending end (model choice; used only when
    ``descending_bend`` > 0). Range 20 mm - ``descending_length``."""
    annulus_to_brachiocephalic: float = 0.090
    """Centreline distance from the annulus to the BCT origin (90 mm; Front Cardiovasc Med
    2022). Range 60-140 mm."""
    brachiocephalic_to_carotid: float = 0.015
    """Centreline spacing of the BCT and LCCA origins (15 mm; Chiu 2012). Range 8-35 mm."""
    carotid_to_subclavian: float = 0.017
    """Centreline spacing of the LCCA and LSA origins (17 mm; Chiu 2012). Range 8-35 mm."""
    brachiocephalic_diameter: float = 0.0125
    """Brachiocephalic trunk diameter (12.5 mm; CTA, 217 arches). Range 6-20 mm."""
    carotid_diameter: float = 0.0083
    """Left common carotid diameter (8.3 mm). Range 4-14 mm."""
    subclavian_diameter: float = 0.0104
    """Left subclavian diameter (10.4 mm). Range 5-16 mm."""
    brachiocephalic_angle: float = 45.0 * _DEG
    """BCT take-off angle from cranial, leaning right (45 deg; CT arch mapping). 0-70 deg."""
    carotid_angle: float = 26.0 * _DEG
    """LCCA take-off angle from cranial, leaning left (26 deg). Range 0-70 deg."""
    subclavian_angle: float = 29.0 * _DEG
    """LSA take-off angle from cranial, leaning left (29 deg). Range 0-70 deg."""
    branch_stub_length: float = 0.025
    """Length of each supra-aortic stub beyond the arch wall (model choice). 10-60 mm."""
    left_ostium_height: float = 0.0144
    """Left coronary ostium height above the annulus (14.4 mm; Tops 2008). Range 6-30 mm,
    below the sinotubular junction."""
    right_ostium_height: float = 0.0172
    """Right coronary ostium height above the annulus (17.2 mm; Tops 2008, Stolzmann 2009)."""
    ostia_angle: float = 123.0 * _DEG
    """Angle between the ostia around the root axis (123 deg; Almuwaqqat 2012). 90-160 deg."""
    left_ostium_diameter: float = 0.0046
    """Left ostium width (4.6 mm; autopsy series). Range 2-8 mm."""
    right_ostium_diameter: float = 0.0037
    """Right ostium width (3.7 mm; autopsy series). Range 2-8 mm."""
    coronary_stub_length: float = 0.006
    """Length of each coronary stub beyond the sinus wall (model choice). Range 3-20 mm."""
    edge_length: float = 0.0037
    """Target triangle edge length away from the coronary ostia (model choice: 3.7 mm gives
    ~2,450 vertices for the default, the size the PBD wall is budgeted for). Range 2-8 mm."""

    def __post_init__(self) -> None:
        mm = 1e-3
        ranges: dict[str, tuple[float, float]] = {
            "annulus_diameter": (15 * mm, 35 * mm),
            "sinus_diameter": (20 * mm, 50 * mm),
            "stj_diameter": (15 * mm, 40 * mm),
            "stj_height": (12 * mm, 35 * mm),
            "ascending_diameter": (18 * mm, 50 * mm),
            "proximal_arch_diameter": (15 * mm, 45 * mm),
            "arch_proximal_diameter": (15 * mm, 45 * mm),
            "arch_distal_diameter": (15 * mm, 45 * mm),
            "isthmus_diameter": (12 * mm, 40 * mm),
            "descending_diameter": (12 * mm, 40 * mm),
            "ascending_length": (35 * mm, 120 * mm),
            "root_tilt": (0.0, 60 * _DEG),
            "arch_width": (40 * mm, 120 * mm),
            "arch_height": (20 * mm, 120 * mm),
            "arch_rotation": (0.0, 90 * _DEG),
            "descending_length": (50 * mm, 300 * mm),
            "descending_bend": (0.0, 60 * _DEG),
            "descending_bend_length": (20 * mm, 300 * mm),
            "annulus_to_brachiocephalic": (60 * mm, 140 * mm),
            "brachiocephalic_to_carotid": (8 * mm, 35 * mm),
            "carotid_to_subclavian": (8 * mm, 35 * mm),
            "brachiocephalic_diameter": (6 * mm, 20 * mm),
            "carotid_diameter": (4 * mm, 14 * mm),
            "subclavian_diameter": (5 * mm, 16 * mm),
            "brachiocephalic_angle": (0.0, 70 * _DEG),
            "carotid_angle": (0.0, 70 * _DEG),
            "subclavian_angle": (0.0, 70 * _DEG),
            "branch_stub_length": (10 * mm, 60 * mm),
            "left_ostium_height": (6 * mm, 30 * mm),
            "right_ostium_height": (6 * mm, 30 * mm),
            "ostia_angle": (90 * _DEG, 160 * _DEG),
            "left_ostium_diameter": (2 * mm, 8 * mm),
            "right_ostium_diameter": (2 * mm, 8 * mm),
            "coronary_stub_length": (3 * mm, 20 * mm),
            "edge_length": (2 * mm, 8 * mm),
        }
        for name, (lo, hi) in ranges.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and lo <= value <= hi):
                raise AnatomyError(f"{name} must be in [{lo:.4g}, {hi:.4g}], found {value!r}")
        for name in ("left_ostium_height", "right_ostium_height"):
            h = getattr(self, name)
            if h > self.stj_height - 2 * mm:
                raise AnatomyError(
                    f"{name} must be at least 2 mm below stj_height={self.stj_height:.4g} m, "
                    f"found {h:.4g} m")
        if self.sinus_diameter < max(self.annulus_diameter, self.stj_diameter) + 2 * mm:
            raise AnatomyError(
                "sinus_diameter must exceed annulus_diameter and stj_diameter by 2 mm, found "
                f"{self.sinus_diameter:.4g} m")
        if self.ascending_length < self.stj_height + 20 * mm:
            raise AnatomyError(
                f"ascending_length must be >= stj_height + 20 mm = {self.stj_height + 0.02:.4g}"
                f" m, found {self.ascending_length:.4g} m")
        for name, spacing, d1, d2 in (
                ("brachiocephalic_to_carotid", self.brachiocephalic_to_carotid,
                 self.brachiocephalic_diameter, self.carotid_diameter),
                ("carotid_to_subclavian", self.carotid_to_subclavian, self.carotid_diameter,
                 self.subclavian_diameter)):
            if spacing < 0.5 * (d1 + d2) + 4 * mm:
                raise AnatomyError(
                    f"{name} must leave >= 4 mm of wall between the branch origins, i.e. be >= "
                    f"{0.5 * (d1 + d2) + 4 * mm:.4g} m for these diameters, found {spacing:.4g} m")
        if self.descending_bend_length > self.descending_length:
            raise AnatomyError(
                f"descending_bend_length must be <= descending_length = "
                f"{self.descending_length:.4g} m, found {self.descending_bend_length:.4g} m")
        if self.annulus_to_brachiocephalic < self.ascending_length:
            raise AnatomyError(
                "annulus_to_brachiocephalic must be >= ascending_length (the BCT arises from "
                f"the arch), found {self.annulus_to_brachiocephalic:.4g} m < "
                f"{self.ascending_length:.4g} m")


_PARAMS: dict[str, AnatomyParams] = {
    "default": AnatomyParams(),
    # Elongated, unfolded aorta of an older / hypertensive patient: longer and wider ascending
    # aorta, higher and narrower (more "gothic") arch, branches further from the annulus,
    # within or at the edge of the ANATOMY.md ranges.
    "elongated": AnatomyParams(
        ascending_length=0.068,          # 50 -> 68 mm
        ascending_diameter=0.035,        # 31 -> 35 mm (+1 SD, Hager 2002)
        sinus_diameter=0.034,            # 31 -> 34 mm (+0.7 SD)
        stj_diameter=0.0265,             # 25 -> 26.5 mm
        root_tilt=15.0 * _DEG,           # 25 -> 15 deg: more vertical root
        arch_width=0.062,                # 72 -> 62 mm (narrower)
        arch_height=0.062,               # 45 -> 62 mm (deeper)
        annulus_to_brachiocephalic=0.112,  # 90 -> 112 mm (longer ascending)
        carotid_to_subclavian=0.019,       # 17 -> 19 mm (Chiu 2012 mean 18.7)
        brachiocephalic_angle=30.0 * _DEG,  # 45 -> 30 deg (45 - 1 SD)
    ),
}
ANATOMY_NAMES: tuple[str, ...] = tuple(_PARAMS)


def anatomy_params(name: str) -> AnatomyParams:
    """The parameters of a built-in anatomy."""
    if name not in _PARAMS:
        raise AnatomyError(f"anatomy must be one of {sorted(_PARAMS)}, found {name!r}")
    return _PARAMS[name]


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / float(np.linalg.norm(v))


@dataclass(frozen=True, eq=False)
class Anatomy:
    """A watertight lumen surface plus the landmarks the simulator needs (see sim_iface.md).

    Attributes:
        name: anatomy name ("default", "elongated", or the file stem of a user mesh).
        vertices: (N, 3) rest-shape vertices, m.
        faces: (M, 3) int64, consistently oriented, normals out of the lumen; watertight.
        wall_face_mask: (M,) True for vessel wall (incl. the valve plane); False for cap
            faces closing the open ends.
        exit_point: (3,) centre of the open descending-aorta end.
        exit_normal: (3,) unit, out of the lumen (caudal) through that end.
        fixed_vertices: (K,) vertices PBD holds fixed: the boundary rings of the open ends and
            the cap vertices inside them.
        annulus_vertices: (R,) the annulus ring and the valve-plane vertices inside it (they
            move rigidly with the ring under the heartbeat).
        annulus_center: (3,) centre of the annulus.
        root_axis: (3,) unit, from the annulus into the ascending aorta.
        ostia: {'left', 'right'} ostium centres on the (virtual) sinus wall, m.
        ostium_vertices: {'left', 'right'} nearest wall vertex to each ostium.
        start_point: (3,) lumen point in the descending aorta near the exit end.
        start_direction: (3,) unit lumen direction there (cranial).

    Derived: :attr:`exit_discs`, the open cuts the tip can leave through (one per cap).
    All arrays are read-only copies. Equality and hashing are by identity (``eq=False``);
    :attr:`content_hash` compares contents.
    """

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
        # Own read-only copies, so neither the caller nor the simulator can change the rest
        # shape under the other's feet.
        dtypes = {"vertices": np.float64, "faces": np.int64, "wall_face_mask": bool,
                  "exit_point": np.float64, "exit_normal": np.float64,
                  "fixed_vertices": np.int64, "annulus_vertices": np.int64,
                  "annulus_center": np.float64, "root_axis": np.float64,
                  "start_point": np.float64, "start_direction": np.float64}
        for name, dtype in dtypes.items():
            arr = np.array(getattr(self, name), dtype=dtype)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        ostia = {}
        for side, point in self.ostia.items():
            arr = np.array(point, dtype=np.float64)
            arr.setflags(write=False)
            ostia[side] = arr
        object.__setattr__(self, "ostia", ostia)
        mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        object.__setattr__(self, "_mesh", mesh)

    def __repr__(self) -> str:
        # (the dataclass repr would print every vertex: errors that show an anatomy use this)
        return (f"Anatomy(name={self.name!r}, {len(self.vertices)} vertices, "
                f"{len(self.faces)} faces, content_hash={self.content_hash!r})")

    @functools.cached_property
    def content_hash(self) -> str:
        """SHA-256 (16 hex digits) of the mesh and landmarks: every array attribute, the
        ostia and their vertices, not the name.

        Two builds of a built-in anatomy agree on it only where numpy ran the same SIMD code
        (:mod:`cgail_sim.disk_cache`); demonstration bags store it to identify the
        anatomy they were recorded in.
        """
        h = hashlib.sha256()
        for key in _ARRAYS:
            arr = np.asarray(getattr(self, key))
            kind = {"f": "<f8", "i": "<i8", "b": "u1"}[arr.dtype.kind]
            h.update(f"{key}{arr.shape}".encode())
            h.update(np.ascontiguousarray(arr, dtype=kind).tobytes())
        for side in sorted(self.ostia):
            h.update(f"ostium_{side}".encode())
            h.update(np.ascontiguousarray(self.ostia[side], dtype="<f8").tobytes())
            h.update(str(int(self.ostium_vertices[side])).encode())
        return h.hexdigest()[:16]

    @functools.cached_property
    def exit_discs(self) -> np.ndarray:
        """(D, 7) the open cuts as discs, the one exit rule's input (:mod:`cgail_sim.
        exits`): one row ``(centre, normal out of the lumen, radius)`` per cap (a connected
        region of ``wall_face_mask == False`` faces), measured from the cap faces.

        Row 0 is the descending end: centre :attr:`exit_point`, normal :attr:`exit_normal` and
        the largest distance of its cap's vertices from that centre, in the plane. The other
        caps (supra-aortic branch and coronary stub ends) follow: their area-weighted centroid,
        mean normal and largest in-plane vertex distance. The valve plane at the annulus is
        wall (the valve is closed: the tip collides with it), so it is no disc; a mesh whose
        annulus is an open cap gets a disc there like any cap.

        Raises:
            AnatomyError: no cap around :attr:`exit_point` (every anatomy the loaders and
                ``prepare_anatomy`` make has one).
        """
        return _exit_discs(self)

    @property
    def mesh(self) -> trimesh.Trimesh:
        """The rest-shape surface as a trimesh object (shared: do not modify)."""
        return self._mesh

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(P,) bool: True where a point lies inside the lumen (rest shape)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        if len(pts) == 0:
            return np.zeros(0, dtype=bool)
        return np.asarray(self._mesh.contains(pts), dtype=bool)


# ------------------------------------------------------------------------------------------
# Geometry of the parametric aorta
# ------------------------------------------------------------------------------------------
_EXT = 0.008
"""Extension of every tube beyond its clip plane, so the cut crosses a clean cylinder (m)."""
_GRID = 0.003
"""Spacing of the marching-tetrahedra grid before remeshing (m)."""
_STEP = 0.0005
"""Spacing of the dense spine samples (m)."""


@dataclass
class _Tube:
    """A straight stub: axis from ``start`` along ``direction``, clipped at ``length``."""

    name: str
    start: np.ndarray
    direction: np.ndarray
    radius: float
    length: float
    blend: float

    @property
    def end(self) -> np.ndarray:
        return self.start + self.length * self.direction


class AortaGeometry:
    """The generator's geometry for one parameter set: the dense spine (``spine``, ``arc`` with
    s = 0 at the annulus, ``tangent``, ``radius``), the root frame (``axis``, ``e1`` towards
    the right coronary sinus, ``e2``), the branch and coronary stubs (``tubes``), the ostia,
    and the implicit ``field``. :func:`build_anatomy` meshes it; tests use it to measure the
    mesh against the parameters."""

    def __init__(self, p: AnatomyParams) -> None:
        self.p = p
        z = np.array([0.0, 0.0, 1.0])
        self.z = z
        right_ant = _unit(np.array([-1.0, -1.0, 0.0]))
        self.axis = _unit(math.cos(p.root_tilt) * z + math.sin(p.root_tilt) * right_ant)
        rot = p.arch_rotation
        self.d = np.array([math.cos(rot), math.sin(rot), 0.0])   # towards left-posterior
        start = p.ascending_length * self.axis
        half = p.arch_width / 2
        pts = [np.outer(np.arange(-_EXT - 0.01, p.ascending_length, _STEP), self.axis)]
        th = np.linspace(0.0, math.pi, 400)
        pts.append(start + half * (1 - np.cos(th))[:, None] * self.d
                   + p.arch_height * np.sin(th)[:, None] * z)
        end = start + p.arch_width * self.d
        if p.descending_bend > 0.0:
            descending, raw_exit = _bent_descending(end, p)
            pts.append(descending)
        else:
            pts.append(end - np.outer(np.arange(_STEP, p.descending_length + _EXT + 0.02, _STEP),
                                      z))
        raw = np.vstack(pts)
        raw = _resample(raw, _STEP)
        smooth = gaussian_filter1d(raw, sigma=0.007 / _STEP, axis=0, mode="nearest")
        spine = _resample(smooth, _STEP)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(spine, axis=0), axis=1))])
        # s = 0 at the annulus (the origin, on the straight root segment).
        arc -= arc[int(np.argmin(np.linalg.norm(spine, axis=1)))]
        self.spine = spine
        self.arc = arc
        tang = np.gradient(spine, axis=0)
        self.tangent = tang / np.linalg.norm(tang, axis=1, keepdims=True)
        # Descending end: the spine point descending_length below the arch end (along the
        # bend, when there is one).
        if p.descending_bend > 0.0:
            i_exit = int(np.argmin(np.linalg.norm(spine - raw_exit, axis=1)
                                   + 1e3 * (arc < arc[-1] / 2)))
        else:
            z_exit = end[2] - p.descending_length
            i_exit = int(np.argmin(np.abs(spine[:, 2] - z_exit) + 1e3 * (arc < arc[-1] / 2)))
        self.s_exit = float(arc[i_exit])
        self.exit_point = spine[i_exit].copy()
        self.exit_normal = self.tangent[i_exit].copy()
        s_bct = p.annulus_to_brachiocephalic
        s_lcc = s_bct + p.brachiocephalic_to_carotid
        s_lsa = s_lcc + p.carotid_to_subclavian
        s_top = float(arc[int(np.argmax(spine[:, 2]))])
        if s_lsa > s_top + 0.6 * (self.s_exit - s_top):
            raise AnatomyError(
                "annulus_to_brachiocephalic + spacings must place the left subclavian on the "
                f"arch, found it {s_lsa * 1e3:.0f} mm along a centreline whose arch top is at "
                f"{s_top * 1e3:.0f} mm")
        knots_s = [-0.05, 0.0, p.stj_height, 0.5 * (p.stj_height + s_bct),
                   s_bct - 0.5 * p.brachiocephalic_diameter - 0.003, s_lcc, s_lsa,
                   s_lsa + 0.020, self.s_exit, self.s_exit + 0.1]
        knots_d = [p.annulus_diameter, p.annulus_diameter, p.stj_diameter, p.ascending_diameter,
                   p.proximal_arch_diameter, p.arch_proximal_diameter, p.arch_distal_diameter,
                   p.isthmus_diameter, p.descending_diameter, p.descending_diameter]
        self.diameter_at = PchipInterpolator(knots_s, knots_d, extrapolate=True)
        self.radius = 0.5 * self.diameter_at(arc)
        self.s_branches = {"brachiocephalic": s_bct, "carotid": s_lcc, "subclavian": s_lsa}
        # Root frame: e1 points to the right coronary sinus (anterior), e2 completes it.
        ant = np.array([0.0, -1.0, 0.0])
        e1 = _unit(ant - (ant @ self.axis) * self.axis)
        e2 = np.cross(self.axis, e1)
        self.e1, self.e2 = e1, e2
        # The left ostium lies towards the patient's left (+x): pick the rotation sign.
        sign = 1.0 if (math.cos(p.ostia_angle) * e1 + math.sin(p.ostia_angle) * e2)[0] > 0 \
            else -1.0
        self.phi_right = 0.0
        self.phi_left = sign * p.ostia_angle
        self.sinus_phis = np.array([0.0, sign * 2 * math.pi / 3, -sign * 2 * math.pi / 3])
        # Tubes.
        self.tubes: list[_Tube] = []
        for name, s_b, dia, ang, lean in (
                ("brachiocephalic", s_bct, p.brachiocephalic_diameter,
                 p.brachiocephalic_angle, -1.0),
                ("carotid", s_lcc, p.carotid_diameter, p.carotid_angle, 1.0),
                ("subclavian", s_lsa, p.subclavian_diameter, p.subclavian_angle, 1.0)):
            i = int(np.argmin(np.abs(arc - s_b)))
            direction = _unit(math.cos(ang) * z + math.sin(ang) * lean * self.d)
            length = float(self.radius[i]) + p.branch_stub_length
            self.tubes.append(_Tube(name, spine[i].copy(), direction, dia / 2, length, 0.003))
        self.ostia: dict[str, np.ndarray] = {}
        for side, h, phi, dia in (
                ("left", p.left_ostium_height, self.phi_left, p.left_ostium_diameter),
                ("right", p.right_ostium_height, self.phi_right, p.right_ostium_diameter)):
            radial = math.cos(phi) * e1 + math.sin(phi) * e2
            wall = float(self.root_radius(np.array([h]), np.array([phi]))[0])
            origin = h * self.axis
            self.ostia[side] = origin + wall * radial
            self.tubes.append(_Tube(f"{side}_coronary", origin, radial, dia / 2,
                                    wall + p.coronary_stub_length, 0.0012))
        self.tree = cKDTree(spine)
        self._check_stub_clearance()

    def _check_stub_clearance(self) -> None:
        """Neighbouring supra-aortic stubs must not converge (they would merge when meshed)."""
        p = self.p
        t = np.linspace(0.0, 1.0, 60)
        angles = {"brachiocephalic": "brachiocephalic_angle", "carotid": "carotid_angle",
                  "subclavian": "subclavian_angle"}
        stubs = [tb for tb in self.tubes if tb.name in angles]
        for a, b in itertools.pairwise(stubs):
            # Compare the parts outside the arch lumen (from half-way out to the cut).
            pa = a.start + np.outer(0.5 * a.length + t * 0.5 * a.length, a.direction)
            pb = b.start + np.outer(0.5 * b.length + t * 0.5 * b.length, b.direction)
            gap = float(np.min(np.linalg.norm(pa[:, None] - pb[None], axis=2))) \
                - a.radius - b.radius
            need = 1.2 * p.edge_length
            if gap < need:
                raise AnatomyError(
                    f"{angles[a.name]} and {angles[b.name]} must keep the {a.name} and {b.name} "
                    f"stubs >= {need * 1e3:.1f} mm apart (1.2 mesh edges), found "
                    f"{gap * 1e3:.1f} mm: make them diverge (larger {angles[b.name]} leans the "
                    f"{b.name} further left) or space the origins further apart")

    # -- field -----------------------------------------------------------------------------
    def root_radius(self, h: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Radius of the lobed root at height h above the annulus and angle phi (from e1)."""
        p = self.p
        hs = np.clip(h / p.stj_height, 0.0, 1.0)
        base = 0.5 * (p.annulus_diameter + (p.stj_diameter - p.annulus_diameter) * hs)
        peak_base = 0.5 * (p.annulus_diameter + p.stj_diameter) / 2
        bump = (0.5 * p.sinus_diameter - peak_base) * np.sin(np.pi * hs)
        dphi = np.angle(np.exp(1j * (phi[:, None] - self.sinus_phis[None, :])))
        lobe = np.clip(np.cos(1.5 * dphi), 0.0, None).max(axis=1)
        return base + bump * lobe

    def field(self, pts: np.ndarray, min_tube_radius: float = 0.0) -> np.ndarray:
        """Signed field, negative inside the lumen (approximately a distance near the wall).

        ``min_tube_radius`` inflates thinner stubs; the coarse extraction grid uses it so that
        the coronary stubs appear (as bumps of the right topology) before remeshing projects
        them onto their true radius.
        """
        pts = np.asarray(pts, dtype=float)
        dist, idx = self.tree.query(pts, k=4)
        f = (dist - self.radius[idx]).min(axis=1)
        # Lobed root (sinuses of Valsalva) on 0 <= h <= stj_height.
        h = pts @ self.axis
        q = pts - h[:, None] * self.axis
        rho = np.linalg.norm(q, axis=1)
        phi = np.arctan2(q @ self.e2, q @ self.e1)
        root = rho - self.root_radius(h, phi)
        root = np.maximum(root, np.maximum(-h, h - self.p.stj_height))
        f = np.minimum(f, root)
        for tube in self.tubes:
            rel = pts - tube.start
            t = np.clip(rel @ tube.direction, 0.0, tube.length + _EXT)
            d = np.linalg.norm(rel - t[:, None] * tube.direction, axis=1) - max(
                tube.radius, min_tube_radius)
            f = _smin(f, d, tube.blend)
        return f

    def target_edge(self, pts: np.ndarray) -> np.ndarray:
        """Target edge length: ``edge_length``, refined to ~1.2 mm around the ostia."""
        pts = np.atleast_2d(pts)
        near = np.min([np.linalg.norm(pts - o, axis=1) for o in self.ostia.values()], axis=0)
        return np.minimum(self.p.edge_length, 0.0012 + 0.35 * np.maximum(near - 0.003, 0.0))


#: Direction the descending aorta bends towards (``AnatomyParams.descending_bend``): the
#: patient's right-anterior, horizontal.
_BEND_DIRECTION = np.array([-1.0, -1.0, 0.0]) / math.sqrt(2.0)


def _bent_descending(end: np.ndarray, p: AnatomyParams) -> tuple[np.ndarray, np.ndarray]:
    """Raw spine of a bent descending aorta below the arch end ``end`` and its open end.

    Straight down (-z) for ``descending_length - descending_bend_length``, then a circular arc
    of ``descending_bend_length`` turning through ``descending_bend`` towards
    :data:`_BEND_DIRECTION`, then straight on along the final tangent past the open end (as the
    straight aorta runs on past its end, so the cut crosses a clean cylinder).

    Returns:
        ``(points (K, 3) every _STEP from the arch end, open end (3,))``.
    """
    down = np.array([0.0, 0.0, -1.0])
    straight = p.descending_length - p.descending_bend_length
    radius = p.descending_bend_length / p.descending_bend
    s = np.arange(_STEP, p.descending_length + _EXT + 0.02, _STEP)
    top = end + straight * down
    theta = p.descending_bend
    tangent = math.cos(theta) * down + math.sin(theta) * _BEND_DIRECTION
    bottom = top + radius * (math.sin(theta) * down + (1.0 - math.cos(theta)) * _BEND_DIRECTION)
    out = np.empty((len(s), 3))
    upper = s <= straight
    out[upper] = end + np.outer(s[upper], down)
    arc = (s > straight) & (s <= p.descending_length)
    phi = (s[arc] - straight) / radius
    out[arc] = top + radius * (np.outer(np.sin(phi), down)
                               + np.outer(1.0 - np.cos(phi), _BEND_DIRECTION))
    lower = s > p.descending_length
    out[lower] = bottom + np.outer(s[lower] - p.descending_length, tangent)
    return out, bottom


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (fillet of radius ~k)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _resample(points: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-12])
    points = points[keep]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    s = np.arange(0.0, arc[-1], step)
    return np.stack([np.interp(s, arc, points[:, k]) for k in range(3)], axis=1)


def _build(p: AnatomyParams, name: str) -> Anatomy:
    g = AortaGeometry(p)
    spacing = _GRID
    lo = g.spine.min(axis=0) - 0.025
    hi = g.spine.max(axis=0) + 0.025
    for tube in g.tubes:
        lo = np.minimum(lo, tube.end - 0.02)
        hi = np.maximum(hi, tube.end + 0.02)
    shape = np.ceil((hi - lo) / spacing).astype(int) + 1
    axes = [lo[k] + spacing * np.arange(shape[k]) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    # Only evaluate near the spine; far samples are plainly outside.
    near = g.tree.query(grid, distance_upper_bound=0.045)[0] < np.inf
    for tube in g.tubes:
        rel = grid - tube.start
        t = np.clip(rel @ tube.direction, 0.0, tube.length + _EXT)
        near |= np.linalg.norm(rel - t[:, None] * tube.direction, axis=1) < tube.radius + 0.01
    values = np.full(len(grid), 1.0)
    values[near] = g.field(grid[near], min_tube_radius=0.9 * spacing)
    verts, faces = mesh_io.marching_tetrahedra(values.reshape(tuple(shape)), lo, spacing)
    verts, faces = mesh_io.largest_component(verts, faces)
    remesher = mesh_io.Remesher(verts, faces, g.field, g.target_edge)
    verts, faces = remesher.run(iterations=5)
    # Clip and cap: descending end, branch ends and coronary ends (caps) and the annulus
    # (valve plane, wall).
    cap_mask = np.zeros(len(faces), dtype=bool)
    caps: list[tuple[str, np.ndarray, np.ndarray, float, float, bool]] = [
        ("descending", g.exit_point, g.exit_normal, 0.5 * p.descending_diameter, p.edge_length,
         False),
        ("annulus", np.zeros(3), -g.axis, 0.5 * p.annulus_diameter, p.edge_length, True),
    ]
    for tube in g.tubes:
        edge = float(g.target_edge(tube.end[None])[0])
        caps.append((tube.name, tube.end, tube.direction, tube.radius, edge, False))
    fixed: list[np.ndarray] = []
    annulus_ids = np.zeros(0, dtype=np.int64)
    for _cap_name, point, normal, radius, edge, is_wall in caps:
        verts, new_faces, kept, cap_ids = mesh_io.clip_and_cap(
            verts, faces, point, normal, radius + 0.001, _EXT + radius + 0.002, edge, g.field)
        n_new = len(new_faces) - len(kept)
        cap_mask = np.concatenate([cap_mask[kept], np.full(n_new, not is_wall)])
        faces = new_faces
        if is_wall:
            annulus_ids = cap_ids
        else:
            fixed.append(cap_ids)
    verts, faces, remap = mesh_io.compact_with_map(verts, faces)
    euler = len(verts) - len(np.unique(np.sort(np.concatenate(
        [faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)) + len(faces)
    if euler != 2:
        raise AnatomyError(f"expected a sphere-like lumen surface (Euler characteristic 2), "
                           f"found {euler}: branches too close for the meshing grid?")
    fixed_ids = remap[np.concatenate(fixed)]
    annulus_ids = remap[annulus_ids]
    wall_mask = ~cap_mask
    # Relax the triangles next to the cuts (cap and valve-plane vertices held).
    hold = np.zeros(len(verts), dtype=bool)
    hold[fixed_ids] = True
    hold[annulus_ids] = True
    verts = mesh_io.relax(verts, faces, g.field, hold, iterations=3)
    return _assemble(name, verts, faces, wall_mask, g, np.unique(fixed_ids), annulus_ids)


def _assemble(name: str, verts: np.ndarray, faces: np.ndarray, wall_mask: np.ndarray,
              g: AortaGeometry, fixed: np.ndarray, annulus_ids: np.ndarray) -> Anatomy:
    p = g.p
    wall_vertices = np.unique(faces[wall_mask])
    wall_tree = cKDTree(verts[wall_vertices])
    ostium_vertices = {k: int(wall_vertices[wall_tree.query(o)[1]]) for k, o in g.ostia.items()}
    i_start = int(np.argmin(np.abs(g.arc - (g.s_exit - 0.02))))
    del p
    return Anatomy(
        name=name,
        vertices=verts,
        faces=faces.astype(np.int64),
        wall_face_mask=wall_mask,
        exit_point=g.exit_point.copy(),
        exit_normal=_unit(g.exit_normal),
        fixed_vertices=fixed.astype(np.int64),
        annulus_vertices=np.unique(annulus_ids).astype(np.int64),
        annulus_center=np.zeros(3),
        root_axis=g.axis.copy(),
        ostia={k: v.copy() for k, v in g.ostia.items()},
        ostium_vertices=ostium_vertices,
        start_point=g.spine[i_start].copy(),
        start_direction=_unit(-g.tangent[i_start]),
    )


def _exit_discs(anatomy: Anatomy) -> np.ndarray:
    """:attr:`Anatomy.exit_discs` measured from the cap faces."""
    caps = np.flatnonzero(~anatomy.wall_face_mask)
    label = _face_components(anatomy.faces[caps]) if len(caps) else np.zeros(0, np.int64)
    regions = [anatomy.faces[caps[label == k]] for k in np.unique(label)]
    centroids, normals, areas = [], [], []
    for faces in regions:
        tri = anatomy.vertices[faces]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = 0.5 * np.linalg.norm(cross, axis=1)
        centroids.append((tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum())
        normals.append(_unit(cross.sum(axis=0)))
        areas.append(float(area.sum()))
    exit_point = np.asarray(anatomy.exit_point, dtype=np.float64)
    gaps = [float(np.linalg.norm(c - exit_point)) for c in centroids]
    # the descending cap: the one whose centroid is nearest exit_point, within its own size
    first = int(np.argmin(gaps)) if regions else -1
    if first < 0 or gaps[first] > 2.0 * math.sqrt(areas[first] / math.pi):
        found = f"the nearest cap {min(gaps) * 1e3:.1f} mm away" if regions else "no cap faces"
        raise AnatomyError(f"expected a cap (wall_face_mask False) closing the descending end "
                           f"at exit_point {np.round(exit_point * 1e3, 1).tolist()} mm, found "
                           f"{found}")
    centroids[first], normals[first] = exit_point, _unit(anatomy.exit_normal)
    order = [first] + [k for k in range(len(regions)) if k != first]
    radii = []
    for k in order:
        rel = anatomy.vertices[np.unique(regions[k])] - centroids[k]
        in_plane = rel - (rel @ normals[k])[:, None] * normals[k]
        radii.append(float(np.linalg.norm(in_plane, axis=1).max()))
    return exits.disc_array(np.array([centroids[k] for k in order]),
                            np.array([normals[k] for k in order]), np.array(radii))


_CACHE: dict[str, Anatomy] = {}
_ARRAYS = ("vertices", "faces", "wall_face_mask", "exit_point", "exit_normal", "fixed_vertices",
           "annulus_vertices", "annulus_center", "root_axis", "start_point", "start_direction")


def _cache_path(name: str, params: AnatomyParams) -> Path | None:
    """Disk-cache file of a built anatomy, or None when the disk cache is off.

    Keyed by the name and parameters, the sources of the generator (this module,
    :mod:`~cgail_sim.mesh_io` and the key's own module) and the numerical environment
    (numpy's SIMD level and the library versions, :func:`disk_cache.numerical_environment`):
    a mesh built by another commit or by another CPU's numpy is never read back.
    """
    root = disk_cache.cache_dir()
    if root is None:
        return None
    key = disk_cache.cache_key(sources=(__file__, mesh_io.__file__, disk_cache.__file__),
                               inputs=f"{name}|{params!r}", length=16)
    name = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)[:40]
    return root / f"anatomy_{name}_{key}.npz"


def _load_cached(name: str, path: Path | None) -> Anatomy | None:
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path) as data:
            arrays = {k: np.array(data[k]) for k in _ARRAYS}
            ostia = {s: np.array(data[f"ostium_{s}"]) for s in ("left", "right")}
            ostium_vertices = {s: int(data[f"ostium_vertex_{s}"]) for s in ("left", "right")}
    except (OSError, KeyError, ValueError):
        return None
    return Anatomy(name=name, ostia=ostia, ostium_vertices=ostium_vertices, **arrays)


def _save_cached(anatomy: Anatomy, path: Path | None) -> None:
    if path is None:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
        arrays: dict[str, np.ndarray] = {k: np.asarray(getattr(anatomy, k)) for k in _ARRAYS}
        for side in ("left", "right"):
            arrays[f"ostium_{side}"] = np.asarray(anatomy.ostia[side])
            arrays[f"ostium_vertex_{side}"] = np.asarray(anatomy.ostium_vertices[side])
        np.savez(tmp, **arrays)  # type: ignore[arg-type]  # numpy stubs mistype **kwds
        os.replace(tmp, path)
    except OSError:
        pass


def build_anatomy_from_params(params: AnatomyParams, name: str = "custom") -> Anatomy:
    """Build an anatomy from custom parameters (cached like :func:`build_anatomy`).

    Raises:
        AnatomyError: parameters whose geometry cannot be meshed (e.g. converging branch
            stubs), with the field names to change.
    """
    if not isinstance(params, AnatomyParams):
        raise AnatomyError(f"params must be an AnatomyParams, found {type(params).__name__}")
    key = f"{name}|{params!r}"
    if key not in _CACHE:
        path = _cache_path(name, params)
        anatomy = _load_cached(name, path)
        if anatomy is None:
            anatomy = _build(params, name)
            _save_cached(anatomy, path)
        _CACHE[key] = anatomy
    return _CACHE[key]


def build_anatomy(name: str = "default") -> Anatomy:
    """Build (or return the cached) built-in anatomy.

    Args:
        name: one of :data:`ANATOMY_NAMES` ("default", "elongated").

    Returns:
        The anatomy. It is cached in memory per process and on disk under
        ``~/.cache/cgail_planner/`` (keyed by the parameters, this code and numpy's SIMD
        level, see :mod:`cgail_sim.disk_cache`; set ``CGAIL_PLANNER_NO_DISK_CACHE=1``
        to disable), since a cold build takes a few seconds.

    Raises:
        AnatomyError: unknown name.
    """
    return build_anatomy_from_params(anatomy_params(name), name)


# ------------------------------------------------------------------------------------------
# User meshes
# ------------------------------------------------------------------------------------------
_LANDMARK_KEYS = ("exit_point", "annulus_center", "left_ostium", "right_ostium")
_OPTIONAL_KEYS = ("start_point", "exit_normal", "root_axis", "start_direction", "caps")


def save_anatomy_mesh(anatomy: Anatomy, path: str | Path) -> Path:
    """Write the anatomy as a mesh in millimetres plus a ``<stem>.yaml`` landmark sidecar.

    The pair round-trips through :func:`load_anatomy_mesh`. Cap centres other than the exit are
    written under ``caps`` so the loader marks the same faces as caps.

    Returns:
        The path of the YAML sidecar.
    """
    import yaml

    p = Path(path)
    mesh = trimesh.Trimesh(anatomy.vertices * 1e3, anatomy.faces, process=False)
    mesh.export(p)
    caps = []
    cap_faces = np.flatnonzero(~anatomy.wall_face_mask)
    if len(cap_faces):
        adj = _face_components(anatomy.faces[cap_faces])
        for label in np.unique(adj):
            tri = anatomy.vertices[anatomy.faces[cap_faces[adj == label]]]
            centre = tri.reshape(-1, 3).mean(axis=0)
            if np.linalg.norm(centre - anatomy.exit_point) > 0.003:
                caps.append([round(float(x) * 1e3, 4) for x in centre])

    def mm(v: np.ndarray) -> list[float]:
        return [round(float(x) * 1e3, 4) for x in v]

    data = {
        "units": "mm",
        "exit_point": mm(anatomy.exit_point),
        "exit_normal": [round(float(x), 6) for x in anatomy.exit_normal],
        "annulus_center": mm(anatomy.annulus_center),
        "root_axis": [round(float(x), 6) for x in anatomy.root_axis],
        "left_ostium": mm(anatomy.ostia["left"]),
        "right_ostium": mm(anatomy.ostia["right"]),
        "start_point": mm(anatomy.start_point),
        "start_direction": [round(float(x), 6) for x in anatomy.start_direction],
        "caps": caps,
    }
    sidecar = p.with_suffix(".yaml")
    sidecar.write_text(yaml.safe_dump(data, sort_keys=False))
    return sidecar


def _face_components(faces: np.ndarray) -> np.ndarray:
    """Label of the vertex-connected component of each face."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = int(faces.max()) + 1
    a = np.concatenate([faces[:, 0], faces[:, 1]])
    b = np.concatenate([faces[:, 1], faces[:, 2]])
    _, label = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)),
                                    directed=False)
    return label[faces[:, 0]]


def _vec(landmarks: dict[str, Any], key: str, source: str) -> np.ndarray:
    value = np.asarray(landmarks[key], dtype=float)
    if value.shape != (3,) or not np.all(np.isfinite(value)):
        raise MeshLoadError(f"landmark {key} must be 3 finite numbers (mm), found "
                            f"{landmarks[key]!r} in {source}")
    return value


def _planar_region(mesh: trimesh.Trimesh, point: np.ndarray, tol: float) -> np.ndarray:
    """Faces coplanar (within ``tol``) and edge-connected with the face nearest ``point``."""
    _, _, tri = trimesh.proximity.closest_point(mesh, point[None])
    seed = int(tri[0])
    n0 = mesh.face_normals[seed]
    c0 = mesh.triangles_center[seed]
    flat = (np.abs((mesh.vertices[mesh.faces] - c0) @ n0).max(axis=1) < tol) & (
        mesh.face_normals @ n0 > 0.98)
    if not flat[seed]:
        return np.zeros(0, dtype=np.int64)
    adj = mesh.face_adjacency
    keep = flat[adj[:, 0]] & flat[adj[:, 1]]
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = len(mesh.faces)
    graph = coo_matrix((np.ones(int(keep.sum())), (adj[keep, 0], adj[keep, 1])), shape=(m, m))
    _, label = connected_components(graph, directed=False)
    return np.flatnonzero(flat & (label == label[seed]))


def load_anatomy_mesh(path: str | Path, landmarks: dict[str, Any] | None = None,
                      name: str | None = None) -> Anatomy:
    """Load a user lumen surface (STL/OBJ/PLY in millimetres) as an :class:`Anatomy`.

    The mesh must be one closed (watertight) surface whose open ends are closed with flat caps.
    Landmarks, in millimetres in the mesh's frame, come from ``landmarks`` or, when it is None,
    from a YAML sidecar next to the mesh (``<stem>.yaml``):

    * ``exit_point`` (required): centre of the flat cap closing the descending end;
    * ``annulus_center`` (required): centre of the (closed) aortic annulus;
    * ``left_ostium``, ``right_ostium`` (required): coronary ostium centres on the wall;
    * ``start_point`` (optional): a lumen point in the descending aorta (default 15 mm
      inside from the exit);
    * ``exit_normal``, ``root_axis``, ``start_direction`` (optional unit vectors, estimated
      from the cap / valve-plane faces when absent);
    * ``caps`` (optional): centres of further flat caps (branch ends) to mark as non-wall.

    Raises:
        MeshLoadError: unreadable, not watertight or wrongly scaled mesh (see
            :func:`mesh_io.read_mesh_mm`), missing sidecar or landmarks, or a landmark not on
            / not inside the lumen.
    """
    import yaml

    p = Path(path)
    mesh = mesh_io.read_mesh_mm(p)
    source = "the landmarks argument"
    if landmarks is None:
        sidecar = p.with_suffix(".yaml")
        if not sidecar.is_file():
            raise MeshLoadError(
                f"expected landmarks as an argument or in a YAML sidecar {sidecar}, found "
                "neither")
        try:
            landmarks = yaml.safe_load(sidecar.read_text())
        except yaml.YAMLError as err:
            raise MeshLoadError(f"expected valid YAML in {sidecar}, found: {err}") from err
        source = str(sidecar)
        if not isinstance(landmarks, dict):
            raise MeshLoadError(f"expected a mapping of landmarks in {sidecar}, found "
                                f"{type(landmarks).__name__}")
    missing = [k for k in _LANDMARK_KEYS if k not in landmarks]
    if missing:
        raise MeshLoadError(f"expected landmarks {list(_LANDMARK_KEYS)}, found {missing} "
                            f"missing in {source}")
    units = landmarks.get("units", "mm")
    if units != "mm":
        raise MeshLoadError(f"landmark units must be 'mm', found {units!r} in {source}")
    pts = {k: _vec(landmarks, k, source) * 1e-3 for k in _LANDMARK_KEYS}
    surface_dist = {
        k: float(np.abs(trimesh.proximity.signed_distance(mesh, pts[k][None]))[0])
        for k in _LANDMARK_KEYS}
    for k in ("exit_point", "left_ostium", "right_ostium", "annulus_center"):
        if surface_dist[k] > 0.003:
            raise MeshLoadError(
                f"landmark {k} must lie on the surface (within 3 mm), found it "
                f"{surface_dist[k] * 1e3:.1f} mm away in {source}")
    exit_cap = _planar_region(mesh, pts["exit_point"], 5e-4)
    if len(exit_cap) == 0:
        raise MeshLoadError(
            f"expected a flat cap closing the descending end at exit_point, found a curved "
            f"surface there ({source})")
    cap_faces = [exit_cap]
    for i, c in enumerate(landmarks.get("caps") or []):
        region = _planar_region(mesh, _vec({"caps": c}, "caps", source) * 1e-3, 5e-4)
        if len(region) == 0:
            raise MeshLoadError(f"expected a flat cap at caps[{i}] = {c}, found none")
        cap_faces.append(region)
    exit_normal = (_unit(_vec(landmarks, "exit_normal", source)) if "exit_normal" in landmarks
                   else _unit(mesh.face_normals[exit_cap].mean(axis=0)))
    valve = _planar_region(mesh, pts["annulus_center"], 5e-4)
    if "root_axis" in landmarks:
        root_axis = _unit(_vec(landmarks, "root_axis", source))
    elif len(valve):
        root_axis = _unit(-mesh.face_normals[valve].mean(axis=0))
    else:
        raise MeshLoadError(f"expected root_axis or a flat valve plane at annulus_center, "
                            f"found neither ({source})")
    verts = np.asarray(mesh.vertices, dtype=float)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    wall = np.ones(len(faces), dtype=bool)
    for region in cap_faces:
        wall[region] = False
    fixed = np.unique(faces[np.concatenate(cap_faces)])
    if len(valve):
        annulus = np.unique(faces[valve])
    else:
        h = (verts - pts["annulus_center"]) @ root_axis
        annulus = np.flatnonzero((np.abs(h) < 0.0015)
                                 & (np.linalg.norm(verts - pts["annulus_center"], axis=1) < 0.02))
    if len(annulus) < 3:
        raise MeshLoadError(f"expected an annulus ring of >= 3 vertices at annulus_center, "
                            f"found {len(annulus)}")
    start = (_vec(landmarks, "start_point", source) * 1e-3 if "start_point" in landmarks
             else pts["exit_point"] - 0.015 * exit_normal)
    tmp_contains = mesh.contains(start[None])[0]
    if not tmp_contains:
        raise MeshLoadError(f"start_point must lie inside the lumen, found {start * 1e3} mm "
                            f"outside ({source})")
    start_dir = (_unit(_vec(landmarks, "start_direction", source))
                 if "start_direction" in landmarks else -exit_normal)
    wall_vertices = np.unique(faces[wall])
    tree = cKDTree(verts[wall_vertices])
    ostia = {"left": pts["left_ostium"], "right": pts["right_ostium"]}
    return Anatomy(
        name=name or p.stem,
        vertices=verts,
        faces=faces,
        wall_face_mask=wall,
        exit_point=pts["exit_point"],
        exit_normal=exit_normal,
        fixed_vertices=fixed.astype(np.int64),
        annulus_vertices=annulus.astype(np.int64),
        annulus_center=pts["annulus_center"],
        root_axis=root_axis,
        ostia=ostia,
        ostium_vertices={k: int(wall_vertices[tree.query(o)[1]]) for k, o in ostia.items()},
        start_point=start,
        start_direction=start_dir,
    )

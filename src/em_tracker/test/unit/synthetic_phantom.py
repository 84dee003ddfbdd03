"""A synthetic phantom for the calibration tests: fiducials in an aorta-sized box, an aortic
arch tube (mesh and traced wall points), hidden transforms, a pivoting tool, and the
Aurora's noise (:data:`AURORA_POSITION_RMS_M`, :data:`AURORA_ORIENTATION_RMS_RAD`)."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from em_tracker.core.pose import Registration
from em_tracker.core.registration import (
    apply_transform,
    AURORA_ORIENTATION_RMS_RAD,
    AURORA_POSITION_RMS_M,
)

#: per-axis sigma giving the Aurora's 3-D RMS position error
SIGMA = AURORA_POSITION_RMS_M / math.sqrt(3.0)
#: aorta-sized phantom: 150 x 100 x 80 mm box, centred on the phantom origin
HALF = np.array([0.075, 0.05, 0.04])


def hidden_transform(rng: np.random.Generator) -> np.ndarray:
    """A random rigid transform: rotation up to 180 deg, translation up to 200 mm."""
    axis = rng.normal(size=3)
    angle = rng.uniform(0.0, math.pi)
    t = rng.normal(size=3)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    out[:3, 3] = t / np.linalg.norm(t) * rng.uniform(0.05, 0.2)
    return out


def pose_errors(est: np.ndarray, truth: np.ndarray, at: np.ndarray) -> tuple[float, float]:
    """(largest position error over the points ``at``, m; rotation error, deg)."""
    pos = float(np.max(np.linalg.norm(apply_transform(est, at) - apply_transform(truth, at),
                                      axis=1)))
    ang = Rotation.from_matrix(est[:3, :3] @ truth[:3, :3].T).magnitude()
    return pos, math.degrees(ang)


def fiducials(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` fiducials spread over the phantom box (corners jittered inwards)."""
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    picked = corners[rng.permutation(8)[:n]] * HALF
    return picked * rng.uniform(0.7, 1.0, size=picked.shape)


def touch(model: np.ndarray, truth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tracker-frame readings of model points under ``truth`` (phantom <- aurora) + noise."""
    inv = np.linalg.inv(truth)
    return apply_transform(inv, model) + rng.normal(0.0, SIGMA, size=model.shape)


#: lumen radius of the arch tube, m
RADIUS = 0.012
#: centreline length of the arch tube (60 mm up, a half turn of radius 40 mm, 100 mm down), m
ARCH_LENGTH = 0.06 + math.pi * 0.04 + 0.1


def centreline(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An aortic arch in the phantom frame, by arc length ``s`` (m): 60 mm straight up, a
    half turn of radius 40 mm, then 100 mm straight down. Returns points and unit tangents."""
    r, up = 0.04, 0.06
    arc = math.pi * r
    pts, tan = np.zeros((len(s), 3)), np.zeros((len(s), 3))
    for i, si in enumerate(np.clip(s, 0.0, ARCH_LENGTH)):
        if si < up:
            pts[i], tan[i] = [-r, -up + si, 0.0], [0.0, 1.0, 0.0]
        elif si < up + arc:
            a = (si - up) / r
            pts[i], tan[i] = [-r * math.cos(a), r * math.sin(a), 0.0], [math.sin(a),
                                                                        math.cos(a), 0.0]
        else:
            pts[i], tan[i] = [r, -(si - up - arc), 0.0], [0.0, -1.0, 0.0]
    return pts, tan


def wall(s: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Points on the tube wall at arc length ``s`` and angle ``phi`` around the centreline."""
    c, t = centreline(s)
    z = np.array([0.0, 0.0, 1.0])
    side = np.cross(t, z)
    return c + RADIUS * (np.cos(phi)[:, None] * side + np.sin(phi)[:, None] * z)


def tube_mesh() -> tuple[np.ndarray, np.ndarray]:
    """Vertices (m) and triangles of the arch tube's wall (open ends), phantom frame."""
    rings, around = 240, 48
    s = np.repeat(np.linspace(0.0, ARCH_LENGTH, rings), around)
    phi = np.tile(np.linspace(0.0, 2 * math.pi, around, endpoint=False), rings)
    verts = wall(s, phi)
    faces = []
    for i in range(rings - 1):
        for j in range(around):
            a, b = i * around + j, i * around + (j + 1) % around
            faces += [[a, b, a + around], [b, b + around, a + around]]
    return verts, np.array(faces)


def traced(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    """A tip sliding along the wall from end to end, spiralling, phantom frame (no noise)."""
    s = np.linspace(0.005, ARCH_LENGTH - 0.005, n)
    return wall(s, s / 0.02 + rng.uniform(-0.3, 0.3, n))


def perturbed(truth: np.ndarray, centre: np.ndarray, rng: np.random.Generator,
              *, mm: float = 5.0, deg: float = 5.0) -> Registration:
    """``truth`` turned ``deg`` about a random axis through ``centre`` and moved ``mm``."""
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    off = np.eye(4)
    off[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(deg)
                                       ).as_matrix()
    off[:3, 3] = centre - off[:3, :3] @ centre + shift / np.linalg.norm(shift) * mm * 1e-3
    return Registration(off @ truth)


#: the divot of the pivot calibration, tracker frame, m
PIVOT = np.array([0.03, -0.02, -0.25])


def pivoting(rng: np.random.Generator, offset: np.ndarray, n: int, *, tilt_deg: float,
             spin_deg: float = 15.0, axes: int = 2, noise: bool = True
             ) -> tuple[np.ndarray, np.ndarray]:
    """Sensor poses (R_i, t_i) of a tool whose tip (``offset`` in the sensor frame) stays on
    :data:`PIVOT`: tilts within +-``tilt_deg`` about ``axes`` axes across the shaft, spin
    within +-``spin_deg`` about it, and the Aurora's noise (per-axis sigma = RMS / sqrt 3)."""
    base = Rotation.random(random_state=rng.integers(2**31)).as_matrix()
    shaft = base @ offset / np.linalg.norm(offset)
    across = np.linalg.svd(shaft[None, :])[2][1:]  # two unit vectors across the shaft
    tilt = rng.uniform(-1.0, 1.0, (n, axes)) * math.radians(tilt_deg)
    rotvec = tilt @ across[:axes] + np.outer(rng.uniform(-1, 1, n) * math.radians(spin_deg),
                                             shaft)
    rot = Rotation.from_rotvec(rotvec).as_matrix() @ base
    pos = PIVOT - rot @ offset
    if noise:
        pos = pos + rng.normal(0.0, AURORA_POSITION_RMS_M / math.sqrt(3.0), pos.shape)
        jitter = rng.normal(0.0, AURORA_ORIENTATION_RMS_RAD / math.sqrt(3.0), (n, 3))
        rot = Rotation.from_rotvec(jitter).as_matrix() @ rot
    return rot, pos


def hidden_offset(rng: np.random.Generator, length_m: float = 0.015) -> np.ndarray:
    """A sensor -> tip offset of ``length_m`` in a random direction of the sensor frame."""
    v = rng.normal(size=3)
    return v / np.linalg.norm(v) * length_m

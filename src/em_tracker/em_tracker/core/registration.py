"""Registration ``aurora -> phantom``: paired-point (fiducials) and ICP on the lumen wall.

Both give ``T_phantom_aurora`` as a :class:`~em_tracker.core.pose.Registration` (the form of
the ``registration`` parameter of ``aurora_node``), metres throughout.

* :func:`register_paired_points`: least-squares rigid fit of touched fiducials (tracker frame)
  onto their model positions (phantom frame), SVD method of Arun et al. (1987) with Umeyama's
  (1991) reflection guard, its fiducial registration error (FRE) and a leave-one-out estimate
  of the target registration error (TRE). Too few or nearly collinear fiducials are refused.
* :func:`refine_icp`: point-to-plane ICP of a traced tip trajectory (tracker frame) onto the
  lumen wall (phantom frame, :class:`LumenSurface`) from the paired-point result, with robust
  rejection of outliers.

Error budget (Fitzpatrick, West & Maurer 1998): with a fiducial localisation error FLE (3-D
RMS), the expected ``FRE^2 = (1 - 2/N) FLE^2``; the Aurora alone gives 0.48 mm
(:data:`AURORA_POSITION_RMS_M`), a pointer placed by hand on a divot adds about as much.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from em_tracker.core.errors import CalibrationError
from em_tracker.core.pose import Registration

FloatArray = NDArray[np.float64]

#: NDI Aurora 6DOF sensor, cube volume: 3-D RMS position error, m (NDI specification; the same
#: figure as ``cgail_learning.evaluate.TrackingNoise``).
AURORA_POSITION_RMS_M = 0.48e-3
#: NDI Aurora 6DOF sensor, cube volume: RMS orientation error (rotation angle), rad.
AURORA_ORIENTATION_RMS_RAD = math.radians(0.30)


def as_points(points: object, name: str, *, min_count: int = 1) -> FloatArray:
    """``points`` as a finite ``(N, 3)`` float array with ``N >= min_count``.

    Raises:
        CalibrationError: wrong shape, too few points or a NaN/inf coordinate (one line).
    """
    arr = np.asarray(points, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise CalibrationError(f'{name}: expected an (N, 3) array of points, found shape '
                               f'{arr.shape}')
    if arr.shape[0] < min_count:
        raise CalibrationError(f'{name}: expected at least {min_count} points, found '
                               f'{arr.shape[0]}')
    bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
    if bad.size:
        raise CalibrationError(f'{name}: expected finite coordinates, found NaN/inf at row '
                               f'{int(bad[0])}')
    return arr


def rigid_fit(source_m: FloatArray, target_m: FloatArray) -> FloatArray:
    """The rigid ``T`` (4x4) minimising ``sum |R s_i + t - d_i|^2`` (Arun/Umeyama SVD).

    The reflection guard flips the sign of the last singular direction when the SVD solution
    would have ``det R = -1`` (noisy or near-planar points), so ``R`` is always a rotation.
    No degeneracy checks: see :func:`register_paired_points`.

    Args:
        source_m: (N, 3) points, N >= 3.
        target_m: (N, 3) corresponding points.
    """
    src_c = source_m.mean(axis=0)
    dst_c = target_m.mean(axis=0)
    h = (source_m - src_c).T @ (target_m - dst_c)
    u, _, vt = np.linalg.svd(h)
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag(d) @ u.T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = dst_c - rot @ src_c
    return out


def apply_transform(matrix: FloatArray, points_m: FloatArray) -> FloatArray:
    """Map (N, 3) points by the 4x4 rigid transform ``matrix``."""
    return points_m @ matrix[:3, :3].T + matrix[:3, 3]


def line_distance_rms(points_m: FloatArray) -> float:
    """RMS distance of the points from their best-fit line, m.

    From the singular values ``s1 >= s2 >= s3`` of the centred points: ``sqrt((s2^2 + s3^2) /
    N)``; zero when they are collinear (or fewer than 3).
    """
    centred = points_m - points_m.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    return float(math.sqrt(float(np.sum(s[1:] ** 2)) / len(points_m)))


@dataclass(frozen=True)
class PairedPointConfig:
    """Acceptance limits of :func:`register_paired_points`."""

    min_line_distance_m: float = 0.01
    """Smallest RMS distance of the fiducials (either set) from their best-fit line, m;
    [1e-4, 1]. The rotation about that line is fixed only by this lever arm: its standard
    error is about ``FLE / (sqrt(3 N) d)`` rad, i.e. 1.7 deg for 4 fiducials at d = 10 mm with
    FLE = 1 mm (Aurora plus a hand-held pointer), 0.7 deg for 6 at 0.48 mm, enough for a
    catheter target tens of mm away; at 5 mm the error doubles."""
    max_fre_m: float = 0.002
    """FRE above this raises the ``fre_too_high`` flag, m; (0, 0.1]. Expected FRE is
    ``sqrt(1 - 2/N) FLE`` (about 0.8 mm for FLE = 1 mm): 2 mm means FLE > 2.4 mm, a fiducial
    touched off its divot or two fiducials swapped."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_line_distance_m)
                and 1e-4 <= self.min_line_distance_m <= 1.0):
            raise ValueError('min_line_distance_m must be in [0.0001, 1], found '
                             f'{self.min_line_distance_m!r}')
        if not (math.isfinite(self.max_fre_m) and 0.0 < self.max_fre_m <= 0.1):
            raise ValueError(f'max_fre_m must be in (0, 0.1], found {self.max_fre_m!r}')


@dataclass(frozen=True)
class PairedPointResult:
    """Outcome of :func:`register_paired_points`."""

    registration: Registration
    """``T_phantom_aurora``: maps tracker-frame points onto the model (phantom frame)."""
    fre_m: float
    """Fiducial registration error: RMS of ``residuals_m``, m."""
    tre_m: float
    """Leave-one-out TRE estimate, m: RMS over the fiducials of the error at each one when
    registering on the others (includes that fiducial's own FLE, so it errs high). NaN with
    fewer than 4 fiducials or when leaving one out makes the rest nearly collinear."""
    residuals_m: FloatArray
    """(N,) distances between each registered tracker point and its model point, m."""
    loo_errors_m: FloatArray
    """(N,) leave-one-out error at each fiducial, m (NaN where the rest are degenerate)."""
    fre_too_high: bool
    """``fre_m > max_fre_m``: check the fiducials before using the registration."""


def _check_spread(points_m: FloatArray, name: str, min_line_distance_m: float) -> None:
    spread = line_distance_rms(points_m)
    if spread < min_line_distance_m:
        raise CalibrationError(
            f'{name}: fiducials (nearly) collinear: expected an RMS distance from their '
            f'best-fit line of at least {min_line_distance_m * 1e3:.1f} mm, found '
            f'{spread * 1e3:.2f} mm; add fiducials away from that line')


def register_paired_points(model_m: object, tracker_m: object,
                           config: PairedPointConfig | None = None) -> PairedPointResult:
    """Rigid least-squares registration of touched fiducials onto their model positions.

    Args:
        model_m: (N, 3) fiducial positions in the phantom frame (the model), m.
        tracker_m: (N, 3) the same fiducials touched with the tracked tool, aurora frame, m.
        config: acceptance limits (defaults: :class:`PairedPointConfig`).

    Returns:
        The registration ``T_phantom_aurora``, FRE, leave-one-out TRE and per-fiducial errors.

    Raises:
        CalibrationError: mismatched or non-finite arrays, fewer than 3 fiducials, or
            fiducials (nearly) collinear in either frame (one line naming what was found).
    """
    cfg = config or PairedPointConfig()
    model = as_points(model_m, 'model fiducials')
    tracker = as_points(tracker_m, 'tracker fiducials')
    if model.shape != tracker.shape:
        raise CalibrationError(f'expected as many tracker as model fiducials, found '
                               f'{len(tracker)} and {len(model)}')
    if len(model) < 3:
        raise CalibrationError(f'expected at least 3 fiducials, found {len(model)}')
    _check_spread(model, 'model fiducials', cfg.min_line_distance_m)
    _check_spread(tracker, 'tracker fiducials', cfg.min_line_distance_m)
    matrix = rigid_fit(tracker, model)
    residuals = np.linalg.norm(apply_transform(matrix, tracker) - model, axis=1)
    fre = float(np.sqrt(np.mean(residuals ** 2)))
    n = len(model)
    loo = np.full(n, np.nan)
    if n >= 4:
        for i in range(n):
            keep = np.arange(n) != i
            if line_distance_rms(model[keep]) < cfg.min_line_distance_m:
                continue
            sub = rigid_fit(tracker[keep], model[keep])
            loo[i] = np.linalg.norm(apply_transform(sub, tracker[i:i + 1])[0] - model[i])
    tre = float(np.sqrt(np.mean(loo ** 2))) if np.all(np.isfinite(loo)) else math.nan
    return PairedPointResult(registration=Registration(matrix), fre_m=fre, tre_m=tre,
                             residuals_m=residuals, loo_errors_m=loo,
                             fre_too_high=fre > cfg.max_fre_m)


@dataclass(frozen=True, eq=False)
class LumenSurface:
    """Samples of the lumen wall (phantom frame) with unit normals, for nearest-point queries.

    Build it with :meth:`from_mesh` (triangles, sampled densely) or :meth:`from_points` (a
    point cloud; normals estimated from neighbours). Normal signs do not matter.
    """

    points_m: FloatArray
    """(M, 3) surface samples, m."""
    normals: FloatArray
    """(M, 3) unit normals at the samples."""
    _tree: cKDTree = field(init=False, repr=False)

    def __post_init__(self) -> None:
        pts = as_points(self.points_m, 'surface', min_count=3)
        nrm = np.asarray(self.normals, dtype=float)
        if nrm.shape != pts.shape or not np.all(np.isfinite(nrm)):
            raise CalibrationError(f'surface: expected finite normals of shape {pts.shape}, '
                                   f'found {nrm.shape}')
        object.__setattr__(self, 'points_m', pts)
        object.__setattr__(self, 'normals', nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
        object.__setattr__(self, '_tree', cKDTree(pts))

    @classmethod
    def from_mesh(cls, vertices_m: object, faces: object, *, spacing_m: float = 0.5e-3,
                  max_samples: int = 2_000_000, seed: int = 0) -> LumenSurface:
        """Sample a triangle mesh uniformly by area, about one sample per ``spacing_m^2``.

        Args:
            vertices_m: (V, 3) vertices, m.
            faces: (F, 3) vertex indices of the triangles.
            spacing_m: mean distance between samples, m (0.5 mm: the nearest-sample offset
                along the wall stays well under the Aurora's noise).
            max_samples: refuse a mesh needing more samples (a mesh in mm read as m...).
            seed: seed of the sampling (deterministic).

        Raises:
            CalibrationError: bad arrays, no area, or more than ``max_samples`` samples.
        """
        verts = as_points(vertices_m, 'mesh vertices', min_count=3)
        tri = np.asarray(faces)
        if (tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer)
                or tri.size == 0 or tri.min() < 0 or tri.max() >= len(verts)):
            raise CalibrationError(f'mesh faces: expected an (F, 3) array of vertex indices '
                                   f'in [0, {len(verts)}), found shape {tri.shape}')
        corners = verts[tri]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        double_area = np.linalg.norm(cross, axis=1)
        total = 0.5 * float(double_area.sum())
        if not total > 0.0:
            raise CalibrationError('mesh: expected triangles with a positive area, found none')
        count = math.ceil(total / spacing_m ** 2)
        if count > max_samples:
            raise CalibrationError(
                f'mesh: expected at most {max_samples} samples, found an area of {total:.4g} '
                f'm^2 needing {count} at {spacing_m * 1e3:g} mm spacing (mesh not in metres?)')
        rng = np.random.default_rng(seed)
        face = rng.choice(len(tri), size=count, p=double_area / double_area.sum())
        u, v = rng.random(count), rng.random(count)
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        c = corners[face]
        pts = c[:, 0] + u[:, None] * (c[:, 1] - c[:, 0]) + v[:, None] * (c[:, 2] - c[:, 0])
        return cls(pts, cross[face])

    @classmethod
    def from_points(cls, points_m: object, *, neighbours: int = 12) -> LumenSurface:
        """A wall given as a point cloud; each normal is the least-variance direction of the
        point's ``neighbours`` nearest points (PCA), so the cloud must be dense and smooth."""
        pts = as_points(points_m, 'surface points', min_count=neighbours)
        _, idx = cKDTree(pts).query(pts, k=neighbours)
        nbr = pts[idx] - pts[idx].mean(axis=1, keepdims=True)
        cov = np.einsum('nki,nkj->nij', nbr, nbr)
        _, vecs = np.linalg.eigh(cov)
        return cls(pts, vecs[:, :, 0])

    def nearest(self, query_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The nearest surface sample of each query point and its normal."""
        _, idx = self._tree.query(query_m)
        return self.points_m[idx], self.normals[idx]


@dataclass(frozen=True)
class IcpConfig:
    """Settings of :func:`refine_icp`."""

    max_iterations: int = 60
    """Iteration limit; [1, 1000]."""
    tolerance_m: float = 1e-5
    """Stop once an iteration moves no inlier point more than this, m; (0, 1e-3]. 10 um is
    1/50 of the Aurora's noise; below it the switching of nearest samples (0.5 mm apart) can
    keep the last steps cycling at a few um."""
    reject_sigmas: float = 3.0
    """Inliers are within this many robust sigmas (1.4826 x median |distance|); [1, 10]."""
    min_reject_distance_m: float = 1e-3
    """Points this close to the wall are never rejected, m (about twice the Aurora's noise,
    so a good fit keeps its points); [0, 0.05]."""
    max_distance_m: float = 0.01
    """Points farther than this from the wall are always rejected, m; (0, 0.1]."""
    min_inlier_fraction: float = 0.5
    """Refuse the fit when fewer of the points than this are inliers; (0, 1]."""

    def __post_init__(self) -> None:
        if not 1 <= self.max_iterations <= 1000:
            raise ValueError(f'max_iterations must be in [1, 1000], found '
                             f'{self.max_iterations!r}')
        for name, low, high, low_open in (('tolerance_m', 0.0, 1e-3, True),
                                          ('reject_sigmas', 1.0, 10.0, False),
                                          ('min_reject_distance_m', 0.0, 0.05, False),
                                          ('max_distance_m', 0.0, 0.1, True),
                                          ('min_inlier_fraction', 0.0, 1.0, True)):
            value = getattr(self, name)
            ok = (isinstance(value, (int, float)) and math.isfinite(value)
                  and (value > low if low_open else value >= low) and value <= high)
            if not ok:
                raise ValueError(f"{name} must be in {'(' if low_open else '['}{low}, {high}], "
                                 f'found {value!r}')


@dataclass(frozen=True)
class IcpResult:
    """Outcome of :func:`refine_icp`."""

    registration: Registration
    """Refined ``T_phantom_aurora``."""
    rms_m: float
    """RMS point-to-wall distance of the inliers after the last iteration, m."""
    iterations: int
    """Iterations run."""
    converged: bool
    """The last iteration moved the points less than ``tolerance_m``."""
    inliers: NDArray[np.bool_]
    """(N,) points kept by the last iteration."""
    correction_m: float
    """Translation of the points' centroid from the initial registration, m."""
    correction_rad: float
    """Rotation from the initial registration, rad."""


def _inliers(dist: FloatArray, cfg: IcpConfig) -> NDArray[np.bool_]:
    sigma = 1.4826 * float(np.median(dist))
    limit = min(cfg.max_distance_m, max(cfg.min_reject_distance_m, cfg.reject_sigmas * sigma))
    return dist <= limit


def refine_icp(points_m: object, surface: LumenSurface, initial: Registration,
               config: IcpConfig | None = None) -> IcpResult:
    """Point-to-plane ICP of a traced trajectory onto the lumen wall.

    Each iteration pairs every mapped point with its nearest wall sample, keeps the points
    within ``reject_sigmas`` robust sigmas (clamped to ``[min_reject_distance_m,
    max_distance_m]``), and solves the linearised point-to-plane least squares
    ``n_i . (w x (p_i - c) + v + p_i - s_i) = 0`` for a small rotation ``w`` about the inliers'
    centroid ``c`` and a translation ``v`` (Chen & Medioni 1992). Directions the wall does not
    constrain (along a straight tube, about a torus axis) get a minimum-norm zero update, so
    they keep the initial value: a trajectory that covers bends fixes all six.

    Args:
        points_m: (N, 3) tip positions touching the wall, aurora frame, m (N >= 6).
        surface: the lumen wall, phantom frame.
        initial: start, normally :attr:`PairedPointResult.registration` (the capture range
            is a few mm: points must land on the right wall).
        config: settings (defaults: :class:`IcpConfig`).

    Raises:
        CalibrationError: bad points, or fewer inliers than ``min_inlier_fraction``.
    """
    cfg = config or IcpConfig()
    pts = as_points(points_m, 'trajectory', min_count=6)
    need = max(6, math.ceil(cfg.min_inlier_fraction * len(pts)))
    matrix = initial.matrix.copy()
    converged = False
    iterations = 0
    while iterations < cfg.max_iterations:
        iterations += 1
        mapped = apply_transform(matrix, pts)
        near, normal = surface.nearest(mapped)
        resid = np.einsum('ij,ij->i', mapped - near, normal)
        keep = _inliers(np.abs(resid), cfg)
        if int(keep.sum()) < need:
            raise CalibrationError(
                f'trajectory: expected at least {need} of {len(pts)} points within '
                f'{cfg.max_distance_m * 1e3:g} mm of the wall, found {int(keep.sum())} '
                '(initial registration too far off, or the wrong surface/units)')
        p, n, r = mapped[keep], normal[keep], resid[keep]
        centre = p.mean(axis=0)
        arm = p - centre
        scale = float(np.sqrt(np.mean(np.sum(arm ** 2, axis=1)))) or 1.0
        jac = np.hstack([np.cross(arm, n) / scale, n])
        step = np.linalg.lstsq(jac, -r, rcond=1e-3)[0]
        rot = Rotation.from_rotvec(step[:3] / scale).as_matrix()
        delta = np.eye(4)
        delta[:3, :3] = rot
        delta[:3, 3] = centre + step[3:] - rot @ centre
        matrix = delta @ matrix
        motion = float(np.max(np.linalg.norm(apply_transform(delta, p) - p, axis=1)))
        if motion < cfg.tolerance_m:
            converged = True
            break
    matrix[:3, :3] = Rotation.from_matrix(matrix[:3, :3]).as_matrix()  # re-orthonormalise
    mapped = apply_transform(matrix, pts)
    near, normal = surface.nearest(mapped)
    dist = np.abs(np.einsum('ij,ij->i', mapped - near, normal))
    keep = _inliers(dist, cfg)
    rms = float(np.sqrt(np.mean(dist[keep] ** 2))) if keep.any() else math.nan
    start = apply_transform(initial.matrix, pts).mean(axis=0)
    rel = matrix[:3, :3] @ initial.matrix[:3, :3].T
    return IcpResult(registration=Registration(matrix), rms_m=rms, iterations=iterations,
                     converged=converged, inliers=keep,
                     correction_m=float(np.linalg.norm(mapped.mean(axis=0) - start)),
                     correction_rad=float(Rotation.from_matrix(rel).magnitude()))

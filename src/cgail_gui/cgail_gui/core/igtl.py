"""What the OpenIGTLink bridge sends to 3D Slicer, as plain arrays: no rclpy, no sockets.

**Frame.** Everything goes out in the patient's CT frame as 3D Slicer's world has it:
**RAS** millimetres. The two conventions, as axis directions:

=========  ======================================  ==============================================
frame      +x / +y / +z                            used by
=========  ======================================  ==============================================
``RAS``    patient's Right / Anterior / Superior   3D Slicer's world, NIfTI's scanner frame,
                                                   OpenIGTLink receivers (SlicerOpenIGTLink)
``LPS``    patient's Left / Posterior / Superior   DICOM, ITK; the ``phantom`` frame's axes
=========  ======================================  ==============================================

The ``phantom`` frame (metres, LPS axes, the annulus centre at the origin;
:mod:`cgail_sim.anatomy`) maps to the CT frame by a rigid transform and a scale:

    p_ct_mm = rotation @ (1000 * p_phantom_m) + translation_mm          (:class:`CtFrame`)

* a **prepared anatomy** (``cgail prepare-anatomy``'s directory) records how its lumen relates to
  its input in ``prepare.yaml`` under ``frame_conversion`` (``p_phantom_m = R @ (p_input_mm -
  t_input_mm) / 1000``, input frame ``RAS`` for a NIfTI label map, the declared ``--frame`` of
  a surface mesh). :func:`ct_frame_from_record` inverts that record, it recomputes nothing,
  then turns LPS axes into RAS where the input was LPS. For a NIfTI input the result is the
  scanner RAS frame of the NIfTI affine: load the CT (or the label map) in Slicer and the tip,
  the path and the lumen lie on it.
* a **built-in** or population anatomy, or a mesh without a ``prepare.yaml``, has no CT: its
  phantom coordinates in mm, with the LPS axes turned to RAS (``diag(-1000, -1000, 1000)``, no
  translation), so that Slicer's orientation labels (L/R, A/P, S/I) are the patient's. (That is
  also where Slicer puts the mesh file itself: it reads an STL as LPS millimetres.)

**Messages** (device names at most 20 ASCII characters, the OpenIGTLink limit):
:data:`TIP_DEVICE` TRANSFORM (the tip pose), :data:`PATH_DEVICE` POLYDATA (the planned path as
one polyline), :data:`TARGET_DEVICE` POINT (the planner's goal), :data:`LUMEN_DEVICE` POLYDATA
(the lumen's triangles). The cell arrays are VTK's legacy layout that POLYDATA carries:
``[n, i_0 ... i_{n-1}, n, ...]``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
import ipaddress
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: OpenIGTLink device names of the four streams (SlicerOpenIGTLink names its nodes after them).
TIP_DEVICE = "CatheterTip"
PATH_DEVICE = "PlannedPath"
TARGET_DEVICE = "Target"
LUMEN_DEVICE = "Lumen"
#: OpenIGTLink's device-name field: 20 bytes.
MAX_DEVICE_NAME = 20
#: The OpenIGTLink port 3D Slicer's OpenIGTLinkIF connector uses by default.
DEFAULT_PORT = 18944

#: RAS axes from LPS axes (and back): a rotation of pi about z.
RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0])
#: The formula ``prepare.yaml`` states for ``frame_conversion`` (checked, so that a changed
#: record format is refused rather than misread).
PREPARE_FORMULA = "p_phantom_m = R @ (p_input_mm - t_input_mm) / 1000"
#: A lumen marker vertex farther than this from its rest position is not this anatomy's wall, m.
MAX_WALL_DISPLACEMENT = 0.03


class CtFrameError(ValueError):
    """A CT frame record that cannot be used; the message reads "expected ..., found ..."."""


@dataclass(frozen=True)
class CtFrame:
    """The patient's CT frame (RAS mm) of the ``phantom`` frame (m):
    ``p_ct_mm = rotation @ (1000 * p_phantom_m) + translation_mm``."""

    rotation: FloatArray
    """(3, 3) proper rotation, CT axes from phantom axes."""
    translation_mm: FloatArray
    """(3,) CT coordinates of the phantom origin, mm."""
    source: str
    """Where the frame came from, for the log (a file, or why there is no CT)."""

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64)
        t = np.asarray(self.translation_mm, dtype=np.float64)
        if r.shape != (3, 3) or not np.isfinite(r).all() \
                or not np.allclose(r @ r.T, np.eye(3), atol=1e-6) \
                or not np.linalg.det(r) > 0.0:
            raise CtFrameError(f"expected rotation to be a proper 3x3 rotation, found "
                               f"{r.tolist()} ({self.source})")
        if t.shape != (3,) or not np.isfinite(t).all():
            raise CtFrameError(f"expected translation_mm to be 3 finite numbers, found "
                               f"{t.tolist()} ({self.source})")
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation_mm", t)

    @property
    def matrix(self) -> FloatArray:
        """(4, 4) homogeneous transform, CT mm from phantom m."""
        out = np.eye(4)
        out[:3, :3] = 1000.0 * self.rotation
        out[:3, 3] = self.translation_mm
        return out

    def points_mm(self, points_m: FloatArray) -> FloatArray:
        """(N, 3) CT mm of (N, 3) phantom points in m (a (3,) point gives (3,))."""
        p = np.asarray(points_m, dtype=np.float64)
        return np.asarray((1000.0 * p) @ self.rotation.T + self.translation_mm)

    def pose_mm(self, position_m: FloatArray, rotation: FloatArray) -> FloatArray:
        """(4, 4) CT pose (rotation, translation in mm) of a phantom pose: the TRANSFORM of
        a tool whose frame is ``rotation`` at ``position_m``."""
        out = np.eye(4)
        out[:3, :3] = self.rotation @ np.asarray(rotation, dtype=np.float64)
        out[:3, 3] = self.points_mm(np.asarray(position_m, dtype=np.float64).reshape(3))
        return out


def phantom_ct_frame(source: str = "no CT: the phantom frame in mm, LPS axes turned to RAS"
                     ) -> CtFrame:
    """The frame of an anatomy without a CT (built-in, population, a bare mesh)."""
    return CtFrame(RAS_FROM_LPS.copy(), np.zeros(3), source)


def _matrix(value: Any, shape: tuple[int, ...], name: str, source: str) -> FloatArray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.shape != shape or not np.isfinite(arr).all():
        raise CtFrameError(f"expected frame_conversion.{name} of shape {shape} in {source}, "
                           f"found {value!r}")
    return arr


def ct_frame_from_record(record: Mapping[str, Any], source: str = "prepare.yaml",
                         content_hash: str | None = None) -> CtFrame:
    """The CT frame of a prepared anatomy from its ``prepare.yaml`` record (module docstring).

    Args:
        record: the parsed ``prepare.yaml``.
        source: its path, for messages.
        content_hash: the loaded anatomy's :attr:`~cgail_sim.anatomy.Anatomy.
            content_hash`; when given, the record must be the one of that lumen.

    Raises:
        CtFrameError: no ``frame_conversion``, another formula, an input frame other than RAS
            or LPS, malformed ``R`` / ``t_input_mm``, or a record of another lumen.
    """
    conv = record.get("frame_conversion") if isinstance(record, Mapping) else None
    if not isinstance(conv, Mapping):
        raise CtFrameError(f"expected a frame_conversion mapping in {source}, found "
                           f"{conv!r}")
    formula = conv.get("phantom_from_input")
    if formula != PREPARE_FORMULA:
        raise CtFrameError(f"expected frame_conversion.phantom_from_input {PREPARE_FORMULA!r} "
                           f"in {source}, found {formula!r}")
    frame = conv.get("input_frame")
    if frame not in ("RAS", "LPS"):
        raise CtFrameError(f"expected frame_conversion.input_frame RAS or LPS in {source}, "
                           f"found {frame!r}")
    r = _matrix(conv.get("R"), (3, 3), "R", source)
    t = _matrix(conv.get("t_input_mm"), (3,), "t_input_mm", source)
    if content_hash is not None:
        recorded = (record.get("anatomy") or {}).get("content_hash")
        if recorded != content_hash:
            raise CtFrameError(f"expected {source} to describe the loaded lumen (content hash "
                               f"{content_hash}), found content hash {recorded!r}: the lumen "
                               "changed after cgail prepare-anatomy; run it again")
    # p_input = R^-1 (1000 p) + t (prepare_anatomy's own inverse), then RAS axes.
    to_ras = np.eye(3) if frame == "RAS" else RAS_FROM_LPS
    return CtFrame(to_ras @ np.linalg.inv(r), to_ras @ t, f"{source} (input frame {frame})")


def prepare_record_path(spec: str | os.PathLike[str]) -> Path | None:
    """The ``prepare.yaml`` that describes an anatomy argument, or None (a name, or a mesh
    that ``cgail prepare-anatomy`` did not write)."""
    from cgail_sim.anatomy_spec import is_named, PREPARED_MESH

    if isinstance(spec, str) and is_named(spec):
        return None
    path = Path(spec).expanduser()
    folder = path if path.is_dir() else path.parent if path.name == PREPARED_MESH else None
    record = folder / "prepare.yaml" if folder is not None else None
    return record if record is not None and record.is_file() else None


def ct_frame_of(spec: str | os.PathLike[str], content_hash: str | None = None) -> CtFrame:
    """The CT frame of an anatomy argument (a name or a path, as ``resolve_anatomy`` takes).

    Raises:
        CtFrameError: an unreadable or unusable ``prepare.yaml`` (:func:`ct_frame_from_record`).
    """
    import yaml

    from cgail_sim.anatomy_spec import is_named

    path = prepare_record_path(spec)
    if path is None:
        what = "built-in anatomy" if isinstance(spec, str) and is_named(spec) else \
            "no prepare.yaml beside"
        return phantom_ct_frame(f"{what} {spec}: no CT, the phantom frame in mm with its LPS "
                                "axes turned to RAS")
    try:
        record = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise CtFrameError(f"expected a readable YAML record in {path}, found: {err}") from err
    if not isinstance(record, Mapping):
        raise CtFrameError(f"expected a mapping in {path}, found {type(record).__name__}")
    return ct_frame_from_record(record, str(path), content_hash)


# ------------------------------------------------------------------------------ geometry
def polygon_cells(faces: IntArray) -> NDArray[np.uint32]:
    """VTK cell array ``[3, a, b, c, 3, ...]`` of (M, 3) triangles."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    cells = np.empty((len(f), 4), dtype=np.uint32)
    cells[:, 0] = 3
    cells[:, 1:] = f
    return cells.reshape(-1)


def line_cells(n_points: int) -> NDArray[np.uint32]:
    """VTK cell array of one polyline through points ``0 .. n_points - 1`` (empty below 2)."""
    if n_points < 2:
        return np.zeros(0, dtype=np.uint32)
    return np.concatenate([[n_points], np.arange(n_points)]).astype(np.uint32)


def wall_from_triangles(rest_vertices: FloatArray, wall_faces: IntArray,
                        points: FloatArray) -> FloatArray | None:
    """The lumen's current vertices from the ``lumen`` TRIANGLE_LIST of ``phantom/markers``.

    The marker is ``vertices[wall_faces.reshape(-1)]`` (:class:`~cgail_planner.core.markers.
    LumenMesh`, undecimated); vertices on no wall face (inside the caps) keep their rest place.

    Returns:
        (N, 3) vertices, m; None when the marker is not this anatomy's wall: another point
        count (a decimated marker, another anatomy) or a vertex more than
        :data:`MAX_WALL_DISPLACEMENT` from its rest place.
    """
    rest = np.asarray(rest_vertices, dtype=np.float64)
    index = np.asarray(wall_faces, dtype=np.int64).reshape(-1)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) != len(index):
        return None
    out = rest.copy()
    out[index] = p
    if not np.isfinite(out).all() or \
            float(np.abs(out - rest).max(initial=0.0)) > MAX_WALL_DISPLACEMENT:
        return None
    return out


# ------------------------------------------------------------------------------ config
@dataclass(frozen=True)
class IgtlBridgeConfig:
    """Settings of the OpenIGTLink bridge (``igtl_bridge``)."""

    host: str = "127.0.0.1"
    """Address the server listens on (an IP address or ``localhost``): loopback by default
    (Slicer on the same machine). ``0.0.0.0`` or a LAN address opens it to the network: on
    purpose only (OpenIGTLink has no authentication)."""
    port: int = DEFAULT_PORT
    """TCP port (18944, Slicer's default); 0 = any free port (the node logs it); [0, 65535]."""
    tip_rate_hz: float = 20.0
    """Largest rate of the tip TRANSFORM (the newest pose each period); [1, 200]."""
    follow_wall: bool = True
    """Send the lumen again when ``phantom/markers`` shows the wall moved (dynamic mode)."""

    def __post_init__(self) -> None:
        if self.host != "localhost":
            try:
                ipaddress.ip_address(self.host)
            except ValueError:
                raise ValueError(f"host must be an IPv4 or IPv6 address or 'localhost', found "
                                 f"{self.host!r}") from None
        if isinstance(self.port, bool) or not isinstance(self.port, int) \
                or not 0 <= self.port <= 65535:
            raise ValueError(f"port must be an int in [0, 65535], found {self.port!r}")
        rate = self.tip_rate_hz
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) \
                or not math.isfinite(rate) or not 1.0 <= rate <= 200.0:
            raise ValueError(f"tip_rate_hz must be in [1, 200], found {rate!r}")

"""Input and output files of the calibration commands (all SI after reading).

Inputs (units are named in the file, never guessed):

* fiducials, CSV: columns ``model_x_<u> model_y_<u> model_z_<u>`` (phantom frame) and
  ``tracker_x_<u> tracker_y_<u> tracker_z_<u>`` (aurora frame), ``<u>`` ``mm`` or ``m`` (per
  group), optional ``name``; or YAML ``{unit: mm, fiducials: [{name, model: [x, y, z],
  tracker: [x, y, z]}, ...]}``.
* trajectory, CSV: columns ``x_<u> y_<u> z_<u>`` (aurora frame; other columns ignored).
* sensor poses, CSV: ``x_<u> y_<u> z_<u> qx qy qz qw`` (aurora frame; sensor -> aurora); or a
  rosbag2 bag (directory or ``.mcap``) with ``geometry_msgs/msg/PoseStamped`` on a topic, m.
* lumen wall, phantom frame: ``.stl``/``.ply``/``.obj`` (trimesh; a point-only PLY is a point
  cloud) or ``.npz`` with ``vertices`` + ``faces`` or ``points``, in ``mesh_unit``.

Lines starting with ``#`` in a CSV are comments. Output: a ROS 2 parameters file (see
:func:`write_parameters`). Every failure is one :class:`InputFileError` line. Recordings (the
simulated rig's procedures, :mod:`em_tracker.sim.procedures`) are written in mm by
:func:`write_poses` and :func:`write_fiducials`, which these readers read back.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import csv
import math
import os
from pathlib import Path
import struct
import sys
import tempfile
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
import yaml

from em_tracker.core.errors import CalibrationError, InputFileError
from em_tracker.core.registration import LumenSurface

FloatArray = NDArray[np.float64]
UNITS = {'mm': 1e-3, 'm': 1.0}
#: What the bag and mesh readers raise on a broken file (turned into one InputFileError line).
_READ_ERRORS = (OSError, EOFError, KeyError, IndexError, ValueError, TypeError, AttributeError,
                UnicodeDecodeError, AssertionError, struct.error)


def _read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputFileError(f'{path}: no such file') from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f'{path}: cannot read it ({exc})') from None
    rows = [r for r in csv.reader(line for line in text.splitlines()
                                  if line.strip() and not line.lstrip().startswith('#'))]
    if not rows:
        raise InputFileError(f'{path}: expected a header line and data rows, found no data')
    header = [h.strip().lower() for h in rows[0]]
    if len(rows) < 2:
        raise InputFileError(f'{path}: expected data rows after the header, found none')
    for i, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputFileError(f'{path}: data row {i} has {len(row)} fields, expected '
                                 f'{len(header)} (the header: {",".join(header)})')
    return header, rows[1:]


def _column(path: Path, header: list[str], rows: list[list[str]], name: str) -> FloatArray:
    idx = header.index(name)
    out = np.empty(len(rows))
    for i, row in enumerate(rows):
        try:
            out[i] = float(row[idx])
        except ValueError:
            raise InputFileError(f'{path}: data row {i + 1}, column {name}: expected a number, '
                                 f'found {row[idx]!r}') from None
        if not math.isfinite(out[i]):
            raise InputFileError(f'{path}: data row {i + 1}, column {name}: expected a finite '
                                 f'number, found {row[idx]!r}')
    return out


def _xyz(path: Path, header: list[str], rows: list[list[str]], prefix: str) -> FloatArray:
    """Columns ``<prefix>x_<u>``, ``y``, ``z`` in metres (one unit for the three)."""
    for unit, scale in UNITS.items():
        names = [f'{prefix}{axis}_{unit}' for axis in 'xyz']
        if all(n in header for n in names):
            return np.column_stack([_column(path, header, rows, n) for n in names]) * scale
    want = ' '.join(f'{prefix}{axis}_mm' for axis in 'xyz')
    raise InputFileError(f'{path}: expected columns {want} (or _m), found '
                         f'{",".join(header)}')


def read_fiducials(path: Path) -> tuple[FloatArray, FloatArray, list[str]]:
    """``(model_m, tracker_m, names)`` from a fiducials CSV or YAML file."""
    if path.suffix.lower() in ('.yaml', '.yml'):
        return _read_fiducials_yaml(path)
    header, rows = _read_csv(path)
    model = _xyz(path, header, rows, 'model_')
    tracker = _xyz(path, header, rows, 'tracker_')
    names = ([r[header.index('name')].strip() for r in rows] if 'name' in header
             else [f'F{i + 1}' for i in range(len(rows))])
    return model, tracker, names


def _read_fiducials_yaml(path: Path) -> tuple[FloatArray, FloatArray, list[str]]:
    data = _load_yaml(path)
    if not isinstance(data, dict) or not isinstance(data.get('fiducials'), list):
        raise InputFileError(f'{path}: expected a mapping with a fiducials list, found '
                             f'{type(data).__name__}')
    unit = data.get('unit')
    if unit not in UNITS:
        raise InputFileError(f"{path}: expected unit: mm or m, found {unit!r}")
    model, tracker, names = [], [], []
    for i, item in enumerate(data['fiducials']):
        try:
            m = np.array(item['model'], dtype=float)
            t = np.array(item['tracker'], dtype=float)
        except (TypeError, KeyError, ValueError):
            raise InputFileError(f'{path}: fiducial {i + 1}: expected model: [x, y, z] and '
                                 f'tracker: [x, y, z], found {item!r}') from None
        if m.shape != (3,) or t.shape != (3,) or not (np.all(np.isfinite(m))
                                                      and np.all(np.isfinite(t))):
            raise InputFileError(f'{path}: fiducial {i + 1}: expected 3 finite numbers each '
                                 f'for model and tracker, found {item!r}')
        model.append(m)
        tracker.append(t)
        names.append(str(item.get('name', f'F{i + 1}')))
    scale = UNITS[unit]
    return (np.array(model).reshape(-1, 3) * scale, np.array(tracker).reshape(-1, 3) * scale,
            names)


def read_trajectory(path: Path) -> FloatArray:
    """(N, 3) traced tip positions in the aurora frame, m, from a CSV file."""
    header, rows = _read_csv(path)
    return _xyz(path, header, rows, '')


def read_poses(path: Path, topic: str = 'em_tracker/tip_pose') -> tuple[FloatArray, FloatArray]:
    """``(rotations (N, 3, 3), positions_m (N, 3))`` from a CSV file or a rosbag2 bag."""
    if path.is_dir() or path.suffix == '.mcap':
        return _read_bag_poses(path, topic)
    header, rows = _read_csv(path)
    pos = _xyz(path, header, rows, '')
    missing = [c for c in ('qx', 'qy', 'qz', 'qw') if c not in header]
    if missing:
        raise InputFileError(f'{path}: expected columns qx qy qz qw, missing '
                             f'{" ".join(missing)}')
    quat = np.column_stack([_column(path, header, rows, c) for c in ('qx', 'qy', 'qz', 'qw')])
    return _rotations(path, quat), pos


def _rotations(path: Path, quat_xyzw: FloatArray) -> FloatArray:
    norm = np.linalg.norm(quat_xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 0.01)
    if bad.size:
        raise InputFileError(f'{path}: pose {int(bad[0]) + 1}: expected a unit quaternion '
                             f'(|q| within 0.01 of 1), found |q|={norm[bad[0]]:.4g}')
    return Rotation.from_quat(quat_xyzw / norm[:, None]).as_matrix()


def _read_bag_poses(path: Path, topic: str) -> tuple[FloatArray, FloatArray]:
    try:
        from rosbags.rosbag2 import Reader, ReaderError
        from rosbags.typesys import get_typestore, Stores
    except ImportError:
        raise InputFileError(f'{path}: reading bags needs rosbags (pip install rosbags); '
                             'or export the poses to CSV') from None
    want = topic.strip('/')
    quat: list[tuple[float, float, float, float]] = []
    pos: list[tuple[float, float, float]] = []
    store = get_typestore(Stores.ROS2_JAZZY)
    try:
        with Reader(path) as reader:
            conns = [c for c in reader.connections
                     if c.topic.strip('/') == want or c.topic.strip('/').endswith('/' + want)]
            if not conns or any(c.msgtype != 'geometry_msgs/msg/PoseStamped' for c in conns):
                found = sorted(f'{c.topic} ({c.msgtype})' for c in reader.connections)
                raise InputFileError(f'{path}: expected geometry_msgs/msg/PoseStamped on '
                                     f'{topic}, found {found}')
            for conn, _, raw in reader.messages(connections=conns):
                msg: Any = store.deserialize_cdr(raw, conn.msgtype)
                p, q = msg.pose.position, msg.pose.orientation
                pos.append((p.x, p.y, p.z))
                quat.append((q.x, q.y, q.z, q.w))
    except InputFileError:
        raise
    except (ReaderError, *_READ_ERRORS) as exc:
        raise InputFileError(f'{path}: cannot read the bag ({type(exc).__name__}: '
                             f'{exc})') from None
    if not pos:
        raise InputFileError(f'{path}: expected poses on {topic}, found none')
    p_arr, q_arr = np.array(pos, dtype=float), np.array(quat, dtype=float)
    if not (np.all(np.isfinite(p_arr)) and np.all(np.isfinite(q_arr))):
        raise InputFileError(f'{path}: expected finite poses on {topic}, found NaN/inf')
    return _rotations(path, q_arr), p_arr


def read_surface(path: Path, unit: str) -> LumenSurface:
    """The lumen wall (phantom frame) from a mesh or ``.npz`` file in ``unit`` (mm or m)."""
    scale = UNITS[unit]
    if not path.is_file():
        raise InputFileError(f'{path}: no such file')
    suffix = path.suffix.lower()
    if suffix == '.npz':
        try:
            with np.load(path) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError) as exc:
            raise InputFileError(f'{path}: cannot read it ({exc})') from None
        if 'vertices' in arrays and 'faces' in arrays:
            return LumenSurface.from_mesh(arrays['vertices'] * scale, arrays['faces'])
        if 'points' in arrays:
            return LumenSurface.from_points(arrays['points'] * scale)
        raise InputFileError(f'{path}: expected arrays vertices + faces, or points, found '
                             f'{sorted(arrays)}')
    if suffix not in ('.stl', '.ply', '.obj'):
        raise InputFileError(f'{path}: expected a .stl, .ply, .obj or .npz surface, found '
                             f'{suffix or "no suffix"}')
    try:
        import trimesh
    except ImportError:
        raise InputFileError(f'{path}: reading meshes needs trimesh (pip install trimesh); '
                             'or save vertices/faces to .npz') from None
    try:
        loaded = trimesh.load(str(path), force='mesh', process=False)
    except _READ_ERRORS as exc:
        raise InputFileError(f'{path}: cannot read the mesh ({type(exc).__name__}: '
                             f'{exc})') from None
    faces = np.asarray(getattr(loaded, 'faces', np.zeros((0, 3))))
    verts = np.asarray(getattr(loaded, 'vertices', np.zeros((0, 3))), dtype=float)
    if len(faces):
        return LumenSurface.from_mesh(verts * scale, faces.astype(np.int64))
    if len(verts):
        return LumenSurface.from_points(verts * scale)
    raise InputFileError(f'{path}: expected triangles or points, found an empty mesh')


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[object]],
               comments: Sequence[str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open('w', newline='') as f:
        f.writelines(f'# {c}\n' for c in comments)
        writer = csv.writer(f, lineterminator='\n')
        writer.writerow(header)
        writer.writerows(rows)


def write_poses(path: Path, positions_m: FloatArray, quats_xyzw: FloatArray,
                comments: Sequence[str] = ()) -> None:
    """Write sensor poses (aurora frame) as the CSV :func:`read_poses` reads: ``x_mm y_mm
    z_mm qx qy qz qw`` (positions to 0.1 um)."""
    rows = [[f'{v * 1e3:.4f}' for v in p] + [f'{v:.9f}' for v in q]
            for p, q in zip(positions_m, quats_xyzw, strict=True)]
    _write_csv(path, ['x_mm', 'y_mm', 'z_mm', 'qx', 'qy', 'qz', 'qw'], rows, comments)


def write_fiducials(path: Path, names: Sequence[str], model_m: FloatArray,
                    tracker_m: FloatArray, comments: Sequence[str] = ()) -> None:
    """Write fiducial pairs as the CSV :func:`read_fiducials` reads: ``name``, the model
    positions (phantom frame) and the touched ones (aurora frame), mm to 0.1 um."""
    rows = [[name, *(f'{v * 1e3:.4f}' for v in (*m, *t))]
            for name, m, t in zip(names, model_m, tracker_m, strict=True)]
    header = ['name', *(f'{g}_{a}_mm' for g in ('model', 'tracker') for a in 'xyz')]
    _write_csv(path, header, rows, comments)


def _load_yaml(path: Path) -> Any:
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise InputFileError(f'{path}: no such file') from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputFileError(f'{path}: cannot read it as YAML ({first})') from None


def write_parameters(path: Path, node: str, values: dict[str, Sequence[float]],
                     comments: Sequence[str], *, tool: str) -> None:
    """Set ``values`` under ``<node>: ros__parameters:`` of a ROS 2 parameters file.

    An existing file keeps its other nodes and parameters (its YAML comments are lost, except
    the leading ``#`` lines not written by ``tool``); the file is replaced atomically, so a
    failure leaves it as it was. Use it as a second ``--params-file`` after the defaults.

    Raises:
        InputFileError: the existing file is not a parameters mapping.
    """
    data: dict[str, Any] = {}
    kept: list[str] = []
    if path.exists():
        loaded = _load_yaml(path)
        if loaded is not None and not isinstance(loaded, dict):
            raise InputFileError(f'{path}: expected a ROS 2 parameters mapping to update, '
                                 f'found {type(loaded).__name__}')
        data = loaded or {}
        entry = data.get(node)
        if entry is not None and not (isinstance(entry, dict) and isinstance(
                entry.get('ros__parameters', {}), dict)):
            raise InputFileError(f'{path}: expected {node}: ros__parameters: to be a mapping, '
                                 f'found {entry!r}')
        for line in path.read_text().splitlines():
            if not line.startswith('#'):
                break
            if not line.startswith(f'# {tool}'):
                kept.append(line)
    params = data.setdefault(node, {}).setdefault('ros__parameters', {})
    for name, vals in values.items():
        params[name] = [round(float(v), 12) for v in vals]  # 1 pm, one line per parameter
    text = '\n'.join([*kept, *(f'# {tool}: {c}' for c in comments)]) + '\n'
    text += yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=200)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', dir=path.parent)
    try:
        with os.fdopen(fd, 'w') as f:
            f.write(text)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def run_command(prog: str, parser: argparse.ArgumentParser, args: argparse.Namespace,
                make_config: Callable[[], Any],
                run: Callable[[argparse.Namespace, Any], int]) -> int:
    """The calibration commands' common ending: build the config from the arguments (a bad
    value is a usage error, exit 2 through ``parser.error``), then ``run(args, config)``;
    a bad input file or a refused calibration prints one line and returns 2."""
    try:
        config = make_config()
    except ValueError as exc:
        parser.error(str(exc))
    try:
        return run(args, config)
    except (InputFileError, CalibrationError) as exc:
        print(f'{prog}: error: {exc}', file=sys.stderr)
        return 2

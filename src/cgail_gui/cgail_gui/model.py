"""What the page shows, computed from plain inputs (:class:`GuiModel`; no rclpy).

The node (live topics) and the bag replay feed one model each with numpy arrays; the model
derives the guidance (tip frame, wall distance from raycasts, trial clock) and writes
JSON-ready items into its :class:`~cgail_gui.state.GuiState`.

The wall drawn and raycast is the anatomy's rest shape (:meth:`GuiModel.set_anatomy`) until a
wall arrives as a triangle list (:meth:`GuiModel.set_lumen`: the phantom's ``lumen`` marker,
deformed in dynamic mode); from then on that one is drawn (``mesh`` once per topology, then
``deform`` frames of its vertices) and the rays hit it.
"""

from __future__ import annotations

import base64
from collections.abc import Iterable, Mapping
import threading
from typing import Any, Protocol

import numpy as np

from cgail_gui.config import GuiConfig
from cgail_gui.guidance import (
    bend_on_screen,
    off_heading,
    ray_directions,
    to_tip_frame,
)
from cgail_gui.state import GuiState
from cgail_planner.core.markers import index_triangles
from cgail_planner.core.rotations import quaternion_to_matrix

LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
"""diagnostic_msgs/DiagnosticStatus levels by value."""


class Wall(Protocol):
    """What the model needs of a simulator wall (StaticWall / DeformableWall)."""

    vertices: np.ndarray

    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                ) -> np.ndarray:
        """(R,) distance to the first wall hit along each ray (``max_dist`` when none)."""
        ...  # pragma: no cover


def b64_array(array: np.ndarray, dtype: str) -> str:
    """Little-endian ``dtype`` bytes of ``array`` (C order), base64 text."""
    return base64.b64encode(np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder('<'))
                            .tobytes()).decode('ascii')


def _vec(v: np.ndarray) -> list[float]:
    """A vector as a JSON list rounded to the micrometre / micro-unit."""
    return [round(float(x), 6) for x in np.asarray(v, dtype=float).reshape(-1)]


def _finite(name: str, value: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(value, dtype=float)
    if a.shape != shape or not np.isfinite(a).all():
        raise ValueError(f'{name} must be {shape} finite values, found shape {a.shape}')
    return a


class MeshWall:
    """A wall given as a mesh whose vertices move (topology fixed): rays are cast on the
    simulator's BVH (:class:`~cgail_sim.raycast.WallBVH`), refitted per update.

    Args:
        vertices: (V, 3) positions, m.
        faces: (M, 3) triangles (all of them are wall).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        from cgail_sim.raycast import WallBVH

        self.vertices = np.asarray(vertices, dtype=np.float64)
        self._bvh = WallBVH(self.vertices, faces, np.ones(len(faces), dtype=bool))

    def update(self, vertices: np.ndarray) -> None:
        """New vertex positions (same order)."""
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self._bvh.refit(self.vertices)

    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_dist: float
                ) -> np.ndarray:
        """(R,) distance to the first hit along each ray (``max_dist`` when none)."""
        return self._bvh.raycast(origins, directions, max_dist)


class TrialClock:
    """Trial timer: armed -> running -> reached / timeout / stopped.

    An armed clock starts by itself once the tip has moved ``start_motion_m`` from where it
    was first seen after arming (or at :meth:`start`). It stops as ``reached`` when the tip
    comes within the success radius of the target, and as ``timeout`` at the time limit.
    """

    def __init__(self, limit_s: float, start_motion_m: float = 0.002) -> None:
        self.limit_s = limit_s
        self.start_motion_m = start_motion_m
        self.reset()

    def reset(self) -> None:
        """Back to ``armed`` with 0 s."""
        self.phase = 'armed'
        self.t0: float | None = None
        self.elapsed_s = 0.0
        self._anchor: np.ndarray | None = None

    def start(self, now: float) -> None:
        """Start (or restart) now."""
        self.phase, self.t0, self.elapsed_s = 'running', now, 0.0

    def stop(self, now: float) -> None:
        """Stop a running clock (kept as ``stopped``)."""
        if self.phase == 'running':
            self.update(now)
            if self.phase == 'running':
                self.phase = 'stopped'

    def update(self, now: float, tip: np.ndarray | None = None,
               dist_target: float | None = None, success_radius: float = 0.0) -> None:
        """Advance with the time ``now`` (and the tip position / target distance, if known)."""
        if self.phase == 'armed' and tip is not None:
            if self._anchor is None:
                self._anchor = np.array(tip, dtype=float)
            elif float(np.linalg.norm(tip - self._anchor)) >= self.start_motion_m:
                self.start(now)
        if self.phase != 'running' or self.t0 is None:
            return
        self.elapsed_s = max(0.0, now - self.t0)
        if dist_target is not None and dist_target < success_radius:
            self.phase = 'reached'
        elif self.elapsed_s >= self.limit_s:
            self.phase, self.elapsed_s = 'timeout', self.limit_s

    def item(self) -> dict[str, Any]:
        """The ``trial`` item."""
        return {'phase': self.phase, 'elapsed_s': round(self.elapsed_s, 3),
                'limit_s': self.limit_s}


class GuiModel:
    """Turns tip poses, paths, goals, guidance and diagnostics into page items.

    Args:
        config: the GUI configuration.
        state: where the items go.
        clock: ``'wall'`` - the trial clock runs on the ``now`` given by the caller (the live
            node's ROS clock: system time, or /clock under use_sim_time); ``'stamp'`` - on the
            tip poses' header stamps (replay, so the timer follows the bag whatever the
            playback rate).
    """

    def __init__(self, config: GuiConfig, state: GuiState, clock: str = 'wall') -> None:
        if clock not in ('wall', 'stamp'):
            raise ValueError(f"clock must be 'wall' or 'stamp', found {clock!r}")
        self.config = config
        self.state = state
        self.clock = clock
        self.trial = TrialClock(config.trial_limit_s)
        self._lock = threading.RLock()
        self._wall: Wall | None = None
        #: The wall from a triangle list (:meth:`set_lumen`): (faces, first, soup index, wall).
        self._lumen: tuple[np.ndarray, np.ndarray, np.ndarray, MeshWall] | None = None
        self._tip: np.ndarray | None = None
        self._rot: np.ndarray | None = None
        self._target: np.ndarray | None = None
        self._waypoint: np.ndarray | None = None
        self._diag: dict[str, dict[str, Any]] = {}
        self._tip_seq = 0
        self._last_now = 0.0
        state.set('config', {
            'max_bend': round(config.max_bend_rad, 6), 'trial_limit_s': config.trial_limit_s,
            'success_radius': config.success_radius_m, 'stale_after_s': config.stale_after_s,
            'ray_length': config.ray_length_m, 'ray_cone': round(config.ray_cone_rad, 6),
            'dynamic': config.dynamic, 'anatomy': config.anatomy})
        state.set('trial', self.trial.item())

    # -- anatomy --------------------------------------------------------------------------
    def set_anatomy(self, name: str, vertices: np.ndarray, faces: np.ndarray,
                    wall: Wall | None) -> None:
        """The mesh to draw (metres, frame phantom) and the wall the raycasts hit (ignored once
        a wall came from :meth:`set_lumen`: that one is the current shape)."""
        v = np.asarray(vertices, dtype=float)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f'mesh must be (N, 3) vertices and (M, 3) faces, found '
                             f'{v.shape} and {f.shape}')
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError(f'faces must index vertices 0..{len(v) - 1}')
        with self._lock:
            if self._lumen is not None:
                return
            self._wall = wall
            self._set_mesh(name, v, f)

    def _set_mesh(self, name: str, v: np.ndarray, f: np.ndarray) -> None:
        self.state.set('mesh', {'name': name, 'frame': 'phantom', 'vertex_count': len(v),
                                'face_count': len(f), 'vertices': b64_array(v, 'f4'),
                                'faces': b64_array(f, 'u4')})

    def set_lumen(self, points: np.ndarray, t: float) -> None:
        """The wall as a triangle list (3M, 3) m at time ``t`` s: the phantom's ``lumen``
        marker. A new topology is indexed (:func:`~cgail_planner.core.markers.index_triangles`)
        and sent as ``mesh``; every list goes out as a ``deform`` frame of its vertices, and
        the raycasts hit it."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        if len(p) < 3 or len(p) % 3 or not np.isfinite(p).all():
            raise ValueError(f'lumen must be finite points, 3 per triangle, found {len(p)}')
        with self._lock:
            lumen = self._lumen
            # the same topology: each triangle corner equals its vertex's first appearance
            if lumen is not None and len(lumen[2]) == len(p) and np.array_equal(p[lumen[2]], p):
                vertices = p[lumen[1]]
                lumen[3].update(vertices)
            else:
                vertices, faces, first = index_triangles(p)
                wall = MeshWall(vertices, faces)
                self._lumen = (faces, first, first[faces.reshape(-1)], wall)
                self._wall = wall
                self._set_mesh(self.config.anatomy or 'lumen', vertices, faces)
        self.set_deformation(vertices, t)

    def set_deformation(self, vertices: np.ndarray, t: float) -> None:
        """Current vertex positions of the deforming wall (same order as the mesh)."""
        self.state.set('deform', {'t': round(float(t), 4),
                                  'vertices': b64_array(np.asarray(vertices), 'f4')})

    # -- planner --------------------------------------------------------------------------
    def on_path(self, points: np.ndarray, frame: str) -> None:
        """The planned path, (N, 3) m (N may be 0: no path)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        if not np.isfinite(p).all():
            raise ValueError('path must be finite, found NaN or inf')
        length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0
        self.state.set('path', {'frame': frame, 'points': [_vec(x) for x in p],
                                'length_m': round(length, 6)})

    def on_goal(self, position: np.ndarray, frame: str) -> None:
        """The target position, m."""
        p = _finite('goal', position, (3,))
        with self._lock:
            self._target = p
        self.state.set('target', {'frame': frame, 'p': _vec(p)})
        self._update_guide()

    def on_waypoint(self, position: np.ndarray) -> None:
        """The next waypoint the planner suggests, m."""
        p = _finite('next_waypoint', position, (3,))
        with self._lock:
            self._waypoint = p
        self.state.set('waypoint', {'p': _vec(p)})
        self._update_guide()

    def on_bend(self, alpha: float, gamma: float) -> None:
        """The suggested bend (rad); drawn against ``config.max_bend_rad``."""
        a, g = (float(x) for x in _finite('suggested_bend', np.array([alpha, gamma]), (2,)))
        magnitude, sx, sy = bend_on_screen(a, g)
        self.state.set('bend', {
            'alpha': round(a, 6), 'gamma': round(g, 6), 'magnitude': round(magnitude, 6),
            'screen': [round(sx, 6), round(sy, 6)], 'max': round(self.config.max_bend_rad, 6),
            'fraction': round(min(magnitude / self.config.max_bend_rad, 9.99), 4)})

    # -- tracker --------------------------------------------------------------------------
    def on_tip(self, position: np.ndarray, quaternion: np.ndarray, stamp: float,
               now: float) -> None:
        """A tip pose (m, quaternion x y z w, header stamp s) received at ``now`` (s)."""
        p = _finite('tip position', position, (3,))
        rot = quaternion_to_matrix(quaternion)
        with self._lock:
            self._tip, self._rot = p, rot
            self._tip_seq += 1
            seq = self._tip_seq
        self.state.set('tip', {'seq': seq, 'p': _vec(p), 'q': _vec(quaternion),
                               'heading': _vec(rot[:, 1]), 'up': _vec(rot[:, 2]),
                               'stamp': round(float(stamp), 6)})
        guide = self._update_guide()
        self._advance_trial(stamp if self.clock == 'stamp' else now, p,
                            guide.get('dist_target') if guide else None)

    def on_diagnostics(self, statuses: Iterable[Mapping[str, Any]]) -> None:
        """DiagnosticStatus entries as dicts (name, level, message, hardware_id, values)."""
        changed = False
        for s in statuses:
            name = str(s.get('name', ''))[:120]
            if not name:
                continue
            level = int(s.get('level', 3))
            values = dict(list(s.get('values', {}).items())[:40])
            self._diag[name] = {'level': LEVELS.get(level, 'STALE'),
                                'message': str(s.get('message', ''))[:200],
                                'hardware_id': str(s.get('hardware_id', ''))[:120],
                                'values': {str(k)[:60]: str(v)[:120] for k, v in values.items()}}
            changed = True
        if changed:
            tracker = next((n for n, d in self._diag.items()
                            if n.startswith('aurora') or d['hardware_id'].startswith('ndi_')),
                           None)
            self.state.set('diagnostics', {'statuses': dict(sorted(self._diag.items())),
                                           'tracker': tracker})

    # -- trial ----------------------------------------------------------------------------
    def trial_command(self, action: str, now: float) -> None:
        """``start`` / ``stop`` / ``reset`` the trial clock (``now``: the clock's time base)."""
        with self._lock:
            t = self._last_now if self.clock == 'stamp' else now
            if action == 'start':
                self.trial.start(t)
            elif action == 'stop':
                self.trial.stop(t)
            elif action == 'reset':
                self.trial.reset()
            else:
                raise ValueError(f"trial action must be start, stop or reset, found {action!r}")
            item = self.trial.item()
        self.state.set('trial', item)

    def tick(self, now: float) -> None:
        """Advance the trial clock without a tip pose (live clock only: catches the limit)."""
        with self._lock:
            if self.clock != 'wall' or self.trial.phase != 'running':
                return
            self.trial.update(now)
            self._last_now = now
            item = self.trial.item()
        self.state.set('trial', item)

    def _advance_trial(self, now: float, tip: np.ndarray, dist: float | None) -> None:
        with self._lock:
            before = (self.trial.phase, self.trial.elapsed_s)
            self._last_now = now
            self.trial.update(now, tip, dist, self.config.success_radius_m)
            item = self.trial.item()
        if (item['phase'], item['elapsed_s']) != (before[0], round(before[1], 3)):
            self.state.set('trial', item)

    # -- internal view ----------------------------------------------------------------------
    def _update_guide(self) -> dict[str, Any] | None:
        """Recompute the ``guide`` item from the latest tip, target, waypoint and wall."""
        with self._lock:
            tip, rot = self._tip, self._rot
            if tip is None or rot is None:
                return None
            cfg = self.config
            guide: dict[str, Any] = {}
            if self._target is not None:
                guide['dist_target'] = round(float(np.linalg.norm(self._target - tip)), 6)
            if self._waypoint is not None:
                d = to_tip_frame(rot, tip, self._waypoint)
                angle, sx, sy = off_heading(d)
                guide['waypoint'] = {'distance': round(float(np.linalg.norm(d)), 6),
                                     'angle': round(angle, 6),
                                     'screen': [round(sx, 6), round(sy, 6)],
                                     'local': _vec(d)}
            if self._wall is not None and cfg.ray_count >= 0:
                dirs = ray_directions(rot, cfg.ray_count, cfg.ray_cone_rad)
                hits = np.asarray(self._wall.raycast(np.tile(tip, (len(dirs), 1)), dirs,
                                                     cfg.ray_length_m), dtype=float)
                guide['rays'] = {'length': cfg.ray_length_m, 'cone': round(cfg.ray_cone_rad, 6),
                                 'dist': [round(float(h), 6) for h in hits]}
                guide['wall_min'] = round(float(hits.min()), 6)
                guide['wall_ahead'] = round(float(hits[0]), 6)
        self.state.set('guide', guide)
        return guide


"""The guidance page while demonstrations are recorded (``record_demos``; no rclpy).

:class:`RecordingPage` serves the same page as ``gui_node`` (:mod:`cgail_gui.server`)
from one :class:`~cgail_gui.model.GuiModel` fed by the simulator directly: the anatomy
(the beating wall in dynamic mode), the tip, the target, the commanded bend (teleop's setpoint,
drawn where the guidance page draws the suggested bend) and the ``record`` item (episode,
phase, time left, outcome). No planned path and no waypoint are ever sent: the demonstrator
navigates by themselves. The page's keyboard arrives as ``joy`` commands
(:mod:`cgail_gui.protocol`) and is kept here for the node to publish on ``joy``; a
``record discard`` command is kept until taken.
"""

from __future__ import annotations

from collections.abc import Callable
import threading
import time
from typing import Any

import numpy as np

from cgail_gui.config import GuiConfig
from cgail_gui.model import GuiModel
from cgail_gui.protocol import ClientCommand
from cgail_gui.server import GuiServer, Log
from cgail_gui.state import GuiState
from cgail_gui.static import build_table, find_web_root, missing_vendor

KEYBOARD_FRESH_S = 0.5
"""The page repeats its keyboard state every 0.1 s while a key is held: a state older than
this (wall clock) is dropped, so a page that closes with a key held stops the catheter (teleop
then sees no Joy and stops, as when a gamepad is unplugged)."""


class RecordingPage:
    """The page of one recording (module docstring).

    Args:
        config: bind address, port, trial limit (the episode's), success radius, dynamic mode.
        anatomy: the recording's :class:`~cgail_sim.anatomy.Anatomy`.
        wall: the env's wall (raycast for the wall distances; its vertices in dynamic mode).
        log: log sink.
        clock: wall-clock seconds (tests may replace it).
    """

    def __init__(self, config: GuiConfig, anatomy: Any, wall: Any, log: Log,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._clock = clock
        files = build_table(find_web_root())
        self.missing = missing_vendor(files)
        self.state = GuiState()
        self.model = GuiModel(config, self.state, clock='wall')
        self.server = GuiServer(config, files, self._on_command, log)
        self.state.on_change = lambda: self.server.notify_from(self.state)
        self.server.set_source('live', self.state)
        self._wall = wall
        self.model.set_anatomy(anatomy.name, anatomy.vertices,
                               anatomy.faces[anatomy.wall_face_mask], wall)
        self._lock = threading.Lock()
        self._keys: tuple[tuple[float, ...], tuple[int, ...], float] | None = None
        self._discard = False
        self._serial = -1
        self._phase = ''
        self._last_deform = -1e9
        self._target: np.ndarray | None = None
        self._bend: tuple[float, float] | None = None
        self._pose: tuple[np.ndarray, np.ndarray] | None = None
        self._record: dict[str, Any] | None = None

    # -- server thread ---------------------------------------------------------------------
    def _on_command(self, command: ClientCommand) -> None:
        if command.kind == 'joy':
            with self._lock:
                self._keys = (command.axes, command.buttons, self._clock())
        elif command.kind == 'record' and command.action == 'discard':
            with self._lock:
                self._discard = True
        # (trial and replay commands have no meaning while recording)

    # -- recording thread ------------------------------------------------------------------
    def keyboard(self) -> tuple[tuple[float, ...], tuple[int, ...]] | None:
        """The page's keyboard as (axes, buttons), or None when no fresh state came."""
        with self._lock:
            keys = self._keys
        if keys is None or self._clock() - keys[2] > KEYBOARD_FRESH_S:
            return None
        return keys[0], keys[1]

    def take_discard(self) -> bool:
        """Whether the page asked to discard the episode since the last call."""
        with self._lock:
            asked, self._discard = self._discard, False
        return asked

    def show(self, t: float, record: dict[str, Any], serial: int, tip: np.ndarray,
             rotation: np.ndarray, target: np.ndarray, bend: tuple[float, float]) -> None:
        """Update the page at simulated time ``t`` (s): the episode ``serial`` (a new one
        clears the trial clock), its ``record`` item, the tip pose, the target and the
        commanded bend (rad)."""
        from cgail_planner.core.rotations import matrix_to_quaternion

        model = self.model
        phase = record['phase']
        if serial != self._serial:
            self._serial = serial
            model.trial_command('reset', t)
        if phase == 'running' and self._phase == 'waiting':
            model.trial_command('start', t - record['elapsed_s'])
        if self._target is None or not np.array_equal(target, self._target):
            self._target = np.array(target, dtype=float)
            model.on_goal(self._target, 'phantom')
        if self.config.dynamic and self._clock() - self._last_deform >= \
                0.999 / self.config.mesh_rate_hz:
            self._last_deform = self._clock()
            model.set_deformation(self._wall.vertices, t)
        if bend != self._bend:
            self._bend = bend
            model.on_bend(*bend)
        pose = (np.array(tip, dtype=float), np.array(rotation, dtype=float))
        if self._pose is None or not (np.array_equal(pose[0], self._pose[0])
                                      and np.array_equal(pose[1], self._pose[1])):
            self._pose = pose  # (a still tip is not sent again: the page draws only changes)
            model.on_tip(pose[0], matrix_to_quaternion(pose[1]), t, t)
        else:
            model.tick(t)
        if phase in ('pause', 'done') and model.trial.phase == 'running':
            model.trial_command('stop', t)
        self._phase = phase
        item = {**record, 'serial': serial}
        if item != self._record:
            self._record = item
            self.state.set('record', item)

    def show_devices(self, statuses: list[dict[str, Any]]) -> None:
        """The devices panel: DiagnosticStatus-like dicts (name, level, message)."""
        self.model.on_diagnostics(statuses)

    def start(self) -> int:
        """Serve the page; returns the bound port.

        Raises:
            ServerError: the address cannot be bound.
        """
        return self.server.start()

    def stop(self) -> None:
        """Close the page's connections and the server."""
        self.server.stop()

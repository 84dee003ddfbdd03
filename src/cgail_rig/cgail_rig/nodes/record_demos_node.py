"""Nodes of ``record_demos``: the simulated catheter, and the scripted demonstrator's gamepad.

* :class:`RecorderNode` (``record_demos``) is the catheter of the rig for teleop: it takes
  ``catheter/bend_command`` and ``catheter/insertion_command`` (``teleop_node``'s output, the
  topics the PAM controller and the sleeve driver take on the rig) and, once per control step
  (:meth:`RecorderNode.world_step`, the lockstep executor's world hook), steps the
  :class:`~cgail_learning.recorder.DemoRecorder` with the latest of them. It publishes
  ``em_tracker/tip_pose`` (as the tracker does on the rig), publishes the page's keyboard as
  ``sensor_msgs/Joy`` on ``joy`` (frame ``keyboard``) and reads ``joy`` itself: the device of
  each message (frame ``keyboard``, ``scripted``, else a gamepad), the discard button, and a
  malformed message, which is reported once (teleop rejects it and stops the catheter).
* :class:`ExpertJoyNode` (``expert_joy``) is the scripted demonstrator at the gamepad: the
  scripted expert's action (:class:`~cgail_learning.expert.ScriptedExpert`) for the
  current state, as stick deflections for teleop's ``position`` bend mode (frame ``scripted``).

Topics are named as in the rig; each node declares them under its own name (``~/tip_pose``,
``~/keyboard_joy`` and ``~/joy``, ``~/bend_command``, ``~/insertion_command``; ``expert_joy``:
``~/joy``) and ``record_demos`` remaps them (:data:`cgail_rig.record_demos.REMAPS`).
"""

from __future__ import annotations

from collections.abc import Callable
import math
import time
from typing import Any

from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState, Joy
from std_msgs.msg import Header

from cgail_learning.recorder import DemoRecorder, EpisodeEnd
from cgail_planner.core.errors import InvalidInputError
from cgail_planner.nodes import conversions as conv

KEYBOARD_FRAME = 'keyboard'
"""``header.frame_id`` of the Joy messages of the page's keyboard."""
SCRIPTED_FRAME = 'scripted'
"""``header.frame_id`` of the Joy messages of the scripted demonstrator."""


class JoyLayout:
    """Where teleop reads the sticks and buttons (its parameters), and the discard button."""

    def __init__(self, *, axis_insertion: int = 1, axis_bend_alpha: int = 4,
                 axis_bend_gamma: int = 3, enable_button: int = 4,
                 discard_button: int = 1) -> None:
        self.axis_insertion = axis_insertion
        self.axis_bend_alpha = axis_bend_alpha
        self.axis_bend_gamma = axis_bend_gamma
        self.enable_button = enable_button
        self.discard_button = discard_button
        self.n_axes = max(axis_insertion, axis_bend_alpha, axis_bend_gamma) + 1
        self.n_buttons = max(enable_button, discard_button) + 1

    def item(self) -> dict[str, int]:
        """The layout for the page's keyboard."""
        return {'axis_insertion': self.axis_insertion, 'axis_bend_alpha': self.axis_bend_alpha,
                'axis_bend_gamma': self.axis_bend_gamma, 'enable_button': self.enable_button,
                'discard_button': self.discard_button, 'n_axes': self.n_axes,
                'n_buttons': self.n_buttons}

    def message(self, stamp: Any, frame_id: str, insertion: float, alpha: float,
                gamma: float, deadman: bool) -> Joy:
        """A Joy message with these deflections."""
        axes = [0.0] * self.n_axes
        axes[self.axis_insertion] = float(insertion)
        axes[self.axis_bend_alpha] = float(alpha)
        axes[self.axis_bend_gamma] = float(gamma)
        buttons = [0] * self.n_buttons
        buttons[self.enable_button] = int(deadman)
        return Joy(header=Header(stamp=stamp, frame_id=frame_id), axes=axes, buttons=buttons)


def joy_device(frame_id: str) -> str:
    """The device a Joy message comes from, by its frame: keyboard, scripted or gamepad."""
    return {KEYBOARD_FRAME: 'keyboard', SCRIPTED_FRAME: 'scripted'}.get(frame_id, 'gamepad')


def joy_problem(axes: list[float], buttons: list[int], layout: JoyLayout) -> str:
    """'' for a Joy message teleop can use, else what is wrong with it (one line)."""
    for name in ('axis_insertion', 'axis_bend_alpha', 'axis_bend_gamma'):
        i = getattr(layout, name)
        if i >= len(axes):
            return f'expected at least {i + 1} Joy axes, found {len(axes)}'
        if not (math.isfinite(axes[i]) and -1.0 <= axes[i] <= 1.0):
            return f'expected Joy axis {i} finite in [-1, 1], found {axes[i]!r}'
    if layout.enable_button >= len(buttons):
        return f'expected at least {layout.enable_button + 1} Joy buttons, found {len(buttons)}'
    return ''


class RecorderNode(Node):
    """The simulated catheter of a recording (module docstring).

    Args:
        recorder: the recording.
        page: the guidance page (None: no page).
        layout: teleop's Joy layout and the discard button.
        on_end: called with each episode's end.
        report: called with the one line of a problem the demonstrator should see.
    """

    def __init__(self, recorder: DemoRecorder, page: Any, layout: JoyLayout, *,
                 on_end: Callable[[EpisodeEnd], None], report: Callable[[str], None],
                 **kwargs: Any) -> None:
        super().__init__('record_demos', **kwargs)
        self.recorder = recorder
        self.page = page
        self.layout = layout
        self._on_end = on_end
        self._report = report
        self.bend = (0.0, 0.0)
        self.velocity = 0.0
        self._devices: set[str] = set()
        self._discard_held = False
        self._discard = False
        self.rejected: dict[str, int] = {}
        self._last_joy: dict[str, float] = {}
        self._next_devices = 0.0
        self._tip_pub = self.create_publisher(PoseStamped, '~/tip_pose', conv.SENSOR_QOS)
        self._joy_pub = self.create_publisher(Joy, '~/keyboard_joy', conv.SENSOR_QOS)
        self.create_subscription(JointState, '~/bend_command', self._on_bend, conv.COMMAND_QOS)
        self.create_subscription(JointState, '~/insertion_command', self._on_insertion,
                                 conv.COMMAND_QOS)
        self.create_subscription(Joy, '~/joy', self._on_joy, conv.SENSOR_QOS)

    # ------------------------------------------------------------------ inputs
    def _on_bend(self, msg: JointState) -> None:
        try:
            alpha, gamma = conv.joint_positions(msg, conv.BEND_JOINTS)
        except InvalidInputError as exc:
            self._reject(f'bend command: {exc}')
            return
        self.bend = (alpha, gamma)

    def _on_insertion(self, msg: JointState) -> None:
        names = list(msg.name)
        if 'insertion' not in names or len(msg.velocity) != len(names) \
                or not math.isfinite(msg.velocity[names.index('insertion')]):
            self._reject(f'insertion command: expected a finite velocity of joint insertion, '
                         f'found names {names[:3]} with velocities {list(msg.velocity)[:3]}')
            return
        self.velocity = float(msg.velocity[names.index('insertion')])

    def _on_joy(self, msg: Joy) -> None:
        axes, buttons = list(msg.axes), list(msg.buttons)
        problem = joy_problem(axes, buttons, self.layout)
        if problem:
            self._reject(f'joy ({joy_device(msg.header.frame_id)}): {problem}: teleop stopped '
                         'the catheter (deadman released); fix the device or its axes')
            return
        device = joy_device(msg.header.frame_id)
        self._last_joy[device] = time.monotonic()
        if buttons[self.layout.enable_button]:
            self._devices.add(device)
        held = len(buttons) > self.layout.discard_button and bool(
            buttons[self.layout.discard_button])
        if held and not self._discard_held:
            self._discard = True
        self._discard_held = held

    def _reject(self, text: str) -> None:
        """Report a rejected input once (then only count it)."""
        key = text.split(':', 2)[0]
        self.rejected[key] = self.rejected.get(key, 0) + 1
        if self.rejected[key] == 1:
            self._report(text)

    # ------------------------------------------------------------------ the world
    def world_step(self, dt: float) -> None:
        """One control step: discard if asked, step the recording with the latest commands,
        show it, and publish the tip and the page's keyboard."""
        rec = self.recorder
        discard = self._discard or (self.page is not None and self.page.take_discard())
        self._discard = False
        end = rec.discard() if discard else rec.step(self.bend, self.velocity, self._devices)
        self._devices = set()
        if end is not None:
            self._on_end(end)
        stamp = self.get_clock().now()
        position, rotation = rec.tip
        self._tip_pub.publish(conv.pose_msg(stamp.to_msg(), 'phantom', position, rotation))
        if self.page is not None:
            status = {**rec.status(), 'layout': self.layout.item()}
            self.page.show(stamp.nanoseconds * 1e-9, status, rec.serial, position, rotation,
                           rec.target_position, self.bend)
            if time.monotonic() >= self._next_devices:
                self._next_devices = time.monotonic() + 1.0
                self.page.show_devices(self.device_statuses())
            keys = self.page.keyboard()
            if keys is not None:
                axes, buttons = keys
                self._joy_pub.publish(Joy(header=Header(stamp=stamp.to_msg(),
                                                        frame_id=KEYBOARD_FRAME),
                                          axes=list(axes), buttons=list(buttons)))


    def device_statuses(self) -> list[dict[str, Any]]:
        """The page's devices panel: the simulator, and the Joy input seen last."""
        rec = self.recorder
        now = time.monotonic()
        seen = {d: now - t for d, t in self._last_joy.items() if now - t < 2.0}
        if seen:
            level, message = 0, ', '.join(f'{d} ({age:.1f} s ago)' for d, age in
                                          sorted(seen.items()))
        else:
            level, message = 1, ('no Joy for 2 s: plug in a gamepad, or use the keyboard '
                                 '(hold Space)')
        bad = sum(self.rejected.values())
        return [{'name': 'record_demos: simulator', 'level': 0,
                 'message': f'{rec.mode}, {rec.anatomy}, driver {rec.driver}'},
                {'name': 'record_demos: input', 'level': 2 if bad else level,
                 'message': f'{bad} input(s) rejected' if bad else message}]


class ExpertJoyNode(Node):
    """The scripted demonstrator at the gamepad (module docstring).

    Args:
        recorder: the recording (its env is the one the expert plans in).
        layout: teleop's Joy layout.
        seed: base seed of the expert's episodes (episode start ``n`` uses ``seed + n``).
        period_s: publishing period, s (the env's control step).
    """

    def __init__(self, recorder: DemoRecorder, layout: JoyLayout, *, seed: int,
                 period_s: float, **kwargs: Any) -> None:
        super().__init__('expert_joy', **kwargs)
        from cgail_learning.expert import ScriptedExpert

        self.recorder = recorder
        self.layout = layout
        self.seed = seed
        self.expert = ScriptedExpert(recorder.env)
        self._serial = -1
        self._released = True
        self._pub = self.create_publisher(Joy, '~/joy', conv.SENSOR_QOS)
        self.create_timer(period_s, self._on_tick)

    def _on_tick(self) -> None:
        rec = self.recorder
        stamp = self.get_clock().now().to_msg()
        if rec.phase not in ('waiting', 'running'):
            if not self._released:  # one release, like a hand leaving the deadman
                self._pub.publish(self.layout.message(stamp, SCRIPTED_FRAME, 0.0, 0.0, 0.0,
                                                      False))
                self._released = True
            return
        if rec.serial != self._serial:
            self._serial = rec.serial
            self.expert.reset(self.seed + rec.serial)
        a = self.expert.act()
        self._pub.publish(self.layout.message(stamp, SCRIPTED_FRAME, a[2], a[0], a[1], True))
        self._released = False

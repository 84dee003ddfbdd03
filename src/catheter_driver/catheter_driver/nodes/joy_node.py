"""Gamepad node (``joy``): SDL2 gamepad -> sensor_msgs/Joy with the ROS joy conventions.

Run: ``ros2 run catheter_driver joy_node`` (or ``scripts/ws joy_node``). Parameters have the
names of the ROS 2 ``joy`` package (``device_id``, ``device_name``, ``deadzone``,
``autorepeat_rate``, ``coalesce_interval_ms``, ``sticky_buttons``). It publishes ``~/joy``
(``/joy/joy``); the rig's launch files remap it to ``joy`` (``-r ~/joy:=joy`` by hand).
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from sensor_msgs.msg import Joy

from catheter_driver.core.joy_filter import JoyConfig, JoyFilter
from catheter_driver.exceptions import DeviceDisconnectedError
from catheter_driver.hw.gamepad import Gamepad, GamepadFactory, SdlGamepad
from catheter_driver.nodes import conversions as conv
from cgail_node_utils.entry_point import run_node
from cgail_node_utils.parameters import declare


class JoyNode(Node):
    """Polls a :class:`Gamepad` and publishes Joy; retries opening while none is present."""

    def __init__(self, *, gamepad_factory: GamepadFactory | None = None, **kwargs) -> None:
        super().__init__('joy', **kwargs)
        d = JoyConfig()
        self._device_id = declare(self, 'device_id', 0, 'SDL joystick index', lo=0, hi=255)
        self._device_name = declare(self, 'device_name', '',
                                    'joystick name; takes precedence over device_id when set')
        self.config = JoyConfig(
            deadzone=declare(self, 'deadzone', d.deadzone,
                             'axis deadzone as a fraction of the range, [0, 1)', lo=0.0, hi=1.0),
            autorepeat_rate=declare(self, 'autorepeat_rate', d.autorepeat_rate,
                                    'republish rate of an unchanged state, Hz; 0 = off',
                                    lo=0.0, hi=1000.0),
            coalesce_interval=declare(self, 'coalesce_interval_ms', 1,
                                      'merge axis changes within this interval, ms',
                                      lo=0, hi=10000) / 1000.0,
            sticky_buttons=declare(self, 'sticky_buttons', d.sticky_buttons,
                                   'each press toggles the reported button'))
        poll_rate = declare(self, 'poll_rate_hz', 100.0, 'SDL polling rate, Hz',
                            lo=1.0, hi=1000.0)
        self._retry_interval = declare(self, 'reconnect_interval_s', 1.0,
                                       'time between attempts to open the gamepad, s',
                                       lo=0.01, hi=60.0)
        diag_period = declare(self, 'diagnostics_period_s', 1.0, '/diagnostics period, s',
                              lo=0.01, hi=60.0)
        self._frame_id = declare(self, 'frame_id', 'joy', 'header.frame_id of Joy')
        self._factory: GamepadFactory = gamepad_factory or SdlGamepad.open
        self._filter = JoyFilter(self.config)
        self._pad: Gamepad | None = None
        self._next_try = 0.0
        self._error = 'not opened yet'
        self.open_attempts = 0
        self.published = 0
        self._joy_pub = self.create_publisher(Joy, '~/joy', conv.SENSOR_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                               conv.DIAGNOSTICS_QOS)
        self.create_timer(1.0 / poll_rate, self._on_poll)
        self.create_timer(diag_period, self._on_diagnostics)

    def _on_poll(self) -> None:
        now = time.monotonic()
        if self._pad is None:
            if now < self._next_try:
                return
            self._next_try = now + self._retry_interval
            self.open_attempts += 1
            try:
                self._pad = self._factory(self._device_id, self._device_name)
            except DeviceDisconnectedError as exc:  # GamepadNotFoundError included
                self._error = (f'{exc}; plug in a gamepad (retrying every '
                               f'{self._retry_interval:g} s)')
                self.get_logger().error(self._error, throttle_duration_sec=10.0)
                return
            self._filter.reset()
            self.get_logger().info(f'opened gamepad {self._pad.name!r}, deadzone '
                                   f'{self.config.deadzone}')
        try:
            sample = self._pad.read()
        except DeviceDisconnectedError as exc:
            self._pad.close()
            self._pad = None
            self._error = f'{exc}; waiting for it to come back'
            self.get_logger().error(self._error)
            return
        out = self._filter.update(sample, now)
        if out is not None:
            self._joy_pub.publish(conv.joy_message(self.get_clock().now(), out, self._frame_id))
            self.published += 1

    def _on_diagnostics(self) -> None:
        self._diag_pub.publish(self.diagnostics_message())

    def diagnostics_message(self) -> DiagnosticArray:
        """The current /diagnostics array (one status for the gamepad)."""
        if self._pad is not None:
            level, message = DiagnosticStatus.OK, f'gamepad {self._pad.name!r} open'
        else:
            level, message = DiagnosticStatus.ERROR, f'no gamepad: {self._error}'
        values = [('device_id', self._device_id), ('device_name', self._device_name),
                  ('open', self._pad is not None), ('open_attempts', self.open_attempts),
                  ('published', self.published)]
        return conv.diagnostics(self.get_clock().now(), 'joy: gamepad', 'gamepad', level,
                                message, values)

    def destroy_node(self) -> None:
        """Close the gamepad."""
        if self._pad is not None:
            self._pad.close()
            self._pad = None
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Console script ``joy_node``."""
    run_node(JoyNode, 'joy_node', args)


if __name__ == '__main__':
    main()

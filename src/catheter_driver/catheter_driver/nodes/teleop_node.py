"""Teleop node (``teleop``): Joy -> insertion velocity and bend commands, with a deadman.

Run: ``ros2 run catheter_driver teleop_node`` (or ``scripts/ws teleop_node``). See
:mod:`catheter_driver.core.teleop` for the deadman convention and the bend modes. It reads
``~/joy`` and publishes ``~/insertion_command`` and ``~/bend_command`` (under its name); the
rig's launch files remap them to ``joy`` and ``catheter/...`` (docs/interfaces.md).
"""

from __future__ import annotations

from rclpy.node import Node
from sensor_msgs.msg import JointState, Joy

from catheter_driver.core.teleop import Teleop, TeleopConfig, TeleopOutput
from catheter_driver.exceptions import CommandError
from catheter_driver.nodes import conversions as conv
from cgail_node_utils.entry_point import run_node
from cgail_node_utils.parameters import declare


class TeleopNode(Node):
    """Thin wrapper around :class:`Teleop`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('teleop', **kwargs)
        d = TeleopConfig()
        self.config = TeleopConfig(
            enable_button=declare(self, 'enable_button', d.enable_button,
                                  'deadman button index (must be held)', lo=0, hi=63),
            axis_insertion=declare(self, 'axis_insertion', d.axis_insertion,
                                   'Joy axis for insertion velocity', lo=0, hi=63),
            scale_insertion=declare(self, 'scale_insertion', d.scale_insertion,
                                    'insertion velocity at full deflection, m/s '
                                    '(|.| <= 0.005, negative inverts)', lo=-0.005, hi=0.005),
            axis_bend_alpha=declare(self, 'axis_bend_alpha', d.axis_bend_alpha,
                                    'Joy axis for bend_alpha', lo=0, hi=63),
            axis_bend_gamma=declare(self, 'axis_bend_gamma', d.axis_bend_gamma,
                                    'Joy axis for bend_gamma', lo=0, hi=63),
            scale_bend=declare(self, 'scale_bend', d.scale_bend,
                               'rate mode: rad/s at full deflection; position mode: rad'),
            bend_mode=declare(self, 'bend_mode', d.bend_mode, "'rate' or 'position'"),
            max_insertion_speed=declare(self, 'max_insertion_speed', d.max_insertion_speed,
                                        'insertion speed cap, m/s', lo=1e-6, hi=0.005),
            max_bend=declare(self, 'max_bend', d.max_bend, 'bend angle cap, rad',
                             lo=1e-6, hi=d.max_bend),
            max_dt=declare(self, 'max_dt_s', d.max_dt, 'largest rate-mode integration step, s'),
            joy_timeout=declare(self, 'joy_timeout_s', d.joy_timeout,
                                'enabled and no Joy for this long: one stop, s'))
        self.teleop = Teleop(self.config)
        self._insertion_pub = self.create_publisher(JointState, '~/insertion_command',
                                                    conv.COMMAND_QOS)
        self._bend_pub = self.create_publisher(JointState, '~/bend_command', conv.COMMAND_QOS)
        # refilled per publish (conv.insertion_state's out)
        self._insertion_msg, self._bend_msg = JointState(), JointState()
        self.create_subscription(Joy, '~/joy', self._on_joy, conv.SENSOR_QOS)
        self.create_timer(0.05, self._on_tick)

    def _on_joy(self, msg: Joy) -> None:
        try:
            out = self.teleop.on_joy(list(msg.axes), list(msg.buttons), conv.node_seconds(self))
        except CommandError as exc:
            self.get_logger().warning(f'Joy message rejected: {exc}', throttle_duration_sec=1.0)
            out = self.teleop.on_invalid()
        self._publish(out)

    def _on_tick(self) -> None:
        out = self.teleop.on_tick(conv.node_seconds(self))
        if out.insertion_velocity is not None:
            self.get_logger().warning('Joy went stale while enabled: stop sent')
        self._publish(out)

    def _publish(self, out: TeleopOutput) -> None:
        stamp = self.get_clock().now()
        if out.insertion_velocity is not None:
            self._insertion_pub.publish(conv.insertion_command(stamp, out.insertion_velocity,
                                                               out=self._insertion_msg))
        if out.bend is not None:
            self._bend_pub.publish(conv.bend_command(stamp, out.bend, out=self._bend_msg))


def main(args: list[str] | None = None) -> None:
    """Console script ``teleop_node``."""
    run_node(TeleopNode, 'teleop_node', args)


if __name__ == '__main__':
    main()

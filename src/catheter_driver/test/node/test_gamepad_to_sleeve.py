"""Whole chain in one process: fake gamepad -> joy -> teleop -> sleeve_driver -> simulated CAN."""

import uuid

from rclpy.parameter import Parameter

from catheter_driver.hw.gamepad import FakeGamepad, FakeGamepadFactory
from catheter_driver.nodes.driver_node import DriverNode
from catheter_driver.nodes.joy_node import JoyNode
from catheter_driver.nodes.teleop_node import TeleopNode

# Each node names its topics under its own name; the rig's launch files (docs/interfaces.md)
# remap them onto the shared ones, as here.
JOY_REMAPS = ['--ros-args', '-r', '~/joy:=joy']
TELEOP_REMAPS = ['--ros-args', '-r', '~/joy:=joy',
                 '-r', '~/insertion_command:=catheter/insertion_command',
                 '-r', '~/bend_command:=catheter/bend_command']
DRIVER_REMAPS = ['--ros-args', '-r', '~/insertion_command:=catheter/insertion_command',
                 '-r', '~/insertion_state:=catheter/insertion_state']


def test_deadman_drives_the_simulated_sleeve_and_release_stops_it(harness):
    pad = FakeGamepad(n_axes=6, n_buttons=8, n_hats=0)
    harness.add(JoyNode(gamepad_factory=FakeGamepadFactory(pad), cli_args=JOY_REMAPS))
    # defaults: deadman button 4, insertion axis 1
    harness.add(TeleopNode(cli_args=TELEOP_REMAPS))
    driver = harness.add(DriverNode(parameter_overrides=[
        Parameter('can_channel', value=f'chain_{uuid.uuid4().hex}')], cli_args=DRIVER_REMAPS))
    driver.trigger_configure()
    driver.trigger_activate()
    mech = driver.sim.mechanism
    assert harness.spin_until(lambda: driver._controller is not None
                              and driver._controller.phase.name == 'DRIVE')
    harness.spin_for(0.3)
    assert mech.catheter_position == 0.0  # stick pushed, deadman not held: nothing moves
    pad.set(axes=[0, -32768, 0, 0, 0, 0])  # left stick fully up = insert
    harness.spin_for(0.3)
    assert mech.catheter_position == 0.0
    buttons = [False] * 8
    buttons[4] = True
    pad.set(buttons=buttons)
    assert harness.spin_until(lambda: mech.catheter_position > 0.002)
    assert abs(mech.catheter_velocity) <= 0.005 + 1e-9
    pad.set(buttons=[False] * 8)  # release: one stop, then the sleeve stays put

    def held_still() -> bool:
        # the sleeve also pauses while the grippers regrip (sleeve_velocity 0 for a moment):
        # stopped means no motion over a window longer than a regrip
        before = mech.catheter_position
        harness.spin_for(0.3)
        return mech.sleeve_velocity == 0.0 and mech.catheter_position == before

    assert harness.spin_until(held_still)
    stopped_at = mech.catheter_position
    harness.spin_for(0.5)
    assert mech.catheter_position == stopped_at

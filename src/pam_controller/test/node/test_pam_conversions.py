"""Message <-> core mapping (no rclpy context needed)."""

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
import pytest
from sensor_msgs.msg import JointState

from pam_controller.errors import CommandRejectedError
from pam_controller.nodes import conversions as conv


def test_bend_joints_found_by_name_in_any_order_among_others():
    msg = JointState(name=['insertion', 'bend_gamma', 'bend_alpha'], position=[0.01, -0.2, 0.3])
    np.testing.assert_array_equal(conv.bend_from_joint_state(msg), [0.3, -0.2])


@pytest.mark.parametrize(('names', 'positions', 'match'), [
    (['bend_alpha'], [0.1], 'missing'),
    (['bend_alpha', 'bend_gamma'], [0.1], 'one position per joint name'),
    ([], [], 'missing'),
])
def test_malformed_bend_commands_rejected(names, positions, match):
    with pytest.raises(CommandRejectedError, match=match):
        conv.bend_from_joint_state(JointState(name=names, position=positions))


def test_pressure_layout_and_bend_state():
    msg = conv.pressures_to_multiarray([1.0, 2.0, 3.0, 4.0])
    assert msg.layout.dim[0].label == 'alpha_pos,alpha_neg,gamma_pos,gamma_neg'
    assert (msg.layout.dim[0].size, msg.layout.dim[0].stride, msg.layout.data_offset) == (4, 4, 0)
    assert list(msg.data) == [1.0, 2.0, 3.0, 4.0]
    js = conv.bend_to_joint_state([0.1, -0.2], JointState().header.stamp)
    assert list(js.name) == ['bend_alpha', 'bend_gamma'] and list(js.position) == [0.1, -0.2]


def test_diagnostic_values_formatting():
    st = conv.diagnostic_status('n', 'hw', DiagnosticStatus.WARN, 'm',
                                [('a', 0.5), ('b', float('nan')), ('c', np.array([1.0, 2.5])),
                                 ('d', True)])
    assert {kv.key: kv.value for kv in st.values} == {'a': '0.5', 'b': 'nan', 'c': '[1, 2.5]',
                                                      'd': 'True'}
    assert (st.level, st.name, st.hardware_id, st.message) == (DiagnosticStatus.WARN, 'n', 'hw',
                                                               'm')


def test_refilled_messages_equal_new_ones():
    # the control loop refills its pressures and bend messages (out=)
    from builtin_interfaces.msg import Time

    pressures = bend = None
    for k in range(2):
        p, b, stamp = np.array([1e5, 2e5, 3e5, 4e5]) * (k + 1), (0.1 * k, -0.2), Time(sec=k)
        pressures = conv.pressures_to_multiarray(p, out=pressures)
        assert pressures == conv.pressures_to_multiarray(p)
        bend = conv.bend_to_joint_state(b, stamp, out=bend)
        assert bend == conv.bend_to_joint_state(b, stamp)

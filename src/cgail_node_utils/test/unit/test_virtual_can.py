"""The device nodes' virtual CAN bus: python-can's ``virtual`` semantics with a cheaper copy."""

import can

from cgail_node_utils.virtual_can import LightVirtualBus, open_bus


def test_a_light_bus_talks_to_python_cans_virtual_bus_with_copies_of_its_own() -> None:
    light = open_bus('virtual', 'test_light_vcan', receive_own_messages=False)
    plain = can.Bus(interface='virtual', channel='test_light_vcan')
    try:
        assert isinstance(light, LightVirtualBus)
        sent = can.Message(arbitration_id=0x123, data=[1, 2, 3], is_extended_id=False)
        light.send(sent)
        got = plain.recv(timeout=0.0)
        assert got is not None and got is not sent and got.data is not sent.data
        assert (got.arbitration_id, bytes(got.data), got.dlc, got.is_rx, got.channel) == \
            (0x123, b'\x01\x02\x03', 3, True, 'test_light_vcan')
        sent.data[0] = 9  # the receiver's copy is its own
        assert bytes(got.data) == b'\x01\x02\x03'
        assert light.recv(timeout=0.0) is None  # not its own frames
        plain.send(can.Message(arbitration_id=0x7, data=b'\x05'))
        back = light.recv(timeout=0.0)
        assert back is not None and (back.arbitration_id, bytes(back.data)) == (0x7, b'\x05')
        assert light.recv(timeout=0.0) is None and light.recv(timeout=0.01) is None
    finally:
        light.shutdown()
        plain.shutdown()


def test_a_light_bus_with_filters_or_a_bounded_queue_takes_python_cans_path() -> None:
    light = open_bus('virtual', 'test_light_vcan2', rx_queue_size=2)
    peer = open_bus('virtual', 'test_light_vcan2')
    try:
        light.set_filters([{'can_id': 0x10, 'can_mask': 0x7FF}])
        for can_id in (0x11, 0x10):
            peer.send(can.Message(arbitration_id=can_id, data=b'\x01'))
        # python-can's filtered loop: a zero timeout drops 0x11 and gives up, as it does
        assert light.recv(timeout=0.0) is None
        got = light.recv(timeout=0.0)
        assert got is not None and got.arbitration_id == 0x10
        assert light.recv(timeout=0.0) is None
    finally:
        light.shutdown()
        peer.shutdown()

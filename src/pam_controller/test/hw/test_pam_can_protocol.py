"""CAN message set: DBC contents, exact frame bytes, CRC, and rejection of malformed frames."""

import can
import numpy as np
import pytest

from pam_controller.core.supervisor import BankMode
from pam_controller.errors import ProtocolError
from pam_controller.hw import can_protocol as proto


def test_crc8_sae_j1850_check_value():
    assert proto.crc8_sae_j1850(b'123456789') == 0x4B
    assert proto.crc8_sae_j1850(b'') == 0x00


def _crc8_bitwise(data: bytes) -> int:
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def test_crc8_table_equals_the_bitwise_definition():
    rng = np.random.default_rng(5)
    cases = [bytes([b]) for b in range(256)] + [
        rng.integers(0, 256, size=int(n)).astype(np.uint8).tobytes()
        for n in rng.integers(0, 12, size=2000)]
    assert all(proto.crc8_sae_j1850(c) == _crc8_bitwise(c) for c in cases)


def test_dbc_defines_the_documented_message_set():
    db = proto.load_database()
    table = {m.frame_id: (m.name, m.length, m.cycle_time, m.senders) for m in db.messages}
    assert table == {
        0x200: ('PAM_SETPOINTS', 8, 20, ['HOST']),
        0x201: ('PAM_MEASURED', 8, 10, ['PAM_BANK']),
        0x202: ('PAM_STATUS', 8, 100, ['PAM_BANK']),
        0x700: ('PAM_HOST_HEARTBEAT', 3, 100, ['HOST']),
    }
    sp = db.get_message_by_name('PAM_SETPOINTS').get_signal_by_name('SETPOINT_2')
    assert (sp.start, sp.length, sp.scale, sp.offset, sp.unit) == (24, 12, 0.1, 0, 'kPa')
    meas = db.get_message_by_name('PAM_MEASURED').get_signal_by_name('PRESSURE_0')
    assert (meas.scale, meas.offset, meas.minimum, meas.maximum) == (0.1, -10, -10, 399.5)


def test_setpoints_frame_exact_bytes():
    msg = proto.encode_setpoints([150e3, 0.0, 409.5e3, 100.0], counter=19)
    raw = 1500 | (0 << 12) | (4095 << 24) | (1 << 36) | (3 << 48)
    body = raw.to_bytes(7, 'little')
    assert msg.arbitration_id == 0x200 and not msg.is_extended_id
    assert bytes(msg.data) == body + bytes([proto.crc8_sae_j1850(b'\x02\x00' + body)])


def test_measured_frame_exact_bytes_with_offset():
    msg = proto.encode_measured([0.0, -10e3, 399.5e3, 1e3], counter=5)
    raw = 100 | (0 << 12) | (4095 << 24) | (110 << 36) | (5 << 48)
    assert bytes(msg.data)[:7] == raw.to_bytes(7, 'little')


def test_heartbeat_frame_exact_bytes():
    msg = proto.encode_host_heartbeat(BankMode.VENT, counter=7)
    assert msg.arbitration_id == 0x700
    assert bytes(msg.data)[:2] == bytes([0x27, 0x00])
    assert msg.data[2] == proto.crc8_sae_j1850(b'\x07\x00\x27\x00')


def test_round_trip_all_messages_with_quantisation():
    p = np.array([123456.0, 0.0, 299999.0, 42.0])
    sp = proto.decode(proto.encode_setpoints(p, 3))
    assert isinstance(sp, proto.Setpoints) and sp.counter == 3
    np.testing.assert_allclose(sp.pressures_pa, p, atol=50.0)
    me = proto.decode(proto.encode_measured(p - 5e3, 15))
    assert isinstance(me, proto.Measured) and me.counter == 15
    np.testing.assert_allclose(me.pressures_pa, p - 5e3, atol=50.0)
    faults = frozenset({'FAULT_STUCK', 'FAULT_BAD_FRAME'})
    st = proto.decode(proto.encode_status(proto.BankState.FAULT, faults, 0b0100, 350e3, 9))
    assert st == proto.Status(proto.BankState.FAULT, faults, 4, 350e3, 9)
    hb = proto.decode(proto.encode_host_heartbeat(BankMode.RUN, 16))
    assert hb == proto.HostHeartbeat(BankMode.RUN, 0)


def test_measured_saturates_at_encodable_range():
    me = proto.decode(proto.encode_measured([-50e3, 500e3, 0.0, 0.0], 0))
    assert isinstance(me, proto.Measured)
    np.testing.assert_allclose(me.pressures_pa[:2], [-10e3, 399.5e3])


@pytest.mark.parametrize('values', [[500e3, 0, 0, 0], [-1.0, 0, 0, 0], [float('nan'), 0, 0, 0],
                                    [0, 0, 0]])
def test_setpoints_outside_encodable_range_raise(values):
    with pytest.raises(ProtocolError):
        proto.encode_setpoints(values, 0)


def test_unknown_fault_name_raises():
    with pytest.raises(ProtocolError, match='expected faults among'):
        proto.encode_status(proto.BankState.READY, {'FAULT_FIRE'}, 0, 0.0, 0)


def _good() -> can.Message:
    return proto.encode_measured([100e3, 100e3, 100e3, 100e3], 1)


def test_foreign_frames_are_not_ours():
    assert proto.decode(can.Message(arbitration_id=0x123, data=b'\x01\x02')) is None
    ext = can.Message(arbitration_id=0x201, data=_good().data, is_extended_id=True)
    assert proto.decode(ext) is None


def test_wrong_length_rejected():
    msg = can.Message(arbitration_id=0x201, data=bytes(_good().data)[:6], is_extended_id=False)
    with pytest.raises(ProtocolError, match='expected 8 data bytes for PAM_MEASURED'):
        proto.decode(msg)


def test_bad_crc_rejected():
    data = bytearray(_good().data)
    data[0] ^= 0x01
    with pytest.raises(ProtocolError, match='expected CRC'):
        proto.decode(can.Message(arbitration_id=0x201, data=bytes(data), is_extended_id=False))


def test_valid_payload_on_another_id_rejected_by_crc():
    data = proto.encode_setpoints([1e3, 2e3, 3e3, 4e3], 0).data
    with pytest.raises(ProtocolError, match='expected CRC'):
        proto.decode(can.Message(arbitration_id=0x201, data=data, is_extended_id=False))


def test_remote_and_error_frames_on_our_ids_rejected():
    remote = can.Message(arbitration_id=0x202, is_remote_frame=True, dlc=8, is_extended_id=False)
    with pytest.raises(ProtocolError, match='error/remote frame'):
        proto.decode(remote)


def _with_crc(aid: int, body: bytes) -> can.Message:
    return can.Message(arbitration_id=aid, is_extended_id=False,
                       data=body + bytes([proto.frame_crc(aid, body)]))


def test_out_of_range_enums_rejected_even_with_valid_crc():
    with pytest.raises(ProtocolError, match=r'STATE in 0\.\.4'):
        proto.decode(_with_crc(0x202, bytes([0x07, 0, 0, 0, 0, 0, 0])))
    with pytest.raises(ProtocolError, match=r'MODE in 0\.\.3'):
        proto.decode(_with_crc(0x700, bytes([0x90, 0])))


def test_fast_codec_equals_cantools():
    """Every message takes the fast path (cgail_node_utils.can_codec), and it gives cantools'
    bytes and values, value tables included."""
    db = proto.load_database()
    codecs = proto._codecs()
    assert set(codecs) == {m.name for m in db.messages}
    assert all(c.supported for c in codecs.values())
    rng = np.random.default_rng(3)
    for msg_def in db.messages:
        codec = codecs[msg_def.name]
        lows = np.array([s.minimum for s in msg_def.signals])
        highs = np.array([s.maximum for s in msg_def.signals])
        tol = np.array([abs(s.conversion.scale) * 1e-6 for s in msg_def.signals])
        for k in range(3000):
            if k < 4:  # the bounds, and just inside cantools' tolerance
                values = [lows, highs, lows - 0.9 * tol, highs + 0.9 * tol][k]
            else:
                values = rng.uniform(lows, highs)
            signals = {s.name: (float(v) if s.conversion.scale != 1 else
                                (round(float(v)) if k % 2 else float(round(float(v)))))
                       for s, v in zip(msg_def.signals, values, strict=True)}
            want = db.encode_message(msg_def.name, signals)
            assert codec.pack(signals) == want, (msg_def.name, signals)
            data = bytes(rng.integers(0, 256, size=msg_def.length).astype(np.uint8))
            decoded = db.decode_message(msg_def.frame_id, data, decode_choices=False)
            assert codec.unpack(data) == {n: float(v) for n, v in decoded.items()}
        beyond = {s.name: float(s.maximum) for s in msg_def.signals}
        beyond[msg_def.signals[0].name] = float(msg_def.signals[0].maximum) + 1.0
        assert codec.pack(beyond) is None  # out of range: cantools raises
        assert codec.pack({}) is None  # signals missing: cantools raises

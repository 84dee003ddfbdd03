"""Combined API framing and encoders, exact values."""

from __future__ import annotations

import struct

import pytest

from em_tracker.core.errors import ProtocolError
from em_tracker.hw import combined_api as api


@pytest.mark.parametrize('text,crc', [
    (b'INIT:', 0xE3A5), (b'OKAY', 0xA896), (b'RESET', 0xBE6F), (b'VER:0', 0x65EE),
    (b'123456789', 0xBB3D),  # CRC-16/ARC check value
])
def test_crc16_known_values(text, crc):
    assert api.crc16(text) == crc


def test_crc_of_data_plus_its_crc_is_zero():
    data = b'\xc4\xa5\x2d\x00'
    assert api.crc16(data + struct.pack('<H', api.crc16(data))) == 0


def test_command_round_trip():
    assert api.encode_command('INIT:') == b'INIT:E3A5\r'
    assert api.encode_command('RESET') == b'RESET\r'
    assert api.decode_command(b'TX:0001031A\r') == api.Command('TX', '0001')
    assert api.decode_command(b'TX 0001') == api.Command('TX', '0001')


@pytest.mark.parametrize('frame,match', [
    (b'INIT:0000', 'CRC E3A5'), (b'INIT:E3', 'CRC digits'), (b'\xff\xfe', 'ASCII'),
    (b'in it:E3A5', 'upper-case'), (b'TX\r', "':' or ' ' after the command name"),
])
def test_decode_command_rejects(frame, match):
    with pytest.raises(ProtocolError, match=match):
        api.decode_command(frame)


def test_text_reply_and_error():
    assert api.encode_text_reply('OKAY') == b'OKAYA896\r'
    assert api.decode_text_reply(b'OKAYA896\r') == 'OKAY'
    err = api.encode_error(0x0C)
    assert err.startswith(b'ERROR0C') and api.decode_text_reply(err) == 'ERROR0C'
    with pytest.raises(ProtocolError, match='CRC'):
        api.decode_text_reply(b'OKAYA897\r')
    with pytest.raises(ValueError, match='code must be'):
        api.encode_error(0x100)


def test_tx_body_exact():
    frame = api.ToolFrame(0x0A, api.ToolState.VALID, (1.0, 0.0, -0.0001, 0.0),
                          (12.34, -0.01, 2000.0), 0.0123, 0x31, 0x1F)
    body = api.encode_tx_body([frame], 0x0000)
    assert body == ('010A+10000+00000-00001+00000+001234-000001+200000+00123'
                    '000000310000001F\n0000')
    missing = api.ToolFrame(0x0A, api.ToolState.MISSING, port_status=0x71, frame_number=2)
    assert api.encode_tx_body([missing], 0x0080) == '010AMISSING0000007100000002\n0080'


def test_tx_saturates_and_rejects_nan():
    frame = api.ToolFrame(0x01, api.ToolState.VALID, position_mm=(1e9, 0.0, 0.0))
    assert '+999999' in api.encode_tx_transform(frame)
    with pytest.raises(ValueError, match='finite'):
        api.encode_tx_transform(api.ToolFrame(0x01, api.ToolState.VALID,
                                              position_mm=(float('nan'), 0.0, 0.0)))


def test_bx_reply_layout():
    frame = api.ToolFrame(0x0A, api.ToolState.VALID, (1.0, 0.0, 0.0, 0.0), (1.5, 2.5, -3.5),
                          0.25, 0x31, 7)
    reply = api.encode_bx_reply([frame], 0x0001)
    assert reply[:2] == b'\xc4\xa5'
    length, header_crc = struct.unpack('<HH', reply[2:6])
    assert length == 1 + 2 + 32 + 8 + 2 == len(reply) - 8
    assert header_crc == api.crc16(reply[:4])
    body = reply[6:-2]
    assert struct.unpack('<H', reply[-2:])[0] == api.crc16(body)
    count, handle, hstatus = struct.unpack('<BBB', body[:3])
    assert (count, handle, hstatus) == (1, 0x0A, api.BX_HANDLE_VALID)
    assert struct.unpack('<8f', body[3:35]) == (1.0, 0.0, 0.0, 0.0, 1.5, 2.5, -3.5, 0.25)
    assert struct.unpack('<IIH', body[35:]) == (0x31, 7, 1)
    missing = api.encode_bx_body([api.ToolFrame(0x0A, api.ToolState.MISSING, frame_number=3)])
    assert len(missing) == 1 + 2 + 8 + 2 and missing[2] == api.BX_HANDLE_MISSING


def test_phsr_body():
    assert api.encode_phsr_body([]) == '00'
    assert api.encode_phsr_body([(0x0A, 0x001), (0x0B, 0x031)]) == '020A0010B031'


@pytest.mark.parametrize('kwargs,match', [
    ({'handle': 0}, 'handle'), ({'handle': 1, 'port_status': -1}, 'port_status'),
    ({'handle': 1, 'frame_number': 2**32}, 'frame_number'),
])
def test_tool_frame_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        api.ToolFrame(state=api.ToolState.MISSING, **kwargs)

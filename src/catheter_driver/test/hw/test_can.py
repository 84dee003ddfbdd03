"""CAN message set and the simulated driver on a python-can virtual bus."""

import math
import uuid

import can
import pytest

from catheter_driver.core.relay import GripperState, RelayConfig, RelayController, SleeveFeedback
from catheter_driver.exceptions import DeviceDisconnectedError, ProtocolError
from catheter_driver.hw.can_protocol import (
    COMMAND_ID,
    default_dbc_path,
    DriverCodec,
    DriverCommand,
    DriverStatus,
    ESTOP_ID,
    STATUS_ID,
)
from catheter_driver.hw.driver_link import CanDriverLink
from catheter_driver.hw.sim_driver import main, SimulatedDriver

CODEC = DriverCodec()


@pytest.fixture
def channel():
    return f'test_{uuid.uuid4().hex}'


@pytest.fixture
def rig(channel):
    sim = SimulatedDriver(channel, codec=CODEC)
    link = CanDriverLink.open('virtual', channel, CODEC)
    yield sim, link
    link.close()
    sim.stop()


def test_dbc_is_found_and_has_the_documented_ids():
    assert default_dbc_path().name == 'driver.dbc'
    assert (ESTOP_ID, COMMAND_ID, STATUS_ID) == (0x080, 0x200, 0x210)


def test_command_frame_layout_exact_bytes():
    msg = CODEC.encode_command(DriverCommand(0.005, True, False, counter=7))
    assert msg.arbitration_id == 0x200 and not msg.is_extended_id
    # 5000 um/s = 0x1388 little-endian, bit 16 = moving close, counter 7 in byte 3
    assert bytes(msg.data) == bytes([0x88, 0x13, 0x01, 0x07])
    assert CODEC.decode_command(msg) == DriverCommand(0.005, True, False, 7)
    neg = CODEC.encode_command(DriverCommand(-0.02, False, True, counter=300))
    assert bytes(neg.data) == bytes([0xE0, 0xB1, 0x02, 300 & 0xFF])


def test_status_frame_round_trip_and_layout():
    status = DriverStatus(0.012345, -0.005, GripperState.CLOSED, GripperState.OPENING,
                          stopped=True, stall=False, interlock=True, command_timeout=False,
                          counter=42)
    msg = CODEC.encode_status(status)
    assert bytes(msg.data) == bytes([0x39, 0x30, 0x00, 0x00, 0x78, 0xEC, 0b0101_1110, 42])
    decoded = CODEC.decode_status(msg)
    assert decoded.sleeve_position == pytest.approx(0.012345, abs=1e-12)
    assert decoded.sleeve_velocity == pytest.approx(-0.005, abs=1e-12)
    assert (decoded.moving, decoded.fixed) == (GripperState.CLOSED, GripperState.OPENING)
    assert (decoded.stopped, decoded.interlock, decoded.counter) == (True, True, 42)


def test_estop_frame():
    msg = CODEC.encode_stop(True)
    assert (msg.arbitration_id, bytes(msg.data)) == (0x080, b'\x01')
    assert CODEC.decode_stop(msg) is True


@pytest.mark.parametrize(('msg', 'match'), [
    (can.Message(arbitration_id=STATUS_ID, data=b'\x00\x01\x02', is_extended_id=False),
     'expected 8 data bytes in DRV_STATUS, found 3'),
    (can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False),
     'expected frame id 0x210'),
    (can.Message(arbitration_id=STATUS_ID, data=bytes([0, 0, 0, 0x7F, 0, 0, 0, 0]),
                 is_extended_id=False), r'expected a sleeve position in \[-0.01, 0.2\] m'),
])
def test_malformed_status_raises_protocol_error(msg, match):
    with pytest.raises(ProtocolError, match=match):
        CODEC.decode_status(msg)


@pytest.mark.parametrize('velocity', [math.nan, math.inf, 1.0])
def test_unencodable_command_raises(velocity):
    with pytest.raises(ProtocolError):
        CODEC.encode_command(DriverCommand(velocity, True, False))


def test_relay_over_the_virtual_bus_tracks_the_simulated_catheter(rig):
    sim, link = rig
    dt = 0.01
    status = sim.step(dt)
    assert link.poll() == status
    fb = SleeveFeedback(status.sleeve_position, status.moving, status.fixed)
    ctrl = RelayController(RelayConfig(), fb)
    for _ in range(1200):  # 12 s at 5 mm/s: at least one full relay
        cmd = ctrl.step(0.005, fb, dt)
        link.send_command(DriverCommand(cmd.sleeve_velocity, cmd.moving_close, cmd.fixed_close))
        sim.step(dt)
        assert sim.mechanism.min_held >= 1
        assert abs(sim.mechanism.catheter_velocity) <= 0.005 + 1e-9
        status = link.poll()
        assert status is not None
        fb = SleeveFeedback(status.sleeve_position, status.moving, status.fixed)
    ctrl.step(0.0, fb, dt)  # take in the last feedback
    # Positions travel as micrometre integers on the bus.
    assert ctrl.position == pytest.approx(sim.mechanism.catheter_position, abs=2e-6 * 20)
    assert sim.mechanism.catheter_position > RelayConfig().stroke_max
    assert link.protocol_errors == 0 and link.dropped_frames == 0
    assert sim.commands_received == 1200


def test_garbage_frames_are_counted_not_fatal(rig):
    sim, link = rig
    sim.inject_garbage(9)
    good = sim.step(0.01)
    sim.inject_garbage(3)
    assert link.poll() == good
    assert link.protocol_errors == 12
    assert link.last_error


def test_disconnect_silences_the_device_and_reconnect_recovers(rig):
    sim, link = rig
    sim.step(0.01)
    assert link.poll() is not None
    sim.disconnect()
    assert sim.step(0.01) is None
    assert link.poll() is None
    sim.reconnect()
    assert sim.step(0.01) is not None
    assert link.poll() is not None
    assert link.dropped_frames == 0  # the device does not count silent periods


def test_command_watchdog_stops_the_sleeve(rig):
    sim, link = rig
    # Drive phase by hand: moving closed, fixed open.
    for _ in range(40):
        link.send_command(DriverCommand(0.0, True, True))
        sim.step(0.01)
    for _ in range(40):
        link.send_command(DriverCommand(0.0, True, False))
        sim.step(0.01)
    link.send_command(DriverCommand(0.005, True, False))
    moved = [sim.step(0.01) for _ in range(40)]
    assert moved[0].sleeve_velocity == pytest.approx(0.005)
    assert moved[-1].command_timeout and moved[-1].sleeve_velocity == 0.0
    position = moved[-1].sleeve_position
    assert 0.005 * 0.18 <= position <= 0.005 * 0.21  # stopped ~200 ms after the last command


def test_estop_latch_and_stall_reported(rig):
    sim, link = rig
    for close_fixed in [True] * 40 + [False] * 40:
        link.send_command(DriverCommand(0.0, True, close_fixed))
        sim.step(0.01)
    link.send_stop(True)
    link.send_command(DriverCommand(0.005, True, False))
    status = sim.step(0.01)
    assert status.stopped and status.sleeve_velocity == 0.0
    link.send_stop(False)
    link.send_command(DriverCommand(0.005, True, False))
    assert sim.step(0.01).sleeve_velocity == pytest.approx(0.005)
    sim.set_stall(True)
    link.send_command(DriverCommand(0.005, True, False))
    status = sim.step(0.01)
    assert status.stall and status.sleeve_velocity == 0.0


def test_opening_a_missing_bus_interface_raises_disconnected():
    with pytest.raises(DeviceDisconnectedError, match='expected to open CAN'):
        CanDriverLink.open('no_such_interface', 'x', CODEC)


def test_sim_driver_console_script_runs(capsys):
    assert main(['--duration', '1.0', '--channel', f'cli_{uuid.uuid4().hex}']) == 0
    out = capsys.readouterr().out
    assert 'phase=' in out and 'catheter=' in out


def test_fast_codec_equals_cantools():
    """Every driver frame takes cgail_node_utils.can_codec, with cantools' bytes and values
    (signed signals and their bounds included); out-of-range values still reach cantools."""
    import cantools
    import numpy as np

    db = cantools.database.load_file(str(default_dbc_path()))
    rng = np.random.default_rng(9)
    for msg_def in db.messages:
        codec = CODEC._codecs[msg_def.frame_id]
        assert codec.supported
        lows = np.array([s.minimum for s in msg_def.signals])
        highs = np.array([s.maximum for s in msg_def.signals])
        tol = np.array([abs(s.conversion.scale) * 1e-6 for s in msg_def.signals])
        for k in range(3000):
            values = ([lows, highs, lows - 0.9 * tol, highs + 0.9 * tol][k] if k < 4
                      else rng.uniform(lows, highs))
            signals = {s.name: (round(float(v), 3) if s.conversion.scale != 1
                                else round(float(v)))
                       for s, v in zip(msg_def.signals, values, strict=True)}
            assert codec.pack(signals) == msg_def.encode(signals), (msg_def.name, signals)
            data = bytes(rng.integers(0, 256, size=msg_def.length).astype(np.uint8))
            decoded = msg_def.decode(data, decode_choices=False)
            assert codec.unpack(data) == {n: float(v) for n, v in decoded.items()}
        beyond = {s.name: float(s.maximum) + 1.0 for s in msg_def.signals}
        assert codec.pack(beyond) is None

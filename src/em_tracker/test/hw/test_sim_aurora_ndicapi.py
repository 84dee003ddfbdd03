"""The simulated Aurora read by ndicapi (an independent implementation) over a pty."""

from __future__ import annotations

import time

import ndicapy
import numpy as np
import pytest

from em_tracker.core.errors import DeviceDisconnected, DeviceError, DeviceTimeout, ProtocolError
from em_tracker.hw import combined_api as api
from em_tracker.hw.aurora import AuroraSettings, IsolatedAurora, NdiAurora
from em_tracker.hw.sim_aurora import ScriptedTrajectory, SimAurora, SimGroundTruth

HANDLE = 0x0A
POS = (12.34, -56.78, -210.5)
QUAT = (0.5, 0.5, -0.5, 0.5)


@pytest.fixture
def sim(tmp_path):
    traj = ScriptedTrajectory([0.0, 1000.0], [POS, POS], [QUAT, QUAT])
    device = SimAurora(traj, link_path=str(tmp_path / 'aurora')).start()
    yield device
    device.close()


@pytest.fixture
def tracking(sim):
    """A raw ndicapy handle after INIT/PINIT/PENA/TSTART."""
    dev = ndicapy.ndiOpen(sim.port)
    assert dev is not None
    for command in ('INIT:', 'PINIT:0A', 'PENA:0AD', 'TSTART:'):
        assert ndicapy.ndiCommand(dev, command) == 'OKAY'
    yield dev
    ndicapy.ndiClose(dev)


def test_init_crc_and_handshake_replies(sim):
    dev = ndicapy.ndiOpen(sim.port)
    try:
        assert ndicapy.ndiCommand(dev, 'INIT:') == 'OKAY'
        assert sim.stats.commands[-1] == 'INIT:E3A5'
        assert ndicapy.ndiCommand(dev, 'COMM:50000') == 'OKAY'
        assert sim.stats.baud == 115200
        assert ndicapy.ndiCommand(dev, 'PHSR:02') == '010A001'
        assert ndicapy.ndiGetPHSRNumberOfHandles(dev) == 1
        assert ndicapy.ndiGetPHSRHandle(dev, 0) == HANDLE
        assert ndicapy.ndiCommand(dev, 'PINIT:0A') == 'OKAY'
        assert ndicapy.ndiCommand(dev, 'PHSR:02') == '00'
        assert ndicapy.ndiCommand(dev, 'PHSR:03') == '010A011'
        assert ndicapy.ndiCommand(dev, 'PENA:0AD') == 'OKAY'
        assert ndicapy.ndiCommand(dev, 'PHSR:04') == '010A031'
        assert ndicapy.ndiCommand(dev, 'TSTART:') == 'OKAY'
        assert ndicapy.ndiCommand(dev, 'TSTOP:') == 'OKAY'
    finally:
        ndicapy.ndiClose(dev)


@pytest.mark.parametrize('command,code', [
    ('TX:0001', 0x0C),     # not tracking yet
    ('PENA:0AD', 0x0E),    # not initialised
    ('PINIT:0B', 0x08),    # no such handle
    ('FOO:', 0x01),        # unknown command
    ('COMM:90000', 0x06),  # bad baud digit
])
def test_error_replies_are_decoded_by_ndicapi(sim, command, code):
    dev = ndicapy.ndiOpen(sim.port)
    try:
        ndicapy.ndiCommand(dev, 'INIT:')
        with pytest.raises(OSError, match=f'0x{code:02x}'):
            ndicapy.ndiCommand(dev, command)
        assert ndicapy.ndiGetError(dev) == code
    finally:
        ndicapy.ndiClose(dev)


def test_tx_transform_read_by_ndicapi(tracking):
    reply = ndicapy.ndiCommand(tracking, 'TX:0001')
    assert reply.startswith('010A') and reply.endswith('\n0000')
    transform = ndicapy.ndiGetTXTransform(tracking, bytes([HANDLE]))
    assert transform[:4] == pytest.approx(QUAT, abs=1e-4)
    assert transform[4:7] == pytest.approx(POS, abs=0.01)
    assert transform[7] == pytest.approx(0.25, abs=1e-4)
    status = ndicapy.ndiGetTXPortStatus(tracking, bytes([HANDLE]))
    assert status == api.PORT_OCCUPIED | api.PORT_INITIALIZED | api.PORT_ENABLED
    assert ndicapy.ndiGetTXFrame(tracking, bytes([HANDLE])) >= 1


def test_bx_transform_read_by_ndicapi(tracking):
    ndicapy.ndiCommand(tracking, 'BX:0001')
    transform = ndicapy.ndiGetBXTransform(tracking, bytes([HANDLE]))
    assert transform[:4] == pytest.approx(QUAT, abs=1e-6)
    assert transform[4:7] == pytest.approx(POS, abs=1e-4)
    assert ndicapy.ndiGetBXPortStatus(tracking, bytes([HANDLE])) == 0x31
    assert ndicapy.ndiGetBXSystemStatus(tracking) == 0


@pytest.mark.parametrize('command', ['TX:0001', 'BX:0001'])
@pytest.mark.parametrize('fault,bits', [
    ({'missing': True}, 0),
    ({'out_of_volume': True}, api.PORT_OUT_OF_VOLUME),
    ({'broken_coil': True}, api.PORT_BROKEN_COIL),
])
def test_missing_states_read_by_ndicapi(sim, tracking, command, fault, bits):
    sim.inject(**fault)
    ndicapy.ndiCommand(tracking, command)
    kind = command[:2]
    get_transform = getattr(ndicapy, f'ndiGet{kind}Transform')
    get_status = getattr(ndicapy, f'ndiGet{kind}PortStatus')
    assert get_transform(tracking, bytes([HANDLE])) == 'MISSING'
    assert get_status(tracking, bytes([HANDLE])) == 0x31 | bits


@pytest.mark.parametrize('command', ['TX:0001', 'BX:0001'])
def test_partially_out_of_volume_keeps_transform(sim, tracking, command):
    sim.inject(partially_out=True)
    ndicapy.ndiCommand(tracking, command)
    kind = command[:2]
    assert getattr(ndicapy, f'ndiGet{kind}Transform')(tracking, bytes([HANDLE]))[4] == \
        pytest.approx(POS[0], abs=0.01)
    status = getattr(ndicapy, f'ndiGet{kind}PortStatus')(tracking, bytes([HANDLE]))
    # ndicapi 3.7.6 sign-extends BX status bytes >= 0x80: only the low byte survives there.
    assert status & 0xFF == 0x31 | api.PORT_PARTIALLY_IN_VOLUME


def test_host_repairs_sign_extended_bx_port_status(sim):
    device = NdiAurora(AuroraSettings(port=sim.port, use_bx=True))
    try:
        device.connect()
        sim.inject(partially_out=True)
        assert device.read().tools[0].port_status == 0x31 | api.PORT_PARTIALLY_IN_VOLUME
    finally:
        device.close()


@pytest.mark.parametrize('command', ['TX:0001', 'BX:0001'])
def test_bad_crc_is_detected_by_ndicapi(sim, tracking, command):
    sim.inject(bad_crc=1)
    with pytest.raises(OSError, match='Bad CRC'):
        ndicapy.ndiCommand(tracking, command)
    ndicapy.ndiCommand(tracking, command)  # next reply is clean again
    assert ndicapy.ndiGetError(tracking) == 0


def test_frame_numbers_follow_the_device_clock_and_drops(sim, tracking):
    ndicapy.ndiCommand(tracking, 'TX:0001')
    t1 = time.monotonic()
    first = ndicapy.ndiGetTXFrame(tracking, bytes([HANDLE]))
    time.sleep(0.06)
    sim.inject(drop_frames=5)
    time.sleep(0.03)
    ndicapy.ndiCommand(tracking, 'TX:0001')
    t2 = time.monotonic()
    second = ndicapy.ndiGetTXFrame(tracking, bytes([HANDLE]))
    assert abs((second - first) - 5 - (t2 - t1) * 40.0) <= 2.0


# ---------------------------------------------------------------- host classes over the pty
@pytest.mark.parametrize('cls', [NdiAurora, IsolatedAurora])
@pytest.mark.parametrize('use_bx', [False, True])
def test_host_startup_and_read(sim, cls, use_bx):
    device = cls(AuroraSettings(port=sim.port, use_bx=use_bx))
    try:
        assert device.connect() == [HANDLE]
        reply = device.read()
        tool = reply.tools[0]
        assert tool.visible and tool.handle == HANDLE
        assert tool.position_mm == pytest.approx(POS, abs=0.01)
        assert tool.quat_wxyz == pytest.approx(QUAT, abs=1e-4)
        assert tool.port_status == 0x31
        sim.inject(missing=True)
        assert not device.read().tools[0].visible
    finally:
        device.close()
    assert sim.stats.commands[-1].startswith('TSTOP:')


@pytest.mark.parametrize('fault,exc', [
    ({'bad_crc': 1}, ProtocolError),
    ({'tracking_error': 0x0C}, DeviceError),
    ({'garbage': 1}, ProtocolError),
])
def test_host_maps_faults_to_exceptions(sim, fault, exc):
    device = NdiAurora(AuroraSettings(port=sim.port))
    try:
        device.connect()
        sim.inject(**fault)
        with pytest.raises(exc):
            device.read()
    finally:
        sim.clear_faults()
        device.close()


def test_tracking_error_code_is_kept(sim):
    device = NdiAurora(AuroraSettings(port=sim.port))
    try:
        device.connect()
        sim.inject(tracking_error=0x0C)
        with pytest.raises(DeviceError) as info:
            device.read()
        assert info.value.code == 0x0C
    finally:
        sim.clear_faults()
        device.close()


def test_disconnect_then_reconnect(sim):
    device = NdiAurora(AuroraSettings(port=sim.port))
    try:
        device.connect()
        sim.disconnect()
        with pytest.raises(DeviceDisconnected):
            device.read()
        with pytest.raises(DeviceDisconnected):
            device.connect()
        sim.reconnect()
        assert device.connect() == [HANDLE]
        assert device.read().tools[0].visible
    finally:
        device.close()


def test_isolated_device_survives_a_crash_inside_ndicapi(sim):
    device = IsolatedAurora(AuroraSettings(port=sim.port))
    try:
        device.connect()
        sim.inject(garbage=1, garbage_bytes=b'\xff\xfe', bad_crc=1)
        with pytest.raises(DeviceDisconnected, match='exited with code'):
            device.read()
        assert device.connect() == [HANDLE]
        assert device.read().tools[0].visible
    finally:
        device.close()


@pytest.mark.slow
def test_unanswered_command_times_out(sim):
    """ndicapi waits 5 s for a reply, then the host reports DeviceTimeout."""
    device = NdiAurora(AuroraSettings(port=sim.port))
    try:
        device.connect()
        sim.inject(no_reply=1)
        with pytest.raises(DeviceTimeout):
            device.read()
    finally:
        device.close()


def test_sim_aurora_console_entry_prints_the_port(tmp_path):
    import signal
    import subprocess
    import sys

    link = tmp_path / 'aurora'
    proc = subprocess.Popen([sys.executable, '-m', 'em_tracker.hw.sim_aurora', '--link',
                             str(link)], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith('simulated Aurora on /dev/pts/') and str(link) in line
        device = NdiAurora(AuroraSettings(port=str(link)))
        assert device.connect() == [HANDLE]
        assert device.read().tools[0].visible
        device.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5) == 0
    assert not link.exists()


def test_srom_image_written_with_pvwr_before_pinit(sim, tmp_path):
    rom = bytes(range(256)) * 3 + b'\xa5' * 100  # 868 bytes, padded to 1024 by ndicapi
    path = tmp_path / 'tool.rom'
    path.write_bytes(rom)
    device = NdiAurora(AuroraSettings(port=sim.port, srom_files=((HANDLE, str(path)),)))
    try:
        assert device.connect() == [HANDLE]
    finally:
        device.close()
    names = [c.split(':')[0] for c in sim.stats.commands]
    assert names.count('PVWR') == 16 and names.index('PVWR') < names.index('PINIT')
    assert bytes(sim.ports[HANDLE].srom) == rom + bytes(1024 - len(rom))


def test_srom_write_failure_is_reported(sim, tmp_path):
    device = NdiAurora(AuroraSettings(port=sim.port,
                                      srom_files=((0x0B, str(tmp_path / 'none.rom')),)))
    with pytest.raises(DeviceError, match='cannot read the SROM image'):
        device.connect()
    device.close()


# ---------------------------------------------------------------- hidden ground truth
#: phantom turned +90 deg about z at (100, 0, -200) mm; sensor z along the shaft, 10 mm behind
PLACEMENT = [[0.0, -1.0, 0.0, 100.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, -200.0],
             [0.0, 0.0, 0.0, 1.0]]
MOUNTING = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 10.0],
            [0.0, 0.0, 0.0, 1.0]]


def _still(position_mm):
    return ScriptedTrajectory([0.0, 1000.0], [position_mm, position_mm])


def test_host_reads_the_sensor_pose_in_the_tracker_frame():
    truth = SimGroundTruth(phantom_in_tracker=PLACEMENT, tip_in_sensor=MOUNTING)
    sim = SimAurora(_still([10.0, 20.0, 30.0]), truth=truth).start()
    device = NdiAurora(AuroraSettings(port=sim.port))
    try:
        device.connect()
        tool = device.read().tools[0]
        assert tool.position_mm == pytest.approx((90.0, 10.0, -170.0), abs=0.01)
        assert tool.quat_wxyz == pytest.approx((0.5, -0.5, -0.5, 0.5), abs=1e-4)
    finally:
        device.close()
        sim.close()


def test_noise_is_one_draw_per_frame_from_the_seed():
    """The same frame reads the same however often it is polled; the next frame differs; a
    second device with the same seed reads the same frames."""
    truth = SimGroundTruth(position_noise_mm=0.48, orientation_noise_deg=0.3, seed=7)
    clock = [0.0]
    readings = []
    for _ in range(2):
        sim = SimAurora(_still([0.0, 0.0, -200.0]), truth=truth, clock=lambda: clock[0]).start()
        device = NdiAurora(AuroraSettings(port=sim.port, use_bx=True))
        try:
            clock[0] = 0.0
            device.connect()
            poll = []
            for t in (0.01, 0.02, 0.04):  # frames 0, 0, 1 at 40 Hz
                clock[0] = t
                tool = device.read().tools[0]
                poll.append((*tool.position_mm, *tool.quat_wxyz))
            readings.append(poll)
        finally:
            device.close()
            sim.close()
    first, again, second = readings[0]
    assert first == again and first != second
    assert readings[1] == readings[0]
    assert 0.0 < np.linalg.norm(np.subtract(first[:3], (0.0, 0.0, -200.0))) < 3.0

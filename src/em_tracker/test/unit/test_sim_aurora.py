"""Simulated Aurora behaviour checked with raw bytes (no ndicapi) and its trajectory."""

from __future__ import annotations

import os
import random
import select
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from em_tracker.hw import combined_api as api
from em_tracker.hw.sim_aurora import (
    circle_trajectory,
    pose_matrix,
    ScriptedTrajectory,
    SimAurora,
    SimGroundTruth,
)

SETUP = ('INIT:', 'PINIT:0A', 'PENA:0AD', 'TSTART:')


def _send(fd: int, frame: bytes, timeout: float = 2.0) -> bytes:
    """Write raw bytes; return the text reply (up to its CR), or what came before the timeout."""
    os.write(fd, frame)
    out = b''
    deadline = time.monotonic() + timeout
    while not out.endswith(b'\r') and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.05)[0]:
            out += os.read(fd, 4096)
    return out


def _exchange(fd: int, command: str, timeout: float = 2.0) -> bytes:
    return _send(fd, api.encode_command(command), timeout)


def _open(sim: SimAurora) -> int:
    import tty
    fd = os.open(sim.port, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    return fd


@pytest.fixture
def raw():
    sim = SimAurora().start()
    fd = _open(sim)
    yield sim, fd
    os.close(fd)
    sim.close()


@pytest.fixture
def tracking(raw):
    sim, fd = raw
    for command in SETUP:
        assert _exchange(fd, command) == b'OKAYA896\r'
    return sim, fd


def test_power_on_requires_init(raw):
    _sim, fd = raw
    assert api.decode_text_reply(_exchange(fd, 'PHSR:02')) == 'ERROR10'
    assert _exchange(fd, 'INIT:') == b'OKAYA896\r'


def test_bad_command_crc_answered_error04(raw):
    sim, fd = raw
    os.write(fd, b'INIT:0000\r')
    time.sleep(0.05)
    assert os.read(fd, 100).startswith(b'ERROR04')
    assert sim.stats.bad_command_crc == 1


def test_tracking_mode_rules(raw):
    _sim, fd = raw
    _exchange(fd, 'INIT:')
    assert api.decode_text_reply(_exchange(fd, 'TSTOP:')) == 'ERROR0C'
    assert api.decode_text_reply(_exchange(fd, 'PENA:0AX')) == 'ERROR09'
    _exchange(fd, 'PINIT:0A')
    _exchange(fd, 'PENA:0AD')
    assert _exchange(fd, 'TSTART:') == b'OKAYA896\r'
    assert api.decode_text_reply(_exchange(fd, 'PINIT:0A')) == 'ERROR0C'
    assert api.decode_text_reply(_exchange(fd, 'TX:0001')).startswith('010A')


def test_garbage_and_no_reply_faults(raw):
    sim, fd = raw
    sim.inject(garbage=1)
    assert _exchange(fd, 'INIT:') == sim.faults.garbage_bytes + b'OKAYA896\r'
    sim.inject(no_reply=1)
    assert _exchange(fd, 'INIT:', timeout=0.2) == b''
    with pytest.raises(ValueError, match='unknown fault'):
        sim.inject(smoke=True)


@pytest.mark.parametrize('frame,reply', [
    (b'TX:ZZZZ8848\r', b'ERROR23CA42\r'),  # reply option not hex: parameter out of range
    (b'BX:ZZZZ493F\r', b'ERROR23CA42\r'),
    (b'TX:G001B701\r', b'ERROR23CA42\r'),
    (b'TX:-0016F1C\r', b'ERROR23CA42\r'),  # (int(..., 16) alone would take the sign)
    (b'TX:0x01159A\r', b'ERROR23CA42\r'),
    (b'TX\r', b'ERROR016BC2\r'),  # no ':' or space after the name: not a command
    (b'TX:ZZZZ0000\r', b'ERROR046802\r'),  # wrong CRC
])
def test_malformed_tracking_command_gets_its_error_and_the_device_keeps_answering(
        tracking, frame, reply):
    sim, fd = tracking
    assert _send(fd, frame) == reply
    assert api.decode_text_reply(_exchange(fd, 'TX:0001')).startswith('010A')
    assert sim.stats.frames_served == 1 and sim.stats.handler_errors == []


def test_malformed_port_handles_and_srom_writes_get_their_errors(raw):
    sim, fd = raw
    _exchange(fd, 'INIT:')
    for command in ('PINIT:+A', 'PINIT: A', 'PINIT:0', 'PINIT:', 'PENA:0x'):
        assert api.decode_text_reply(_exchange(fd, command)) == 'ERROR08', command
    _exchange(fd, 'PINIT:0A')
    image = '00' * 64
    for command in (f'PVWR:0A+040{image}', f'PVWR:0A-040{image}', f'PVWR:0A0000{image[:-2]} 0',
                    f'PVWR:0A0400{image}', f'PVWR:0A0000{image}0'):
        assert api.decode_text_reply(_exchange(fd, command)) == 'ERROR23', command
    assert _exchange(fd, f'PVWR:0A03C0{"AB" * 64}') == b'OKAYA896\r'
    assert bytes(sim.ports[0x0A].srom[960:]) == b'\xab' * 64
    assert len(sim.ports[0x0A].srom) == 1024 and sim.stats.handler_errors == []


def _fuzz_lines(rng: random.Random, count: int) -> list[bytes]:
    """Garbage bytes, and CRC-correct or space-separated commands with random parameters,
    with the start-up sequence now and then so that tracking commands are reached too."""
    names = ('INIT', 'RESET', 'BEEP', 'VER', 'COMM', 'PHSR', 'PINIT', 'PENA', 'PDIS', 'PVWR',
             'PHF', 'TSTART', 'TSTOP', 'TX', 'BX', 'GX', 'Q')
    alphabet = '0123456789ABCDEFabcdefGZ:+-_ x\x00\n\t\x7f'
    lines = []
    for i in range(count):
        if i % 40 == 0:
            lines += [api.encode_command(c)[:-1] for c in SETUP]
        if rng.random() < 0.3:
            lines.append(bytes(rng.randrange(256) for _ in range(rng.randrange(40)))
                         .replace(b'\r', b''))
            continue
        name = rng.choice(names)
        params = ''.join(rng.choice(alphabet)
                         for _ in range(rng.choice((0, 1, 2, 3, 4, 5, 134, rng.randrange(150)))))
        if rng.random() < 0.5:
            lines.append(api.encode_command(f'{name}:{params}')[:-1])
        else:
            lines.append(f'{name} {params}'.encode())
    return lines


def test_fuzz_of_garbage_lines_then_a_valid_command_gets_a_valid_reply(raw):
    sim, fd = raw
    out = b''
    for line in _fuzz_lines(random.Random(0), 400):
        os.write(fd, line + b'\r')
        while select.select([fd], [], [], 0)[0]:
            out += os.read(fd, 4096)
    os.write(fd, b'INIT:E3A5\r')
    # Replies can sit in the kernel's pty buffers for a while: read until the device has
    # handled the INIT and nothing more came for 0.5 s.
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        if select.select([fd], [], [], 0.5)[0]:
            out += os.read(fd, 4096)
        elif sim.stats.commands[-1] == 'INIT:E3A5':
            break
    assert out.endswith(b'OKAYA896\r')
    assert api.decode_text_reply(_exchange(fd, 'PHSR:00')) == '010A001'
    assert sim.stats.handler_errors == []  # every line was answered by validation, not a crash


def test_a_handler_that_raises_is_answered_error01_and_the_device_keeps_serving():
    failures = [RuntimeError('pose source failed')]

    def pose_source(t_s):
        if failures:
            raise failures.pop()
        return circle_trajectory(t_s)

    sim = SimAurora(pose_source).start()
    fd = _open(sim)
    try:
        for command in SETUP:
            _exchange(fd, command)
        assert _exchange(fd, 'TX:0001') == b'ERROR016BC2\r'
        assert sim.stats.handler_errors == [
            "b'TX:0001031A': RuntimeError: pose source failed"]
        assert api.decode_text_reply(_exchange(fd, 'TX:0001')).startswith('010A')
    finally:
        os.close(fd)
        sim.close()


def test_trajectory_interpolates_and_loops():
    traj = ScriptedTrajectory([0.0, 1.0, 2.0], [[0, 0, 0], [10, 0, 0], [10, 10, 0]],
                              [[1, 0, 0, 0], [0, 0, 0, 1], [0, 0, 0, 1]], loop=True)
    pos, quat = traj(0.5)
    assert pos.tolist() == [5.0, 0.0, 0.0]
    assert quat == pytest.approx([math_sqrt_half(), 0, 0, math_sqrt_half()])
    assert traj(2.5)[0].tolist() == pytest.approx(traj(0.5)[0].tolist())
    with pytest.raises(ValueError, match='strictly increasing'):
        ScriptedTrajectory([0.0, 0.0], [[0, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match='shape'):
        ScriptedTrajectory([0.0], [[0, 0]])


def math_sqrt_half() -> float:
    return float(np.sqrt(0.5))


# ---------------------------------------------------------------- hidden ground truth
S = math_sqrt_half()
#: phantom turned +90 deg about the tracker's z, its origin at (100, 0, -200) mm
PLACEMENT = np.array([[0.0, -1.0, 0.0, 100.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, -200.0],
                      [0.0, 0.0, 0.0, 1.0]])
#: sensor z along the shaft (tip +y -> sensor +z: +90 deg about x), tip 10 mm ahead of it
MOUNTING = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 10.0],
                     [0.0, 0.0, 0.0, 1.0]])


def test_default_truth_passes_the_pose_source_through():
    assert SimGroundTruth().passthrough and SimAurora().truth.passthrough
    assert not SimGroundTruth(position_noise_mm=0.1).passthrough
    assert not SimGroundTruth(tip_in_sensor=MOUNTING).passthrough


def test_reading_is_the_sensor_pose_in_the_tracker_frame():
    truth = SimGroundTruth(phantom_in_tracker=PLACEMENT, tip_in_sensor=MOUNTING)
    pos, quat = truth.reading([10.0, 20.0, 30.0], [1.0, 0.0, 0.0, 0.0])
    # sensor 10 mm behind the tip along the tip's +y: (10, 10, 30) in the phantom, turned
    # -90 deg about x; then the placement: (-10, 10, 30) + (100, 0, -200), Rz(90) Rx(-90)
    assert pos == pytest.approx([90.0, 10.0, -170.0], abs=1e-12)
    assert quat == pytest.approx([0.5, -0.5, -0.5, 0.5], abs=1e-12)
    assert truth.registration_m() == pytest.approx(np.array(
        [[0, 1, 0, 0.0], [-1, 0, 0, 0.1], [0, 0, 1, 0.2], [0, 0, 0, 1]]), abs=1e-12)
    assert truth.tool_transform_m()[:3, 3] == pytest.approx([0.0, 0.0, 0.01], abs=1e-15)
    # the tip, back from the reading with the true transforms (what calibration recovers)
    tip = truth.registration_m() @ pose_matrix(pos * 1e-3, quat) @ truth.tool_transform_m()
    assert tip[:3, 3] == pytest.approx([0.01, 0.02, 0.03], abs=1e-12)
    assert tip[:3, :3] == pytest.approx(np.eye(3), abs=1e-12)


def test_noise_has_the_stated_rms():
    truth = SimGroundTruth(phantom_in_tracker=PLACEMENT, tip_in_sensor=MOUNTING,
                           position_noise_mm=0.48, orientation_noise_deg=0.3)
    clean_pos, clean_quat = truth.reading([10.0, 20.0, 30.0], [1.0, 0.0, 0.0, 0.0])
    clean = pose_matrix(clean_pos, clean_quat)[:3, :3]
    rng = np.random.default_rng(0)
    pos_err, ang_err = [], []
    for _ in range(2000):
        pos, quat = truth.reading([10.0, 20.0, 30.0], [1.0, 0.0, 0.0, 0.0], rng)
        pos_err.append(np.linalg.norm(pos - clean_pos))
        ang_err.append(Rotation.from_matrix(pose_matrix(pos, quat)[:3, :3] @ clean.T)
                       .magnitude())
    # 2000 draws: the RMS estimates have a ~1 % standard error; 5 % is over 5 of them
    assert np.sqrt(np.mean(np.square(pos_err))) == pytest.approx(0.48, rel=0.05)
    assert np.degrees(np.sqrt(np.mean(np.square(ang_err)))) == pytest.approx(0.3, rel=0.05)


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'phantom_in_tracker': np.eye(3)}, 'phantom_in_tracker must be a rigid 4x4'),
    ({'tip_in_sensor': np.diag([1.0, 1.0, -1.0, 1.0])}, 'tip_in_sensor must be a rigid 4x4'),
    ({'tip_in_sensor': np.full((4, 4), np.nan)}, 'tip_in_sensor must be a rigid 4x4'),
    ({'position_noise_mm': -0.1}, r'position_noise_mm must be in \[0, 10\], found -0.1'),
    ({'orientation_noise_deg': float('inf')}, 'orientation_noise_deg must be in'),
    ({'seed': -1}, 'seed must be a non-negative integer, found -1'),
])
def test_bad_truth_is_refused_with_the_field_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SimGroundTruth(**kwargs)


def test_truth_placements_are_read_only_copies():
    placement = PLACEMENT.copy()
    truth = SimGroundTruth(phantom_in_tracker=placement)
    placement[0, 3] = 0.0
    assert truth.phantom_in_tracker[0, 3] == 100.0
    with pytest.raises(ValueError, match='read-only'):
        truth.phantom_in_tracker[0, 3] = 1.0

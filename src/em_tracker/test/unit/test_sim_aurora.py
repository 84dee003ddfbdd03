"""Simulated Aurora behaviour checked with raw bytes (no ndicapi) and its trajectory."""

from __future__ import annotations

import os
import random
import select
import time

import numpy as np
import pytest

from em_tracker.hw import combined_api as api
from em_tracker.hw.sim_aurora import circle_trajectory, ScriptedTrajectory, SimAurora

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

"""Simulated Aurora behaviour checked with raw bytes (no ndicapi) and its trajectory."""

from __future__ import annotations

import os
import select
import time

import numpy as np
import pytest

from em_tracker.hw import combined_api as api
from em_tracker.hw.sim_aurora import ScriptedTrajectory, SimAurora


def _exchange(fd: int, command: str, timeout: float = 2.0) -> bytes:
    os.write(fd, api.encode_command(command))
    out = b''
    deadline = time.monotonic() + timeout
    while not out.endswith(b'\r') and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.05)[0]:
            out += os.read(fd, 4096)
    return out


@pytest.fixture
def raw():
    sim = SimAurora().start()
    import tty
    fd = os.open(sim.port, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    yield sim, fd
    os.close(fd)
    sim.close()


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

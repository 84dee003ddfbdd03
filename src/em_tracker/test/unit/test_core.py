"""Core logic: quaternion order, units, registration, validation, frames, diagnostics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from em_tracker.core.config import TrackerConfig
from em_tracker.core.pose import (
    convert_sample,
    matrix_to_quat_xyzw,
    mm_to_m,
    ndi_quat_to_ros,
    quat_xyzw_to_matrix,
    Registration,
)
from em_tracker.core.tracking import FrameCounter, Level, LinkState, PortFlags, TrackerHealth


def test_quaternion_reorder_and_units():
    assert ndi_quat_to_ros([0.1, 0.2, 0.3, 0.4]).tolist() == [0.2, 0.3, 0.4, 0.1]
    assert mm_to_m([1000.0, -250.0, 1.0]).tolist() == [1.0, -0.25, 0.001]


def test_matrix_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = -q if q[3] < 0 else q
        assert matrix_to_quat_xyzw(quat_xyzw_to_matrix(q)) == pytest.approx(q, abs=1e-12)


def test_registration_forms_agree():
    s = math.sqrt(0.5)
    from_quat = Registration.from_flat([1, 2, 3, 0, 0, s, s])
    from_matrix = Registration.from_flat([0, -1, 0, 1, 1, 0, 0, 2, 0, 0, 1, 3, 0, 0, 0, 1])
    assert from_quat.matrix == pytest.approx(from_matrix.matrix, abs=1e-12)
    pos, quat = from_quat.apply(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))
    assert pos.tolist() == pytest.approx([1.0, 3.0, 3.0])
    assert quat == pytest.approx([0.0, 0.0, s, s])


@pytest.mark.parametrize('values,match', [
    ([1, 2, 3], '16 values'), ([0, 0, 0, 0, 0, 0, 3], 'unit norm'),
    ([2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1], 'orthonormal'),
    ([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 1, 0, 0, 1], 'last row'),
    ([float('nan')] * 16, 'finite'),
])
def test_registration_rejects(values, match):
    with pytest.raises(ValueError, match=match):
        Registration.from_flat(values)


def test_registration_flat_round_trip():
    reg = Registration.from_flat([0.1, -0.2, 0.3, 0.0, 0.0, -math.sqrt(0.5), math.sqrt(0.5)])
    flat = reg.to_flat()
    assert len(flat) == 7 and flat[6] >= 0.0
    assert Registration.from_flat(flat).matrix == pytest.approx(reg.matrix, abs=1e-12)
    assert Registration.identity().to_flat() == [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]


def test_convert_sample_scales_and_reorders():
    pose = convert_sample((1.0, 0.0, 0.0, 0.0), (100.0, -50.0, -300.0), 0.5,
                          Registration.identity(), max_abs_position_m=1.0)
    assert pose.position_m.tolist() == pytest.approx([0.1, -0.05, -0.3])
    assert pose.quat_xyzw.tolist() == pytest.approx([0.0, 0.0, 0.0, 1.0])
    assert pose.rms_error_m == pytest.approx(5e-4)


@pytest.mark.parametrize('quat,pos,err,match', [
    ((1, 0, 0, 0), (float('nan'), 0, 0), 0.1, 'finite'),
    ((1, 0, 0, 0), (0, 0, 0), float('inf'), 'finite'),
    ((0.5, 0, 0, 0), (0, 0, 0), 0.1, 'unit quaternion'),
    ((1, 0, 0, 0), (0, 0, 1500.0), 0.1, r'<= 1.0 m'),
    ((1, 0, 0, 0), (0, 0, 0), -1.0, 'non-negative'),
])
def test_convert_sample_rejects(quat, pos, err, match):
    with pytest.raises(ValueError, match=match):
        convert_sample(quat, pos, err, Registration.identity(), max_abs_position_m=1.0)


def test_frame_counter():
    fc = FrameCounter()
    assert fc.update(10) and not fc.update(10) and fc.update(11) and fc.update(15)
    assert (fc.received, fc.repeated, fc.dropped) == (3, 1, 3)
    assert fc.update(0xFFFFFFFF) and fc.update(0)  # backwards jump then wrap-around
    assert fc.dropped == 3
    fc.reset()
    assert fc.update(3) and fc.dropped == 3


def test_port_flags():
    flags = PortFlags.decode(0x1F1)
    assert flags.occupied and flags.enabled and flags.out_of_volume
    assert flags.partially_out_of_volume and flags.broken_coil
    assert PortFlags.decode(0x31).problems() == []
    assert PortFlags.decode(0x11).problems() == ['port not enabled']


def test_health_levels():
    h = TrackerHealth()
    assert h.level(0.0, 0.5)[0] is Level.ERROR
    h.link = LinkState.TRACKING
    assert h.level(0.0, 0.5)[0] is Level.STALE
    h.last_frame_time, h.port_status, h.tool_visible = 1.0, 0x31, True
    assert h.level(1.1, 0.5) == (Level.OK, 'tracking')
    assert h.level(2.0, 0.5)[0] is Level.STALE
    h.port_status = 0xB1
    assert h.level(1.1, 0.5) == (Level.WARN, 'partially out of volume')
    h.tool_visible, h.port_status = False, 0x71
    assert h.level(1.1, 0.5) == (Level.WARN, 'tool MISSING (out of volume)')
    h.port_status = 0x131
    assert h.level(1.1, 0.5) == (Level.ERROR, 'sensor coil broken')
    h.link = LinkState.STOPPED
    assert h.level(1.1, 0.5)[0] is Level.STALE
    assert set(h.values()) >= {'frames_dropped', 'port_status', 'reconnects'}


@pytest.mark.parametrize('kwargs,match', [
    ({'baud': 1000}, 'baud'), ({'priority': 'Q'}, 'priority'), ({'tool_handle': -1}, 'tool'),
    ({'rate_hz': float('nan')}, 'rate_hz'), ({'srom_files': ('0A/x.rom',)}, 'srom_files'),
    ({'reconnect_initial_s': 2.0, 'reconnect_max_s': 1.0}, 'reconnect_max_s'),
    ({'max_consecutive_errors': 0}, 'max_consecutive_errors'), ({'port': ''}, 'port'),
])
def test_config_rejects(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrackerConfig(**kwargs)

"""Host adapter <-> simulated regulator bank on a python-can virtual bus (never vcan/udp)."""

import itertools
import math

import can
import numpy as np
import pytest

from pam_controller.core.supervisor import BankMode
from pam_controller.errors import DeviceUnavailableError
from pam_controller.hw import can_protocol as proto
from pam_controller.hw import sim_regulators
from pam_controller.hw.regulator_bank import BankFeedback, CanRegulatorBank, LinkConfig
from pam_controller.hw.sim_regulators import SimRegulatorBank, SimRegulatorConfig

_channels = itertools.count()
DT = 0.01


@pytest.fixture
def rig():
    channel = f'pam_test_{next(_channels)}'
    sim = SimRegulatorBank(SimRegulatorConfig(channel=channel, time_constant_s=0.08), seed=7)
    host = CanRegulatorBank('virtual', channel)
    host.open()
    yield sim, host
    host.close()
    sim.stop()


def run(sim, host, seconds, setpoints=None, mode=BankMode.RUN, heartbeat=True):
    """Host sends (setpoints every step, heartbeat every 0.1 s), sim steps; returns feedback."""
    fb = BankFeedback()
    fb.statuses = []
    for k in range(round(seconds / DT)):
        if heartbeat and k % 10 == 0:
            host.send_heartbeat(mode)
        if setpoints is not None:
            host.send_setpoints(setpoints)
        sim.step(DT)
        got = host.poll()
        fb.measured.extend(got.measured)
        fb.status = got.status or fb.status
        if got.status is not None:
            fb.statuses.append(got.status)
        fb.bad_frames += got.bad_frames
        fb.last_error = got.last_error or fb.last_error
    return fb


def test_first_order_response_matches_exact_solution(rig):
    sim, host = rig
    fb = run(sim, host, 0.08, setpoints=[200e3, 100e3, 0.0, 50e3])
    # The setpoint frame is read in the first step, so after n steps p = sp (1 - e^(-n dt/tau)).
    expected = np.array([200e3, 100e3, 0.0, 50e3]) * (1 - math.exp(-0.08 / 0.08))
    np.testing.assert_allclose(fb.measured[-1], expected, atol=60.0)
    fb = run(sim, host, 1.0, setpoints=[200e3, 100e3, 0.0, 50e3])
    np.testing.assert_allclose(fb.measured[-1], [200e3, 100e3, 0.0, 50e3], atol=60.0)
    assert fb.status.state is proto.BankState.ACTIVE and fb.status.faults == frozenset()
    assert len(fb.measured) == 100 and host.lost_frames == 0


def test_idle_and_vent_modes_vent(rig):
    sim, host = rig
    run(sim, host, 0.5, setpoints=[200e3] * 4)
    fb = run(sim, host, 0.8, setpoints=[200e3] * 4, mode=BankMode.VENT)
    assert np.max(fb.measured[-1]) < 1e3 and fb.status.state is proto.BankState.VENTING
    fb = run(sim, host, 0.5, setpoints=[200e3] * 4, mode=BankMode.IDLE)
    assert fb.status.state is proto.BankState.READY


def test_pressure_saturates_at_supply_and_flags_supply_low(rig):
    sim, host = rig
    fb = run(sim, host, 1.0, setpoints=[400e3, 0.0, 0.0, 0.0])
    assert fb.measured[-1][0] == pytest.approx(350e3, abs=60.0)
    assert 'FAULT_SUPPLY_LOW' in fb.status.faults


def test_setpoint_above_bank_limit_is_clipped_and_flagged():
    channel = f'pam_test_{next(_channels)}'
    sim = SimRegulatorBank(SimRegulatorConfig(channel=channel, max_setpoint_pa=250e3))
    host = CanRegulatorBank('virtual', channel)
    host.open()
    try:
        fb = run(sim, host, 1.0, setpoints=[300e3, 0.0, 0.0, 0.0])
        assert fb.measured[-1][0] == pytest.approx(250e3, abs=60.0)
        assert 'FAULT_OVERPRESSURE' in fb.status.faults
    finally:
        host.close()
        sim.stop()


def test_bank_vents_on_host_heartbeat_timeout_and_recovers(rig):
    sim, host = rig
    run(sim, host, 0.5, setpoints=[150e3] * 4)
    fb = run(sim, host, 1.0, setpoints=[150e3] * 4, heartbeat=False)
    assert 'FAULT_HOST_TIMEOUT' in fb.status.faults
    assert fb.status.state is proto.BankState.VENTING
    assert np.max(fb.measured[-1]) < 5e3
    fb = run(sim, host, 1.0, setpoints=[150e3] * 4)
    assert fb.status.faults == frozenset() and fb.status.state is proto.BankState.ACTIVE
    np.testing.assert_allclose(fb.measured[-1], [150e3] * 4, atol=60.0)


def test_stuck_regulator_detected_with_channel_mask(rig):
    sim, host = rig
    run(sim, host, 1.0, setpoints=[100e3] * 4)
    sim.set_stuck(2)
    fb = run(sim, host, 1.0, setpoints=[200e3] * 4)
    assert fb.status.state is proto.BankState.FAULT
    assert 'FAULT_STUCK' in fb.status.faults and fb.status.channel_fault_mask == 0b0100
    assert fb.measured[-1][2] == pytest.approx(100e3, abs=100.0)
    assert fb.measured[-1][0] == pytest.approx(200e3, abs=100.0)
    sim.set_stuck(2, False)
    fb = run(sim, host, 0.3, setpoints=[200e3] * 4, mode=BankMode.CLEAR_FAULTS)
    fb = run(sim, host, 0.3, setpoints=[200e3] * 4)
    assert fb.status.channel_fault_mask == 0 and fb.status.state is proto.BankState.ACTIVE


def test_a_stuck_regulator_asked_for_what_it_holds_never_becomes_observable(rig):
    sim, host = rig
    run(sim, host, 1.0, setpoints=[100e3] * 4)
    sim.set_stuck(1)
    # within stuck_detect_pa (20 kPa) of the held 100 kPa: delivered, nothing to see
    fb = run(sim, host, 2.0, setpoints=[100e3, 115e3, 100e3, 100e3])
    assert sim.stuck_error_at(1) is None and sim.stuck_observable_at(1) is None
    assert fb.status.faults == frozenset() and fb.status.channel_fault_mask == 0
    assert fb.measured[-1][1] == pytest.approx(100e3, abs=100.0)
    # a healthy channel's lag (a 100 kPa step) is no stuck channel's observable time
    run(sim, host, 1.0, setpoints=[200e3, 85e3, 100e3, 100e3])
    assert sim.stuck_error_at(1) is None and sim.stuck_observable_at(1) is None
    assert [sim.stuck_observable_at(c) for c in range(4)] == [None] * 4


def test_a_stuck_regulator_is_observable_from_the_start_of_the_error_the_bank_flags(rig):
    sim, host = rig
    run(sim, host, 1.0, setpoints=[100e3] * 4)
    sim.set_stuck(3)
    run(sim, host, 1.0, setpoints=[100e3] * 4)
    # 50 kPa away for 0.3 s (< stuck_detect_s): an error, not observable (a healthy lag looks so)
    moved = sim.time_s + DT  # (the setpoint is read in the next step)
    run(sim, host, 0.3, setpoints=[100e3, 100e3, 100e3, 150e3])
    assert sim.stuck_error_at(3) == pytest.approx(moved, abs=1e-9)
    run(sim, host, 0.5, setpoints=[100e3] * 4)
    assert sim.stuck_observable_at(3) is None and 'FAULT_STUCK' not in sim.faults
    # 50 kPa away and kept there: observable from when it moved, flagged stuck_detect_s later
    moved = sim.time_s + DT
    run(sim, host, 0.45, setpoints=[100e3, 100e3, 100e3, 50e3])
    # (known once the error has lasted stuck_detect_s, when the bank flags it)
    assert sim.stuck_observable_at(3) is None and 'FAULT_STUCK' not in sim.faults
    fb = run(sim, host, 0.3, setpoints=[100e3, 100e3, 100e3, 50e3])
    assert sim.stuck_observable_at(3) == pytest.approx(moved, abs=1e-9)
    assert sim.stuck_error_at(3) < moved  # (the first, short error stays the first)
    assert 'FAULT_STUCK' in fb.status.faults and fb.status.channel_fault_mask == 0b1000
    assert [sim.stuck_observable_at(c) for c in range(3)] == [None] * 3
    # frozen afresh: the records start afresh
    sim.set_stuck(3, False)
    assert sim.stuck_observable_at(3) == pytest.approx(moved, abs=1e-9)
    sim.set_stuck(3)
    assert sim.stuck_error_at(3) is None and sim.stuck_observable_at(3) is None
    with pytest.raises(ValueError, match=r'channel must be in 0\.\.3, found 4'):
        sim.stuck_observable_at(4)


def test_bus_silence_then_recovery(rig):
    sim, host = rig
    run(sim, host, 0.2, setpoints=[50e3] * 4)
    sim.set_silent(True)
    fb = run(sim, host, 0.3, setpoints=[50e3] * 4)
    assert fb.measured == [] and fb.status is None
    sim.set_silent(False)
    fb = run(sim, host, 0.3, setpoints=[50e3] * 4)
    assert len(fb.measured) == 30


def test_garbage_from_bank_is_counted_never_raised_nor_trusted(rig):
    sim, host = rig
    run(sim, host, 1.0, setpoints=[120e3] * 4)
    sim.send_garbage(300)
    fb = run(sim, host, 0.05, setpoints=[120e3] * 4)
    assert fb.bad_frames > 100
    assert host.bad_frames_total == fb.bad_frames
    for p in fb.measured:
        np.testing.assert_allclose(p, [120e3] * 4, atol=100.0)


def test_garbage_from_host_is_flagged_by_the_bank(rig):
    sim, host = rig
    run(sim, host, 1.0, setpoints=[10e3] * 4)
    bus = can.Bus(interface='virtual', channel=host.channel)
    try:
        bus.send(can.Message(arbitration_id=0x200, data=b'\xff' * 8, is_extended_id=False))
        bus.send(can.Message(arbitration_id=0x700, data=b'\x01', is_extended_id=False))
    finally:
        bus.shutdown()
    fb = run(sim, host, 0.2, setpoints=[10e3] * 4)
    assert sim.bad_frames_received == 2
    flagged = ['FAULT_BAD_FRAME' in st.faults for st in fb.statuses]
    assert flagged == [True, False]      # reported once, in the next status, then cleared
    np.testing.assert_allclose(fb.measured[-1], [10e3] * 4, atol=100.0)


def test_lost_measured_frames_are_counted_from_the_counter(rig):
    sim, host = rig
    run(sim, host, 0.1, setpoints=[0.0] * 4)
    for _ in range(5):   # the bank sends 5 frames the host never reads
        sim.step(DT)
    while host._bus.recv(timeout=0.0) is not None:
        pass
    run(sim, host, 0.05, setpoints=[0.0] * 4)
    assert host.lost_frames == 5


def test_open_failure_and_send_when_closed_raise_device_unavailable():
    bank = CanRegulatorBank('no_such_interface', 'x')
    with pytest.raises(DeviceUnavailableError, match='expected to open CAN no_such_interface:x'):
        bank.open()
    with pytest.raises(DeviceUnavailableError, match='found it closed'):
        bank.send_setpoints([0.0] * 4)
    assert bank.poll().measured == []


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'channel': ''}, 'channel must be'),
    ({'bitrate': 5}, 'bitrate must be in'),
    ({'heartbeat_period_s': 0.5}, 'heartbeat_period_s must be in'),
    ({'reconnect_initial_s': 2.0, 'reconnect_max_s': 1.0}, 'reconnect_max_s must be in'),
])
def test_bad_link_config_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LinkConfig(**kwargs)


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'time_constant_s': 0.0}, 'time_constant_s must be in'),
    ({'supply_pressure_pa': 500e3}, 'supply_pressure_pa must be in'),
    ({'channel': ''}, 'channel must be'),
])
def test_bad_sim_config_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SimRegulatorConfig(**kwargs)


def test_sim_thread_runs_on_wall_clock_and_main_exits(capsys):
    channel = f'pam_test_{next(_channels)}'
    sim = SimRegulatorBank(SimRegulatorConfig(channel=channel))
    host = CanRegulatorBank('virtual', channel)
    host.open()
    sim.start()
    try:
        import time
        deadline = time.monotonic() + 2.0
        got = []
        while time.monotonic() < deadline and len(got) < 10:
            got.extend(host.poll().measured)
            time.sleep(0.01)
        assert len(got) >= 10
    finally:
        sim.stop()
        host.close()
    assert sim_regulators.main(['--channel', channel, '--duration', '1.0']) == 0
    assert f'sim_regulators on virtual:{channel}' in capsys.readouterr().out

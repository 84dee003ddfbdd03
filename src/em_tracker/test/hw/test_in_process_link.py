"""The in-process link (``link: in_process``): the simulated Aurora answers in the caller's
thread, and the host reads exactly what ndicapi reads over the pty."""

from __future__ import annotations

import numpy as np
import pytest

from em_tracker.core.config import TrackerConfig
from em_tracker.core.errors import DeviceDisconnected, DeviceError, DeviceTimeout, ProtocolError
from em_tracker.hw.aurora import AuroraSettings, InProcessAurora, NdiAurora
from em_tracker.hw.sim_aurora import in_process_device, SimAurora, SimGroundTruth
from em_tracker.nodes.aurora_node import default_device

HANDLE = 0x0A


class _Poses:
    """A pose source that draws a new pose at every frame (positions across the volume,
    sub-millimetre ones too, random orientations)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        pos = self.rng.uniform(-450.0, 450.0, 3) * self.rng.choice([1.0, 1e-2, 1e-3])
        quat = self.rng.normal(size=4)
        return pos, quat / np.linalg.norm(quat)


def _device(tmp_path, name: str, seed: int) -> SimAurora:
    clock = [0.0]
    sim = SimAurora(_Poses(seed), link_path=str(tmp_path / name), clock=lambda: clock[0],
                    truth=SimGroundTruth(position_noise_mm=0.5, orientation_noise_deg=0.3,
                                         seed=seed))
    sim.__dict__['test_clock'] = clock
    return sim.start()


def test_the_in_process_link_reads_what_ndicapi_reads_over_the_pty(tmp_path) -> None:
    serial_sim, direct_sim = _device(tmp_path, 'serial', 3), _device(tmp_path, 'direct', 3)
    serial = NdiAurora(AuroraSettings(port=serial_sim.port))
    direct = InProcessAurora(AuroraSettings(port=direct_sim.port))
    try:
        assert serial.connect() == direct.connect() == [HANDLE]
        for k in range(1, 400):
            for sim in (serial_sim, direct_sim):
                sim.__dict__['test_clock'][0] = k / 40.0
            a, b = serial.read(), direct.read()
            assert a.tools == b.tools  # every value to the bit, statuses, frame numbers
            assert a.system_status == b.system_status
        serial_sim.inject(missing=True)
        direct_sim.inject(missing=True)
        a, b = serial.read(), direct.read()
        assert a.tools == b.tools and not b.tools[0].visible
    finally:
        serial.close()
        direct.close()
        names = [[c.split(':')[0] for c in sim.stats.commands] for sim in (serial_sim,
                                                                            direct_sim)]
        serial_sim.close()
        direct_sim.close()
    assert names[0] == names[1]  # the same start-up, polls and TSTOP
    assert names[1][:2] == ['INIT', 'COMM'] and names[1][-1] == 'TSTOP'


def test_the_link_finds_the_device_by_its_port_while_it_runs(tmp_path) -> None:
    sim = _device(tmp_path, 'found', 0)
    port = sim.port
    assert in_process_device(port) is sim
    sim.close()
    assert in_process_device(port) is None
    with pytest.raises(DeviceDisconnected, match='no simulated Aurora'):
        InProcessAurora(AuroraSettings(port=port)).connect()


@pytest.mark.parametrize(('fault', 'exc'), [
    ({'bad_crc': 1}, ProtocolError),
    ({'garbage': 1}, ProtocolError),
    ({'tracking_error': 0x0C}, DeviceError),
    ({'no_reply': 1}, DeviceTimeout),
])
def test_faults_are_the_same_exceptions_as_over_the_pty(tmp_path, fault, exc) -> None:
    sim = _device(tmp_path, 'faults', 0)
    device = InProcessAurora(AuroraSettings(port=sim.port))
    try:
        device.connect()
        sim.inject(**fault)
        with pytest.raises(exc) as info:
            device.read()
        if exc is DeviceError:
            assert info.value.code == 0x0C
        sim.clear_faults()
        assert device.read().tools[0].visible
        sim.disconnect()
        with pytest.raises(DeviceDisconnected):
            device.read()
        sim.reconnect()
        assert device.connect() == [HANDLE]
    finally:
        device.close()
        sim.close()


def test_the_node_config_picks_the_link(tmp_path) -> None:
    config = TrackerConfig(port=str(tmp_path / 'x'), link='in_process', isolate_device=True)
    assert isinstance(default_device(config), InProcessAurora)
    assert isinstance(default_device(TrackerConfig(port='/dev/ttyUSB0', isolate_device=False)),
                      NdiAurora)
    with pytest.raises(ValueError, match="link must be 'serial' or 'in_process'"):
        TrackerConfig(port='/dev/ttyUSB0', link='usb')
    with pytest.raises(ValueError, match='use_bx must be false'):
        TrackerConfig(port='/dev/ttyUSB0', link='in_process', use_bx=True)

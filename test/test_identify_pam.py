"""identify_pam: the excitation on the simulated bench, the fit of its bag, bad input.

The bench runs on a lockstep rig (phantom with ``fixture: bench``, aurora, pam_controller) on
the test's ROS domain (``ROS_DOMAIN_ID``). Expected values are bounds, not last-bit numbers:
the fit's least squares may end a few ulps apart on another machine.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cgail_bags.bagio import BagWriter, TYPESTORE
from cgail_bags.qos import SENSOR
from cgail_rig.identify_pam import identify_sim, main, pam_config_file
from pam_controller.core import identification as idf

T = TYPESTORE.types
#: One sweep cycle of the full amplitude per axis at 100 kPa/s, no multisine: 18 s of rig time.
QUICK = idf.ExcitationConfig(levels=(1.0,), sweep_rate_pa_s=100e3, multisine_periods=0,
                             rest_s=1.0, settle_s=0.5)


def test_quick_bench_identification_halves_the_nominal_error(tmp_path, monkeypatch) -> None:
    """On the bench, the true plant of seed 1: the identified model's RMS bend error is at most
    half the nominal model's (the issue's bar), and the YAML it writes is a valid
    pam_controller parameter file holding the identified model."""
    from pam_controller.nodes.pam_node import build_settings, PARAMETERS

    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)  # the test run holds its own: pick one
    result = identify_sim(tmp_path, plant_seed=1, excitation=QUICK)
    e = result.errors
    assert e['identified']['all'] <= 0.5 * e['nominal']['all'], e
    params = yaml.safe_load((tmp_path / 'pam_identified.yaml').read_text())
    values = params['pam_controller']['ros__parameters']
    template = yaml.safe_load(pam_config_file().read_text())['pam_controller']
    assert set(values) == set(template['ros__parameters']) == set(PARAMETERS)
    assert set(idf.IDENTIFIED_KEYS) <= set(values)
    settings = build_settings(values)
    assert settings.model == result.config
    assert result.config.bend_offset_rad != (0.0, 0.0)
    assert (tmp_path / 'loops.png').stat().st_size > 10_000
    report = (tmp_path / 'report.md').read_text()
    assert 'RMS bend error' in report and '`bend_offset_alpha_rad`' in report
    assert (tmp_path / 'bench_bag' / 'metadata.yaml').is_file()


@pytest.mark.slow
@pytest.mark.parametrize('plant_seed', [0, 1])
def test_full_excitation_halves_the_nominal_error(tmp_path, plant_seed) -> None:
    """The full excitation (204 s of rig time, about 45 s wall) on two plants: the identified
    model's RMS bend error over every sample is at most half the nominal's (the issue's bar).
    Measured (docs/reports/invitro.md, PAM identification): seed 0 0.44, seed 1 0.48 of the
    nominal's; on the sweeps 0.16 and 0.08.
    What remains is mostly the plant's lag on the held-out multisine, which the controller's
    model has no term for; on the short excitation (one multisine period in 37 s) it weighs
    more and seed 1 ends at 0.51, so the bar is asserted on the full one."""
    result = identify_sim(tmp_path, plant_seed=plant_seed)
    e = result.errors
    assert e['identified']['fit'] < 0.25 * e['nominal']['fit'], e
    assert e['identified']['all'] <= 0.5 * e['nominal']['all'], e


def _pose_msg(ns: int):
    return T['geometry_msgs/msg/PoseStamped'](
        header=T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9),
            frame_id='phantom'),
        pose=T['geometry_msgs/msg/Pose'](
            position=T['geometry_msgs/msg/Point'](x=0.0, y=0.0, z=0.0),
            orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)))


def _bag(path: Path, seconds: float, with_pressures: bool = True) -> Path:
    """A bench bag: poses at 40 Hz (straight tip), pressures at 20 Hz (vented for 1 s, then
    a 10 kPa differential on alpha)."""
    with BagWriter(path) as w:
        w.add_topic('/em_tracker/tip_pose', 'geometry_msgs/msg/PoseStamped', [SENSOR])
        if with_pressures:
            w.add_topic('/pam/pressures', 'std_msgs/msg/Float64MultiArray', [SENSOR])
        for i in range(int(seconds * 40)):
            ns = i * 25_000_000
            w.write('/em_tracker/tip_pose', ns,
                    TYPESTORE.serialize_cdr(_pose_msg(ns), 'geometry_msgs/msg/PoseStamped'))
            if with_pressures and i % 2 == 0:
                p = [0.0] * 4 if ns < 10**9 else [155e3, 145e3, 150e3, 150e3]
                msg = T['std_msgs/msg/Float64MultiArray'](
                    layout=T['std_msgs/msg/MultiArrayLayout'](dim=[], data_offset=0),
                    data=np.array(p))
                w.write('/pam/pressures', ns,
                        TYPESTORE.serialize_cdr(msg, 'std_msgs/msg/Float64MultiArray'))
    return path


@pytest.mark.parametrize(('make', 'expected'), [
    (lambda d: _bag(d / 'bag', 3.0, with_pressures=False),
     r"expected topics \['em_tracker/tip_pose', 'pam/pressures'\] for identify_pam, found "
     r"\['/em_tracker/tip_pose'\] \(missing \['pam/pressures'\]\)"),
    (lambda d: _bag(d / 'bag', 3.0), 'expected at least 100 samples of sweeps, found 40'),
    (lambda d: _bag(d / 'bag', 20.0), 'span of at least 40 kPa on alpha, found 0.0 kPa'),
    (lambda d: d / 'no_such_bag', 'no_such_bag'),
])
def test_bad_input_gives_one_clear_line(tmp_path, capsys, make, expected) -> None:
    bag = make(tmp_path)
    assert main(['--bag', str(bag), '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith('cgail identify-pam: error: '), err
    assert pytest.importorskip('re').search(expected, err), err

"""The simulated in-vitro session (cgail_rig.session).

Fast: argument checks and the report stage on the committed trial bags. Slow (-m slow): the
whole rig in-process (phantom + simulated devices, aurora_node over the pty, pam_node,
driver_node, teleop_node, planner_node, operator_node) for one short trial per condition.
"""

from pathlib import Path
import shutil

import pytest
import yaml

from cgail_rig.session import main, report

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / 'bags' / 'fixtures'


def test_cgail_condition_needs_a_policy(tmp_path, capsys) -> None:
    missing = tmp_path / 'missing.onnx'
    assert main(['--out', str(tmp_path), '--trials', '1', '--policy', str(missing)]) == 2
    assert f'needs --policy <model.onnx> (cgail export-onnx), found no file at {missing}' \
        in capsys.readouterr().err


def test_default_policy_is_the_committed_cgail_model_of_the_anatomy_and_mode() -> None:
    from cgail_rig.session import build_parser, default_policy

    assert build_parser().parse_args([]).policy is None  # resolved from --anatomy and --mode
    for anatomy, mode, name in (('default', 'static', 'cgail_default_static.onnx'),
                                ('default', 'dynamic', 'cgail_default_dynamic.onnx'),
                                ('elongated', 'static', 'cgail_elongated_static.onnx'),
                                ('elongated', 'dynamic', 'cgail_elongated_static.onnx')):
        policy = default_policy(anatomy, mode)
        assert policy.name == name and policy.is_file()
    assert not default_policy('nonexistent', 'static').is_file()


def test_plant_option_goes_to_the_phantom_and_the_controller(capsys, tmp_path) -> None:
    """--plant identified (default) | nominal | ideal: the phantom's ``plant`` parameter, and
    for 'identified' the cached identified model over pam_controller's parameters."""
    from types import SimpleNamespace

    from cgail_rig.session import (
        build_parser,
        identified_pam_parameters,
        SessionSettings,
        TrialRig,
        TrialSpec,
    )

    assert build_parser().parse_args([]).plant == 'identified'
    assert build_parser().parse_args([]).trials == 30
    assert build_parser().parse_args(['--plant', 'identified']).plant == 'identified'
    with pytest.raises(SystemExit):
        build_parser().parse_args(['--plant', 'true'])
    assert "invalid choice: 'true'" in capsys.readouterr().err
    spec = TrialSpec('centerline', 0, 0, 0, 7, 'bag')
    for plant in ('true', 'ideal'):
        rig = SimpleNamespace(settings=SessionSettings(plant=plant), spec=spec)
        overrides = TrialRig._overrides(rig, Path('aurora'))  # type: ignore[arg-type]
        assert overrides['phantom']['plant'] == plant
        assert overrides['pam_controller'] == {'control_rate_hz': 20.0}
    cached = tmp_path / 'plant_seed_4'
    cached.mkdir()
    from pam_controller.core.identification import IDENTIFIED_KEYS

    values = dict.fromkeys(IDENTIFIED_KEYS, 0.0) | {
        'hysteresis_gain_rad_per_pa': 5e-6, 'hysteresis_fraction': 0.75,
        'hysteresis_density_decay': 3.0, 'hysteresis_max_threshold_pa': 5e4}
    (cached / 'pam_identified.yaml').write_text(yaml.safe_dump(
        {'pam_controller': {'ros__parameters': {'can_channel': 'pam0', **values}}}))
    params = identified_pam_parameters(tmp_path, 4, print)  # cached: no bench run
    assert params == tuple((k, values[k]) for k in IDENTIFIED_KEYS)
    rig = SimpleNamespace(settings=SessionSettings(pam_parameters=params), spec=spec)
    overrides = TrialRig._overrides(rig, Path('aurora'))  # type: ignore[arg-type]
    assert overrides['pam_controller'] == {'control_rate_hz': 20.0, **dict(params)}


def test_refuses_to_mix_with_existing_bags(tmp_path, capsys) -> None:
    (tmp_path / 'bags' / 'cgail').mkdir(parents=True)
    (tmp_path / 'bags' / 'cgail' / 'old').mkdir()
    assert main(['--out', str(tmp_path), '--conditions', 'centerline']) == 2
    assert 'already holds bags' in capsys.readouterr().err


def test_report_on_recorded_trials(tmp_path) -> None:
    bags = tmp_path / 'bags'
    for condition in ('cgail', 'centerline'):
        (bags / condition).mkdir(parents=True)
        shutil.copytree(FIXTURES / f'{condition}_trial', bags / condition / f'{condition}_01')
    lines: list[str] = []
    outcomes = [('cgail', 1, 'at the target (1.0 mm)'), ('centerline', 1, 'time limit')]
    assert report(tmp_path, bags, outcomes, lines.append, wall_s=1.0) == 0
    text = (tmp_path / 'metrics.md').read_text()
    assert '| 1 | cgail | at the target (1.0 mm) |' in text
    assert 'Side by side with the paper' in text and 'Kruskal-Wallis' in text
    assert (tmp_path / 'metrics.csv').is_file() and (tmp_path / 'metrics_boxplot.png').is_file()


def test_a_simulation_fault_ends_its_trial_as_a_counted_outcome(tmp_path, monkeypatch,
                                                               capsys) -> None:
    """The beating wall blows up 3 simulated seconds into the trial: the phantom freezes, the
    trial ends at once as a simulation fault (anatomy, seed, time), the session goes on and
    its report counts the fault."""
    from cgail_rig.core.phantom import PhantomPhysics
    from cgail_sim.wall import WallError

    step = PhantomPhysics.step
    clock = {'t': 0.0}

    def blow_up(self, dt, *args, **kwargs):
        clock['t'] += dt
        if clock['t'] > 3.0:
            raise WallError('deformable wall: expected every particle within 40 mm of its rest '
                            'position, found particle 7 2495819.0 mm away (injected)')
        return step(self, dt, *args, **kwargs)

    monkeypatch.setattr(PhantomPhysics, 'step', blow_up)
    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)
    out = tmp_path / 'session'
    main(['--trials', '1', '--plant', 'nominal', '--conditions', 'centerline', '--jobs', '1',
          '--mode', 'dynamic', '--time-limit', '30', '--out', str(out)])
    text = (out / 'metrics.md').read_text()
    assert 'simulation faults: 1 (a trial a fault ended counts as a failure)' in text, text
    row = next(line for line in text.splitlines() if line.startswith('| 1 | centerline |'))
    assert 'simulation fault at ' in row and '(anatomy default, seed ' in row, row
    assert 'particle 7 2495819.0 mm away (injected)' in row, row
    assert 'simulation fault at ' in capsys.readouterr().out


def test_a_named_real_aorta_runs_a_session(tmp_path, monkeypatch) -> None:
    """``--anatomy avt-D18`` (a shipped real aorta, by name) reaches the phantom and the
    planner as that name: the centerline trial runs in D18 and reaches its target."""
    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)
    out = tmp_path / 'session'
    assert main(['--trials', '1', '--plant', 'nominal', '--conditions', 'centerline',
                 '--anatomy', 'avt-D18', '--jobs', '1', '--time-limit', '150',
                 '--out', str(out)]) == 0
    text = (out / 'metrics.md').read_text()
    assert 'callback errors: 0, simulation faults: 0 ' in text, text
    row = next(line for line in text.splitlines() if line.startswith('| centerline_01'))
    assert [c.strip() for c in row.strip('|').split('|')][8] == 'yes', row


def _assert_both_trials_reached(out: Path) -> None:
    """The session's report: no callback error, trial 1 of each condition reached its target
    within epsilon in time, with a tracking error under 10 mm."""
    text = (out / 'metrics.md').read_text()
    assert 'callback errors: 0, simulation faults: 0 ' in text
    rows = [line for line in text.splitlines()
            if line.startswith(('| cgail_01', '| centerline_01'))]
    assert len(rows) == 2, text
    for row in rows:
        cells = [c.strip() for c in row.strip('|').split('|')]
        assert cells[8] == 'yes', row                  # reached within epsilon in time
        assert float(cells[6]) < 10.0, row             # T_a (mm)


@pytest.mark.slow
def test_one_trial_per_condition_end_to_end(tmp_path) -> None:
    """The main job's path (--plant identified, the default): identify_pam on the session's
    plant first, then a trial per condition with the identified model."""
    out = tmp_path / 'session'
    code = main(['--trials', '1', '--out', str(out), '--time-limit', '150'])
    assert code == 0
    assert (out / 'identification' / 'plant_seed_0' / 'pam_identified.yaml').is_file()
    _assert_both_trials_reached(out)
    assert (out / 'metrics_boxplot.png').is_file()
    assert sorted(p.name for p in (out / 'bags').iterdir()) == ['centerline', 'cgail']
    _assert_tf_and_markers_recorded(out / 'bags' / 'cgail' / 'cgail_01', dynamic=False)


def test_a_short_trial_records_tf_the_tip_covariance_and_the_markers(tmp_path,
                                                                     monkeypatch) -> None:
    """The default suite's session run: one centerline trial cut at 8 simulated seconds,
    dynamic (the wall deforms), and what its bag holds besides the metrics' topics."""
    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)  # the test run holds its own: pick one
    out = tmp_path / 'session'
    assert main(['--trials', '1', '--plant', 'nominal', '--conditions', 'centerline',
                 '--mode', 'dynamic', '--time-limit', '8', '--out', str(out)]) == 0
    _assert_tf_and_markers_recorded(out / 'bags' / 'centerline' / 'centerline_01', dynamic=True)


def test_slicer_follows_a_simulated_trial_over_openigtlink(tmp_path, monkeypatch) -> None:
    """A pyigtl client stands in for 3D Slicer while a trial runs with --igtl: it receives
    the tip TRANSFORM as it moves, the planned path and the lumen (RAS mm)."""
    import socket
    import threading

    import numpy as np
    import pyigtl
    import pyigtl.messages

    from cgail_gui.core import igtl
    from cgail_gui.hw.igtl_server import PolyDataReader

    monkeypatch.setitem(pyigtl.messages.message_type_to_class_constructor, 'POLYDATA',
                        PolyDataReader)  # as Slicer reads them
    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        port = probe.getsockname()[1]
    got: dict[str, list] = {}
    stop = threading.Event()

    def slicer() -> None:
        client = pyigtl.OpenIGTLinkClient(host='127.0.0.1', port=port, start_now=True)
        try:
            while not stop.is_set():
                for device in (igtl.TIP_DEVICE, igtl.PATH_DEVICE, igtl.LUMEN_DEVICE):
                    message = client.wait_for_message(device, timeout=0.05)
                    if message is not None:
                        got.setdefault(device, []).append(message)
        finally:
            client.stop()

    thread = threading.Thread(target=slicer, daemon=True)
    thread.start()
    try:
        assert main(['--trials', '1', '--plant', 'nominal', '--conditions', 'centerline',
                     '--time-limit', '8', '--time-scale', '2', '--igtl', '--igtl-port', str(port),
                     '--out', str(tmp_path / 'session')]) == 0
    finally:
        stop.set()
        thread.join(timeout=10)
    tips = got.get(igtl.TIP_DEVICE, [])
    assert len(tips) >= 5, {k: len(v) for k, v in got.items()}
    first, last = (np.asarray(t.matrix, dtype=float)[:3, 3] for t in (tips[0], tips[-1]))
    assert np.linalg.norm(last - first) > 1.0  # mm: the tip moved during the trial
    path = got[igtl.PATH_DEVICE][-1]
    assert path.message_type == 'POLYDATA' and len(path.points) >= 2
    assert len(got[igtl.LUMEN_DEVICE][-1].polygons) > 0


def _assert_tf_and_markers_recorded(bag: Path, dynamic: bool) -> None:
    """The trial's bag carries TF (aurora -> phantom latched, phantom -> catheter_tip with
    every tip pose), the tip with its covariance and both marker arrays, as Foxglove and RViz2
    read them; the recorded lumen moves in a dynamic trial and stays put in a static one."""
    from rosbags.highlevel import AnyReader

    from cgail_rig.session import RECORDED_LUMEN_TRIANGLES

    msgs: dict[str, list] = {}
    types: dict[str, str] = {}
    with AnyReader([bag]) as reader:
        for conn, _, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
            types[conn.topic] = conn.msgtype
    assert types['/tf'] == types['/tf_static'] == 'tf2_msgs/msg/TFMessage'
    assert types['/phantom/markers'] == types['/phantom/lumen'] == \
        'visualization_msgs/msg/MarkerArray'
    [static] = msgs['/tf_static']
    assert [(t.header.frame_id, t.child_frame_id) for t in static.transforms] == [
        ('aurora', 'phantom')]
    tips = {(t.header.stamp.sec, t.header.stamp.nanosec): t.transform.translation
            for m in msgs['/tf'] for t in m.transforms
            if (t.header.frame_id, t.child_frame_id) == ('phantom', 'catheter_tip')}
    poses = msgs['/em_tracker/tip_pose']
    assert len(tips) == len(poses) > 100 and len(msgs['/em_tracker/tip_pose_cov']) == len(poses)
    last = poses[-1]
    tr = tips[(last.header.stamp.sec, last.header.stamp.nanosec)]
    assert (tr.x, tr.y, tr.z) == (last.pose.position.x, last.pose.position.y,
                                  last.pose.position.z)
    lumen = [m for a in msgs['/phantom/lumen'] for m in a.markers if m.ns == 'lumen']
    # a static wall recorded once (the latched sample), a dynamic one refreshed as it moves
    assert lumen[0].type == 11 and (len(lumen) >= 10 if dynamic else len(lumen) == 1)
    assert 0 < len(lumen[0].points) <= 3 * RECORDED_LUMEN_TRIANGLES * 1.2
    assert {m.ns for a in msgs['/phantom/markers'] for m in a.markers} == {'', 'catheter_body'}
    assert {m.ns for a in msgs['/planner/markers'] for m in a.markers} >= {'target', 'path'}
    first, last_wall = lumen[0].points, lumen[-1].points
    moved = max(abs(a.x - b.x) + abs(a.y - b.y) + abs(a.z - b.z)
                for a, b in zip(first, last_wall, strict=True))
    assert moved > 1e-5 if dynamic else moved == 0.0


@pytest.mark.slow
def test_one_trial_per_condition_in_a_prepared_anatomy(prepared_anatomy, tmp_path) -> None:
    """The session in a prepared directory with a policy contracted for it: every node
    resolves the same anatomy, the planner accepts the contract, both trials reach the
    target."""
    from cgail_learning.export import default_contract, write_contract

    policy = write_contract(
        ROOT / 'src' / 'cgail_planner' / 'cgail_planner' / 'models'
        / 'cgail_default_static.onnx', default_contract(prepared_anatomy, 'static'),
        tmp_path / 'cgail_p07_static.onnx')
    out = tmp_path / 'session'
    assert main(['--trials', '1', '--plant', 'nominal', '--out', str(out), '--time-limit',
                 '150', '--anatomy', str(prepared_anatomy), '--policy', str(policy),
                 '--jobs', '1']) == 0
    _assert_both_trials_reached(out)

"""``make_demos --from-bags``: teleoperated session bags -> demonstration bags
(cgail_learning.teleop_demos).

The session bag is ``test/fixtures/session_trial`` (a real simulated in-vitro trial cut down to
the tip, goal and path topics; ``make_session_trial.py``). Expected values are the model's exact
behaviour where it is exact (a reachable step, the true tip followed without clipping) and
bounds elsewhere (EM noise), never a last-bit float.
"""

from contextlib import redirect_stderr, redirect_stdout
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from cgail_learning.demo_bags import read_demo_bag, replay_demo_bag
from cgail_learning.demos_cli import main
from cgail_learning.teleop_demos import ConversionConfig, fit_step, resample
from cgail_sim.ftl_model import action_to_command, advance_pose, CatheterConfig

FIXTURES = Path(__file__).resolve().parents[3] / 'cgail_rig' / 'test' / 'fixtures'
SESSION = FIXTURES / 'session_trial'
SYNTHETIC = Path(__file__).resolve().parents[4] / 'bags' / 'fixtures' / 'cgail_trial'


def run(argv: list[str]) -> tuple[int, dict, list[str]]:
    """``make_demos`` in process: exit status, the JSON report (or {}), the stderr lines."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(argv)
    text = out.getvalue().strip()
    return code, json.loads(text) if text else {}, err.getvalue().splitlines()


def copy_bag(dst: Path, *, drop: tuple[str, ...] = (), goals: tuple = ()) -> Path:
    """The session fixture without the topics ``drop``, plus goal messages ``goals`` (each
    ``(t_s, xyz)``) on planner/goal."""
    from cgail_bags.bagio import BagWriter, iter_raw, open_bag, TYPESTORE

    T = TYPESTORE.types
    with open_bag(SESSION) as reader, BagWriter(dst) as writer:
        for conn in reader.connections:
            if conn.topic not in drop:
                writer.add_topic(conn.topic, conn.msgtype)
        for conn, ns, raw in iter_raw(reader):
            if conn.topic not in drop:
                writer.write(conn.topic, ns, raw)
        for t, xyz in goals:
            ns = round(t * 1e9)
            msg = T['geometry_msgs/msg/PoseStamped'](
                header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
                    sec=ns // 10**9, nanosec=ns % 10**9), frame_id='phantom'),
                pose=T['geometry_msgs/msg/Pose'](
                    position=T['geometry_msgs/msg/Point'](x=xyz[0], y=xyz[1], z=xyz[2]),
                    orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)))
            writer.write('/planner/goal', ns,
                         TYPESTORE.serialize_cdr(msg, 'geometry_msgs/msg/PoseStamped'))
    return dst


@pytest.fixture(scope='module')
def converted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, dict, list[str]]:
    """The session fixture converted from its true tip (``--tip-topic auto``)."""
    out = tmp_path_factory.mktemp('teleop') / 'demos'
    code, report, lines = run(['--from-bags', str(SESSION), '--out', str(out)])
    return out, code, report, lines


# ---------------------------------------------------------------------- the step
CAT = CatheterConfig()


def start_pose() -> tuple[np.ndarray, np.ndarray]:
    angle = 0.3
    r = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(angle), -math.sin(angle)],
                  [0.0, math.sin(angle), math.cos(angle)]])
    return np.array([0.01, -0.02, 0.03]), r


@pytest.mark.parametrize('action', [(0.5, -0.25, 0.8), (-1.0, 1.0, 1.0), (0.0, 0.0, 0.3)])
def test_a_reachable_step_is_inverted_exactly(action) -> None:
    p, r = start_pose()
    al, ga, dl = action_to_command(np.array(action), CAT.theta_max, CAT.segment_length,
                                   CAT.max_step_insertion)
    q = advance_pose(p, r, float(al), float(ga), float(dl))[0]
    got = fit_step(p, r, q, CAT, CAT.theta_max)
    assert got == pytest.approx(np.array(action), abs=1e-7)


def test_too_fast_insertion_is_clipped_to_v_max_dt() -> None:
    p, r = start_pose()
    q = p + 0.002 * r[:, 1]  # 2 mm straight ahead: four steps' worth
    got = fit_step(p, r, q, CAT, CAT.theta_max)
    assert got == pytest.approx(np.array([0.0, 0.0, 1.0]), abs=1e-7)


def test_lateral_motion_saturates_the_bend_with_the_insertion_it_needs() -> None:
    p, r = start_pose()
    q = p + 0.0003 * r[:, 1] + 0.0003 * r[:, 0]  # 45 deg off the heading, beyond 0.9 deg
    got = fit_step(p, r, q, CAT, CAT.theta_max)
    assert -1.0 <= got[1] <= -1.0 + 1e-9 and 0.0 < got[2] <= 1.0
    al, ga, dl = action_to_command(got, CAT.theta_max, CAT.segment_length,
                                   CAT.max_step_insertion)
    landed = advance_pose(p, r, float(al), float(ga), float(dl))[0]
    straight = p + dl * r[:, 1]
    assert np.linalg.norm(landed - q) < np.linalg.norm(straight - q)


def test_a_point_behind_the_tip_is_a_retraction_and_a_pause_is_no_motion() -> None:
    p, r = start_pose()
    assert fit_step(p, r, p - 0.0002 * r[:, 1], CAT, CAT.theta_max) == pytest.approx(
        np.array([0.0, 0.0, -0.4]), abs=1e-9)
    assert fit_step(p, r, p + 1e-4 * r[:, 0], CAT, CAT.theta_max,
                    deadband_m=2e-4).tolist() == [0.0, 0.0, 0.0]


def test_resample_interpolates_and_smooths_a_line_onto_itself() -> None:
    t = np.arange(0.0, 2.0, 0.025)
    p = np.stack([t * 0.005, -t * 0.002, np.full_like(t, 0.1)], axis=1)
    t_new = np.arange(0.0, 1.9, 0.1)
    line = np.stack([t_new * 0.005, -t_new * 0.002, np.full_like(t_new, 0.1)], axis=1)
    assert resample(t, p, t_new, 0.0) == pytest.approx(line, abs=1e-12)
    assert resample(t, p, t_new, 0.4) == pytest.approx(line, abs=1e-12)


@pytest.mark.parametrize('field, value, match', [
    ('max_deviation_m', 0.0, r'max_deviation_m must be in \(0.0, 0.05\], found 0.0'),
    ('smooth_s', -1.0, r'smooth_s must be None or in \[0, 2\] s, found -1.0'),
    ('min_steps', 0, r'min_steps must be an int in \[1, 100000\], found 0'),
    ('tip_topic', '/', r"tip_topic must be 'auto' or a topic name, found '/'"),
])
def test_config_rejects_values_out_of_range(field, value, match) -> None:
    with pytest.raises(ValueError, match=match):
        ConversionConfig(**{field: value})


# ---------------------------------------------------------------------- the command
def test_session_bag_converts_to_one_successful_episode(converted) -> None:
    _out, code, report, lines = converted
    assert code == 0, lines
    assert (report['bags'], report['episodes'], report['successful']) == (1, 1, 1)
    ep = report['per_episode'][0]
    assert (ep['start'], ep['target'], ep['end']) == (1, 1, 'target reached')
    assert report['notes'] == ['tip positions from phantom/tip_pose (1 bag(s))']
    assert report['skipped'] == []
    # the phantom moves the catheter as the model does: its true tip needs no clipping
    # (a step or two may clip where the remeshed wall differs in the last bits: 0.3 % on
    # AVX2-only numpy, where the deviation reached 0.011 mm)
    assert report['clipped_fraction'] <= 0.01 and report['deviation_max_mm'] < 0.1
    assert report['replay']['max_drift_mm'] < 1e-6 and report['replay']['tolerance_mm'] == 1.0
    assert len(lines) == 1
    assert lines[0].startswith(f'cgail make-demos: {SESSION}: start 1 target 1: ')


def test_converted_bag_holds_actions_within_the_action_space(converted) -> None:
    out = converted[0]
    meta, episodes = read_demo_bag(out)
    assert meta['anatomy'] == 'default' and meta['mode'] == 'static'
    (ep,) = episodes
    assert ep.success and len(ep.alpha) == converted[2]['steps']
    m = CAT.max_step_insertion
    limit = CAT.theta_max * np.abs(ep.delta_l) / CAT.segment_length
    assert (np.abs(ep.delta_l) <= m * (1 + 1e-12)).all()
    assert (np.abs(ep.alpha) <= limit * (1 + 1e-12)).all()
    assert (np.abs(ep.gamma) <= limit * (1 + 1e-12)).all()
    assert 0.6 < float(np.mean(ep.delta_l)) / m <= 1.0  # mostly full-speed insertion
    replay = replay_demo_bag(out)
    assert replay.act.shape == (len(ep.alpha), 3) and np.abs(replay.act).max() <= 1.0


def test_source_of_the_conversion_is_in_the_bag(converted) -> None:
    import yaml

    doc = yaml.safe_load((converted[0] / 'metadata.yaml').read_text())
    info = json.loads(doc['rosbag2_bagfile_information']['custom_data']['cgail_planner.demos'])
    assert info['source']['from_bags'] == [str(SESSION)]
    assert info['source']['config']['tip_topic'] == 'auto'
    assert info['source']['clipped_fraction'] <= 0.01


def test_em_tracked_tip_converts_with_bounded_clipping_and_deviation(tmp_path) -> None:
    code, report, lines = run(['--from-bags', str(SESSION), '--tip-topic',
                               'em_tracker/tip_pose', '--out', str(tmp_path / 'em')])
    assert code == 0, lines
    assert (report['episodes'], report['successful']) == (1, 1)
    assert report['notes'] == ['tip positions from em_tracker/tip_pose (1 bag(s))']
    # 0.5 mm RMS noise, smoothed: some steps clip, the tip stays within a millimetre or so
    assert 0.0 < report['clipped_fraction'] < 0.5
    assert 0.0 < report['deviation_mean_mm'] < 0.5 and report['deviation_max_mm'] < 2.0
    assert report['replay']['max_drift_mm'] < 1e-6


def test_bad_inputs_are_one_line_each_and_lose_nothing_else(tmp_path) -> None:
    import shutil

    corrupt = tmp_path / 'corrupt'
    shutil.copytree(SESSION, corrupt)
    mcap = corrupt / 'session_trial.mcap'
    mcap.write_bytes(mcap.read_bytes()[:20000])
    no_goal = copy_bag(tmp_path / 'no_goal', drop=('/planner/goal',))
    # a second goal (target 3) while the catheter is on its way: the first episode ends
    # there; the second cannot start from a scenario start
    from cgail_sim.worlds import load_world

    target3 = load_world('default').scenarios.targets[3].position
    two_goals = copy_bag(tmp_path / 'two_goals', goals=((30.0, tuple(target3)),))
    code, report, lines = run(['--from-bags', str(corrupt), str(no_goal), str(SYNTHETIC),
                               str(two_goals), str(tmp_path / 'missing'),
                               '--out', str(tmp_path / 'demos')])
    assert code == 0, lines
    assert report['bags'] == 5 and report['episodes'] == 1
    ep = report['per_episode'][0]
    assert (ep['bag'], ep['end'], ep['success']) == (str(two_goals), 'next goal', False)
    skipped = report['skipped']
    assert len(skipped) == 5, skipped
    assert skipped[0].startswith(f'{tmp_path / "missing"}: no such bag')
    assert skipped[1].startswith(f'{corrupt}: truncated or corrupt bag')
    assert skipped[2].startswith(f"{no_goal}: expected topics ['planner/goal'] with messages")
    assert skipped[3].startswith(f'{SYNTHETIC}: goal at ') and 'from the nearest scenario ' \
        'target' in skipped[3]
    assert skipped[4].startswith(f'{two_goals}: episode at 30.000 s (target 3): expected it to '
                                 'start within 3 mm of a scenario start')
    assert all('\n' not in s for s in skipped)
    problems = [ln for ln in lines if 'start 1 target 1' not in ln]
    assert len(problems) == 6  # one stderr line each, then:
    # the one episode did not reach its target: nothing for train to replay, said so
    assert problems[-1].endswith('holds no episode that train replays (it replays the '
                                 'successful ones)')
    assert 'replay' not in report


def test_nothing_convertible_exits_2(tmp_path) -> None:
    code, report, lines = run(['--from-bags', str(SYNTHETIC), '--out', str(tmp_path / 'd')])
    assert code == 2 and report == {}
    assert lines[-1] == ('cgail make-demos: error: no episode could be converted from 1 bag(s) '
                         '(1 problem(s) above)')
    assert not (tmp_path / 'd').exists()


def test_a_short_training_run_accepts_the_converted_demonstrations(converted, tmp_path) -> None:
    from cgail_learning.train import main as train

    assert train(['--preset', 'smoke', '--demos', str(converted[0]), '--out',
                  str(tmp_path / 'run'), '--no-progress', '--threads', '1',
                  '--max-steps', '1024']) == 0
    assert (tmp_path / 'run' / 'final.pt').is_file()

"""Demo bags: MCAP round trip, quaternions, errors; expert + re-simulation in the simulator."""

from __future__ import annotations

import copy
from pathlib import Path
import subprocess
import sys
import warnings

import numpy as np
import pytest

from cgail_learning.demo_bags import (
    DemoEpisode,
    load_demo_bag,
    POSE_TOLERANCE_M,
    read_demo_bag,
    recorded_start_pose,
    replay_demo_bag,
    write_demo_bag,
)
from cgail_learning.demos import load_demos
from cgail_learning.errors import DemoAnatomyWarning, DemoError
from cgail_learning.evaluate import kruskal, summarize, Trial
from cgail_planner.core.rotations import matrix_to_quaternion

REPO = Path(__file__).resolve().parents[4]


def _episode(n: int = 5, success: bool = True) -> DemoEpisode:
    rng = np.random.default_rng(n)
    q = rng.normal(size=(n, 4))
    return DemoEpisode(1, 3, rng.normal(size=n) * 0.01, rng.normal(size=n) * 0.01,
                       np.full(n, 5e-4), rng.normal(size=(n, 3)) * 0.1,
                       q / np.linalg.norm(q, axis=1, keepdims=True), rng.normal(size=(n, 3)),
                       success)


@pytest.mark.parametrize(('compress', 'anatomy_hash'), [(False, None), (True, '0123abcd')])
def test_demo_bag_round_trip(tmp_path: Path, compress: bool, anatomy_hash: str | None):
    if compress:
        pytest.importorskip('zstandard')
    eps = [_episode(5), _episode(7, success=False)]
    write_demo_bag(tmp_path / 'bag', eps, anatomy='default', mode='static', dt=0.1,
                   compress=compress, anatomy_hash=anatomy_hash)
    assert list((tmp_path / 'bag').glob('*.mcap'))
    assert '  ros_distro: jazzy\n' in (tmp_path / 'bag' / 'metadata.yaml').read_text()
    meta, back = read_demo_bag(tmp_path / 'bag')
    if anatomy_hash is None:  # as the bags written before the hash was stored
        assert meta == {'anatomy': 'default', 'mode': 'static', 'scenario_seed': 0}
    else:
        from cgail_sim.disk_cache import numpy_simd_targets

        assert meta == {'anatomy': 'default', 'mode': 'static', 'anatomy_hash': anatomy_hash,
                        'numpy_simd': ','.join(numpy_simd_targets()), 'scenario_seed': 0}
        assert 'anatomy_hash' in (tmp_path / 'bag' / 'metadata.yaml').read_text()
    assert [len(e.alpha) for e in back] == [5, 7] and [e.success for e in back] == [True, False]
    for a, b in zip(eps, back, strict=True):
        np.testing.assert_array_equal(a.delta_l, b.delta_l)
        np.testing.assert_array_equal(a.tip_position, b.tip_position)
        np.testing.assert_array_equal(a.tip_quaternion, b.tip_quaternion)
        np.testing.assert_array_equal(a.target_position, b.target_position)
        assert (a.start, a.target) == (b.start, b.target)


def test_demo_errors(tmp_path: Path):
    with pytest.raises(DemoError, match='not found'):
        read_demo_bag(tmp_path / 'nope')
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / 'metadata.yaml').write_text('garbage: [')
    with pytest.raises(DemoError, match='not a readable rosbag2 bag'):
        read_demo_bag(tmp_path / 'junk')
    write_demo_bag(tmp_path / 'b', [_episode(3)], anatomy='default', mode='static', dt=0.1)
    with pytest.raises(DemoError, match='already exists'):
        write_demo_bag(tmp_path / 'b', [_episode(3)], anatomy='default', mode='static', dt=0.1)
    with pytest.raises(DemoError, match='at least one'):
        load_demos([])
    np.savez(tmp_path / 'd.npz', obs=np.zeros((4, 41)), wrong=np.zeros((4, 3)))
    with pytest.raises(DemoError, match='expected arrays obs and act'):
        load_demos([tmp_path / 'd.npz'])


def test_summary_and_kruskal():
    trials = [Trial(True, False, 100, 5.0), Trial(False, True, 40, 30.0),
              Trial(True, False, 120, 7.0)]
    s = summarize(trials)
    assert s['success_rate'] == pytest.approx(2 / 3) and s['T_s_succ'] == 110
    assert s['T_a_all_mm'] == 7.0 and s['collision_rate'] == pytest.approx(1 / 3)
    lo, hi = s['success_ci']  # Wilson, 2 of 3
    assert lo == pytest.approx(0.2077, abs=1e-3) and hi == pytest.approx(0.9385, abs=1e-3)
    assert s['T_s_succ_ci'][0] >= 100 and s['T_s_succ_ci'][1] <= 120
    assert s['T_a_all_ci'][0] <= 7.0 <= s['T_a_all_ci'][1]
    assert all(np.isnan(s['plan_ms_ci']))  # no method planned
    assert kruskal({'a': [1, 2, 3, 4, 5], 'b': [11, 12, 13, 14, 15]}) < 0.05
    assert np.isnan(kruskal({'a': [1.0], 'b': []}))


@pytest.mark.slow
def test_expert_demos_resimulate_in_the_simulator(tmp_path: Path):
    from cgail_learning.demos_cli import record_episodes
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    env = CatheterNavEnv(EnvConfig(mode='static'))
    episodes, stats = record_episodes(env, 2, seed=0)
    assert stats['success_rate'] == 1.0
    write_demo_bag(tmp_path / 'd', episodes, anatomy='default', mode='static', dt=0.1,
                   anatomy_hash=env.anatomy.content_hash)
    replay = replay_demo_bag(tmp_path / 'd')
    assert replay.obs.shape == (sum(len(e.alpha) for e in episodes), 41)
    assert np.all(np.abs(replay.act) <= 1.0) and np.all(replay.act[:, 2] > 0)
    assert replay.report.max_drift_m == 0.0 and replay.report.same_anatomy
    episodes[0].tip_position[10] += 0.002
    write_demo_bag(tmp_path / 'e', episodes, anatomy='default', mode='static', dt=0.1)
    with pytest.raises(DemoError, match='episode 0 step 10'):
        load_demo_bag(tmp_path / 'e')


def test_a_bag_of_another_target_set_replays_in_it(tmp_path: Path):
    """make_demos --scenario-seed: the bag records its target set and replays in it."""
    from cgail_learning.demo_bags import read_demo_bag
    from cgail_learning.demos_cli import record_episodes
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    env = CatheterNavEnv(EnvConfig(mode='static', scenario_seed=3))
    pairs: list = []
    episodes, stats = record_episodes(env, 1, seed=0, pairs=pairs)
    assert stats['success_rate'] == 1.0 and len(pairs) == 1
    write_demo_bag(tmp_path / 'd', episodes, anatomy='default', mode='static', dt=0.1,
                   anatomy_hash=env.anatomy.content_hash, scenario_seed=3)
    assert read_demo_bag(tmp_path / 'd')[0]['scenario_seed'] == 3
    replay = replay_demo_bag(tmp_path / 'd')
    assert replay.report.max_drift_m == 0.0
    # the pairs handed back are what the replay gives
    np.testing.assert_array_equal(replay.obs, pairs[0][0])
    np.testing.assert_array_equal(replay.act, pairs[0][1])
    # the same bag read as target set 0 (an older bag) puts the target elsewhere
    write_demo_bag(tmp_path / 'e', episodes, anatomy='default', mode='static', dt=0.1)
    assert read_demo_bag(tmp_path / 'e')[0]['scenario_seed'] == 0
    with pytest.raises(DemoError, match='target'):
        replay_demo_bag(tmp_path / 'e')


# ----------------------------------------------------------------------------------------------
# Replay: a physical tolerance, the drift reported, the anatomy hash compared
# ----------------------------------------------------------------------------------------------
ACTIONS = [[0.3, -0.2, 1.0]] * 30 + [[0.0, 0.0, -0.6]] * 3 + [[-0.4, 0.5, 0.8]] * 7


def _record(env, start: int, target: int, policy, max_steps: int = 2000
            ) -> tuple[DemoEpisode, np.ndarray, dict]:
    """An episode recorded as make_demos records it (``policy()`` gives each action), the
    observations the env gave and the last step's info."""
    obs, _ = env.reset(options={'start': start, 'target': target})
    rows: dict[str, list] = {k: [] for k in ('al', 'ga', 'dl', 'p', 'q', 'g', 'obs')}
    for _ in range(max_steps):
        rows['obs'].append(obs)
        obs, _, te, tr, info = env.step(np.asarray(policy(), dtype=np.float32))
        rows['al'].append(info['bend'][0])
        rows['ga'].append(info['bend'][1])
        rows['dl'].append(info['insertion'])
        rows['p'].append(env.catheter.tip_position[0].copy())
        rows['q'].append(matrix_to_quaternion(env.catheter.tip_rotation[0]))
        rows['g'].append(np.asarray(info['target_position'], float))
        if te or tr:
            break
    episode = DemoEpisode(start, target,
                          *(np.asarray(rows[k]) for k in ('al', 'ga', 'dl', 'p', 'q', 'g')),
                          success=True)
    return episode, np.stack(rows['obs']), info


@pytest.fixture(scope='module')
def recording():
    """40 scripted steps (a bend, a retraction, another bend) recorded in the static simulator
    from start 1 towards target 2, with the observations the env gave."""
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    env = CatheterNavEnv(EnvConfig(mode='static'))
    actions = iter(ACTIONS)
    episode, obs, info = _record(env, 1, 2, lambda: next(actions), len(ACTIONS))
    assert len(obs) == len(ACTIONS) and not (info['success'] or info['collision'])
    return env, episode, obs


def _bag(tmp_path: Path, episode: DemoEpisode, name: str = 'bag', **kw) -> Path:
    return write_demo_bag(tmp_path / name, [episode], anatomy='default', mode='static', dt=0.1,
                          compress=False, **kw)


def test_recorded_start_pose_inverts_the_first_step(recording):
    env, episode, _ = recording
    start = env.scenarios.starts[1]
    p0, r0 = recorded_start_pose(episode)
    assert p0 == pytest.approx(start.position, abs=1e-15)
    assert r0 == pytest.approx(start.rotation, abs=1e-15)
    retracting = copy.deepcopy(episode)
    retracting.delta_l[0] = -1e-4
    assert recorded_start_pose(retracting) is None


def test_replay_of_a_recording_in_this_anatomy_is_the_recording(tmp_path: Path, recording):
    env, episode, obs = recording
    bag = _bag(tmp_path, episode, anatomy_hash=env.anatomy.content_hash)
    with warnings.catch_warnings():
        warnings.simplefilter('error', DemoAnatomyWarning)
        replay = replay_demo_bag(bag)
    np.testing.assert_array_equal(replay.obs, obs)
    np.testing.assert_allclose(replay.act, np.asarray(ACTIONS, np.float32), rtol=0, atol=1e-6)
    r = replay.report
    assert (r.episodes, r.steps, r.ended_early, r.same_anatomy) == (1, 40, 0, True)
    assert r.max_drift_m == 0.0 and r.max_start_offset_m < 1e-15
    assert r.tolerance_m == POSE_TOLERANCE_M == 1e-3
    assert r.summary() == (
        f'{bag}: 1 episodes, 40 steps re-simulated; recorded starts off the scenario starts by '
        f'max {r.max_start_offset_m * 1e3:.3g} mm, mean {r.mean_start_offset_m * 1e3:.3g} mm; '
        f'tip drift from the recorded poses max 0 mm, mean 0 mm (tolerance 1 mm); anatomy '
        f'{env.anatomy.content_hash}, as recorded')


def test_replay_reports_drift_within_the_tolerance(tmp_path: Path, recording):
    _, episode, _ = recording
    moved = copy.deepcopy(episode)
    moved.tip_position[10] += [0.0, 0.0004, 0.0003]   # 0.5 mm off at one step
    bag = _bag(tmp_path, moved)
    replay = replay_demo_bag(bag)
    assert replay.report.max_drift_m == pytest.approx(5e-4, abs=1e-12)
    assert replay.report.mean_drift_m == pytest.approx(5e-4 / 40, abs=1e-12)
    assert 'tip drift from the recorded poses max 0.5 mm, mean 0.0125 mm' \
        in replay.report.summary()
    with pytest.raises(DemoError, match='step 10: the re-simulated tip: expected it within '
                                        r'0\.4 mm of the recording, found 0\.500 mm'):
        replay_demo_bag(bag, tolerance_m=4e-4)
    with pytest.raises(DemoError, match=r'tolerance_m must be in \(0, 1\) m, found 0'):
        replay_demo_bag(bag, tolerance_m=0)


@pytest.mark.parametrize(('what', 'move', 'match'), [
    ('pose', 0.002, r'episode 0 step 10: the re-simulated tip: expected it within 1 mm of the '
                    r'recording, found 2\.000 mm: re-record the demonstrations '
                    r'\(cgail make-demos\)$'),
    ('start', 0.0015, r'episode 0: the recorded start: expected it within 1 mm of the '
                      r'recording, found 1\.500 mm'),
    ('target', 0.0012, r'episode 0: the recorded target: expected it within 1 mm of the '
                       r'recording, found 1\.200 mm'),
])
def test_replay_beyond_the_tolerance_is_a_one_line_error(tmp_path: Path, recording, what, move,
                                                        match):
    _, episode, _ = recording
    bad = copy.deepcopy(episode)
    if what == 'pose':
        bad.tip_position[10, 0] += move
    elif what == 'start':   # the whole recording shifted: it started elsewhere
        bad.tip_position[:, 0] += move
    else:
        bad.target_position[:, 2] += move
    with pytest.raises(DemoError, match=match) as err:
        load_demo_bag(_bag(tmp_path, bad))
    assert '\n' not in str(err.value)


def test_replay_follows_a_recording_made_from_a_moved_start(tmp_path: Path, recording):
    """Another CPU's mesh moves the scenario start by tens of micrometres and its heading by up
    to ~1 deg: the recording is replayed from the pose it was made from, so its path is
    reproduced, and only the start offset is reported."""
    from scipy.spatial.transform import Rotation

    env, episode, obs = recording
    start = env.scenarios.starts[1].position
    q = Rotation.from_rotvec(np.radians(1.0) * np.array([0.6, 0.0, 0.8]))
    offset = np.array([0.0, 0.0001, 0.0])
    moved = copy.deepcopy(episode)
    moved.tip_position = start + offset + q.apply(episode.tip_position - start)
    moved.tip_quaternion = (q * Rotation.from_quat(episode.tip_quaternion)).as_quat()
    replay = replay_demo_bag(_bag(tmp_path, moved))
    assert replay.report.max_start_offset_m == pytest.approx(1e-4, abs=1e-12)
    assert replay.report.max_drift_m < 1e-12
    np.testing.assert_array_equal(replay.act, replay_demo_bag(_bag(tmp_path, episode, 'b')).act)
    assert np.abs(replay.obs[:, :3] - obs[:, :3]).max() > 1e-4  # observed where it went


def _extended(episode: DemoEpisode, extra: int) -> DemoEpisode:
    """``episode`` with its last recorded step repeated ``extra`` times: a recording that
    went on after the simulator ended it."""
    ext = copy.deepcopy(episode)
    for name in ('alpha', 'gamma', 'delta_l', 'tip_position', 'tip_quaternion',
                 'target_position'):
        arr = getattr(ext, name)
        setattr(ext, name, np.concatenate([arr, np.repeat(arr[-1:], extra, axis=0)]))
    return ext


def test_replay_that_ends_before_the_recorded_end(tmp_path: Path, recording):
    """Reaching the target early (a target moved by the remeshing) keeps the steps until then;
    a collision or exit before the recorded end is an error."""
    from cgail_sim.env import pursuit_actions

    env = recording[0]
    reached, _, info = _record(env, 0, 1, lambda: pursuit_actions(env.engine)[0])
    assert info['success']
    replay = replay_demo_bag(_bag(tmp_path, _extended(reached, 3)))
    assert (replay.report.ended_early, replay.report.steps) == (1, len(reached.alpha))
    assert ', 1 reached the target early;' in replay.report.summary()
    curl = iter([[1.0, 0.0, 1.0]] * 200)
    crashed, _, info = _record(env, 0, 0, lambda: next(curl), 200)
    assert info['collision']
    with pytest.raises(DemoError, match=(
            f'episode 0: expected the re-simulation to last {len(crashed.alpha) + 2} steps, '
            f'found it ended by a collision at step {len(crashed.alpha) - 1}$')):
        replay_demo_bag(_bag(tmp_path, _extended(crashed, 2), 'crashed'))


def test_replay_warns_when_the_anatomy_hash_differs(tmp_path: Path, recording):
    env, episode, _ = recording
    with pytest.warns(DemoAnatomyWarning, match=(
            r"recorded in 'default' anatomy 0000000000000000 \(numpy SIMD .*\), re-simulated "
            rf"in anatomy {env.anatomy.content_hash} .* drifts up to 0 mm, within the 1 mm "
            "tolerance")):
        replay = replay_demo_bag(_bag(tmp_path, episode, anatomy_hash='0' * 16))
    assert replay.report.same_anatomy is False
    assert replay.report.summary().endswith(
        f'anatomy {env.anatomy.content_hash}, recorded in 0000000000000000')
    with warnings.catch_warnings():   # a bag without a hash: no warning, None
        warnings.simplefilter('error', DemoAnatomyWarning)
        old = replay_demo_bag(_bag(tmp_path, episode, 'old'))
    assert old.report.same_anatomy is None and old.report.recorded_anatomy_hash is None
    assert old.report.summary().endswith('(the bag records no anatomy hash)')
    lines: list[str] = []
    obs, _, _ = load_demos([tmp_path / 'old'], report=lines.append)
    assert lines == [old.report.summary()] and len(obs) == 40


def test_the_sources_of_the_demonstrations_are_told_apart(tmp_path: Path, recording):
    """load_demos reports each path's source and episode count (train prints them by source
    and keeps them in the run's metadata): the scripted expert's, a record_demos bag (who,
    device) and a bag converted from session bags."""
    import json

    import yaml

    _, episode, _ = recording
    scripted = _bag(tmp_path, episode, 'scripted')
    recorded, converted = _bag(tmp_path, episode, 'recorded'), _bag(tmp_path, episode, 'conv')
    for bag, key, value in ((recorded, 'cgail_planner.record_demos',
                             {'driver': 'gamepad', 'who': 'A. Surgeon'}),
                            (converted, 'cgail_planner.demos', {'source': {'bags': ['x']}})):
        meta_path = bag / 'metadata.yaml'
        doc = yaml.safe_load(meta_path.read_text())
        custom = doc['rosbag2_bagfile_information'].setdefault('custom_data', {}) or {}
        old = json.loads(custom.get(key, '{}'))
        custom[key] = json.dumps({**old, **value})
        doc['rosbag2_bagfile_information']['custom_data'] = custom
        meta_path.write_text(yaml.safe_dump(doc))
    sources: list[dict] = []
    load_demos([scripted, recorded, converted], sources=sources)
    assert [(s['source'], s['episodes']) for s in sources] == [
        ('scripted expert (cgail make-demos)', 1),
        ('cgail record-demos (gamepad driver, by A. Surgeon)', 1),
        ('teleoperated session bags (cgail make-demos --from-bags)', 1)]


@pytest.mark.slow  # re-simulates the 70 committed demonstrations and trains 8,192 steps
def test_train_smoke_runs_on_the_committed_demonstrations(tmp_path: Path):
    """``train --preset smoke --demos bags/demos/default`` on this machine's numpy, whatever the
    CPU the demonstrations were recorded on."""
    out = subprocess.run(
        [sys.executable, '-m', 'cgail_learning.train', '--preset', 'smoke', '--mode',
         'static', '--demos', str(REPO / 'bags' / 'demos' / 'default'), '--out',
         str(tmp_path / 'run'), '--no-progress'],
        capture_output=True, text=True, timeout=1800, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    line = next(x for x in out.stderr.splitlines()
                if x.startswith('cgail train: demonstrations: '))
    assert '70 episodes, 30185 steps re-simulated' in line and '(tolerance 1 mm)' in line
    assert (tmp_path / 'run' / 'final.pt').is_file()


def test_train_resume_continues_a_run_from_its_latest_checkpoint(tmp_path: Path):
    """``train --resume RUN`` picks the highest-step checkpoint, keeps the run's preset and
    seed, extends it with ``--max-steps``, and rewrites ``scalars.csv`` from the resume step on
    (no duplicated rows); bad combinations are one line, exit 2."""
    import csv

    import numpy as np
    import yaml

    from cgail_learning.train import main

    rng = np.random.default_rng(0)
    demos = tmp_path / 'demos.npz'
    np.savez(demos, obs=rng.normal(size=(512, 41)).astype(np.float32),
             act=rng.uniform(-1, 1, (512, 3)).astype(np.float32), episodes=4)
    preset = yaml.safe_load((REPO / 'src' / 'cgail_learning' / 'config' / 'presets' /
                             'smoke.yaml').read_text())
    preset.update(max_steps=2048, checkpoint_every=1024, eval_every=0, eval_episodes=1)
    (tmp_path / 'tiny.yaml').write_text(yaml.safe_dump(preset))
    run = tmp_path / 'run'
    base = ['--mode', 'static', '--demos', str(demos), '--no-progress']
    assert main(['--preset', str(tmp_path / 'tiny.yaml'), '--seed', '5', '--out', str(run),
                 *base]) == 0
    assert sorted(p.name for p in (run / 'checkpoints').iterdir()) == ['step_1024.pt',
                                                                       'step_2048.pt']
    (run / 'final.pt').unlink()
    (run / 'checkpoints' / 'step_2048.pt').unlink()  # (as if killed after step 1024)
    assert main(['--resume', str(run), '--max-steps', '3072', *base]) == 0
    with (run / 'scalars.csv').open(newline='') as f:
        rows = list(csv.reader(f))[1:]
    steps = sorted({int(r[0]) for r in rows})
    assert steps[0] == 1024 and steps[-1] == 3072
    assert len(rows) == len({(r[0], r[1]) for r in rows})  # no step logged twice
    from cgail_learning.checkpoint import load_checkpoint

    final = load_checkpoint(run / 'final.pt')
    assert final['step'] == 3072 and final['seed'] == 5 and final['run']['next_ckpt'] == 4096
    assert main(['--resume', str(run), '--init-from', str(run / 'final.pt'), *base]) == 2
    assert main(['--resume', str(tmp_path / 'nothing'), *base]) == 2
    assert main(['--resume', str(run), '--mode', 'dynamic', '--demos', str(demos),
                 '--no-progress']) == 2
    # --checkpoint-every overrides the preset's interval, fresh or resumed; a resumed run
    # given a shorter one keeps to it from its resume step (not from the stored next step)
    other = tmp_path / 'other'
    assert main(['--preset', str(tmp_path / 'tiny.yaml'), '--out', str(other),
                 '--checkpoint-every', '2048', *base]) == 0
    assert sorted(p.name for p in (other / 'checkpoints').iterdir()) == ['step_2048.pt']
    assert main(['--resume', str(other), '--max-steps', '4096', '--checkpoint-every', '1024',
                 *base]) == 0
    assert sorted(p.name for p in (other / 'checkpoints').iterdir()) == [
        'step_2048.pt', 'step_3072.pt', 'step_4096.pt']
    assert yaml.safe_load((other / 'config.yaml').read_text())['checkpoint_every'] == 1024
    assert main(['--resume', str(other), '--checkpoint-every', '-1', *base]) == 2
    assert main(['--resume', str(other), '--max-steps', '6144', '--checkpoint-every', '0',
                 *base]) == 0  # (0: none from now on, not one per iteration)
    assert sorted(p.name for p in (other / 'checkpoints').iterdir()) == [
        'step_2048.pt', 'step_3072.pt', 'step_4096.pt']


def test_train_runs_the_bc_warm_start_of_the_preset_once(tmp_path: Path, capsys):
    """``bc.pretrain_epochs`` clones the demonstrations before the first env step (the
    normaliser fitted to them), needs demonstrations even with every reward signal off, and a
    resumed run does not clone again."""
    import numpy as np
    import torch
    import yaml

    from cgail_learning.checkpoint import load_checkpoint
    from cgail_learning.config import config_from_dict
    from cgail_learning.train import main

    rng = np.random.default_rng(0)
    obs = rng.normal(size=(512, 41)).astype(np.float32)
    demos = tmp_path / 'demos.npz'
    np.savez(demos, obs=obs, act=rng.uniform(-1, 1, (512, 3)).astype(np.float32), episodes=4)
    preset = yaml.safe_load((REPO / 'src' / 'cgail_learning' / 'config' / 'presets' /
                             'smoke.yaml').read_text())
    preset.update(max_steps=1024, checkpoint_every=1024, eval_every=0, eval_episodes=1,
                  normalize=True, gail={'strength': 0.0}, curiosity={'strength': 0.0},
                  bc={'strength': 0.0, 'pretrain_epochs': 2})
    assert config_from_dict(preset).needs_demos
    (tmp_path / 'warm.yaml').write_text(yaml.safe_dump(preset))
    run = tmp_path / 'run'
    base = ['--mode', 'static', '--demos', str(demos), '--no-progress']
    assert main(['--preset', str(tmp_path / 'warm.yaml'), '--out', str(run), *base]) == 0
    assert 'cgail train: BC warm start: 2 epochs, last loss' in capsys.readouterr().err
    # the normaliser was fitted to the 512 demonstration states (replacing the first reset's
    # num_envs observations), then saw the same env steps as a run without the warm start
    cold = dict(preset, bc={'strength': 0.0}, gail={'strength': 0.8})
    (tmp_path / 'cold.yaml').write_text(yaml.safe_dump(cold))
    assert main(['--preset', str(tmp_path / 'cold.yaml'), '--out', str(tmp_path / 'cold'),
                 *base]) == 0
    counts = [torch.as_tensor(load_checkpoint(r / 'final.pt')['normalizer']['count']).item()
              for r in (run, tmp_path / 'cold')]
    assert counts[0] - counts[1] == pytest.approx(512 - preset['num_envs'], abs=1e-3)
    assert main(['--resume', str(run), '--max-steps', '2048', *base]) == 0
    assert 'BC warm start' not in capsys.readouterr().err
    preset['bc'] = {'pretrain_epochs': -1}
    with pytest.raises(Exception, match=r'bc\.pretrain_epochs must be in \[0, 1000\], '
                                        r'found -1'):
        config_from_dict(preset)


# ----------------------------------------------------------------------------------------------
# Population bags: each episode names its anatomy and replays in it
@pytest.mark.slow
def test_a_population_bag_replays_each_episode_in_its_own_anatomy(tmp_path: Path):
    import dataclasses

    from cgail_learning.demo_bags import read_demo_bag
    from cgail_learning.demos_cli import record_population
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv
    from cgail_sim.population import sample_anatomy

    episodes, stats = record_population((0, 1), 3, seed=0)
    assert stats['success_rate'] == 1.0 and stats['anatomies'] == 2
    # episode k in anatomy k % 2, with start k % 3: grouped by anatomy in the bag
    assert [(e.anatomy, e.start) for e in episodes] == [
        ('population-0', 0), ('population-0', 2), ('population-1', 1)]
    assert episodes[2].anatomy_hash == sample_anatomy(1).content_hash
    write_demo_bag(tmp_path / 'p', episodes, anatomy='population', mode='static', dt=0.1,
                   population=True)
    meta, back = read_demo_bag(tmp_path / 'p')
    assert meta['population'] and meta['anatomy'] == 'population'
    assert [(e.anatomy, e.anatomy_hash) for e in back] == \
        [(e.anatomy, e.anatomy_hash) for e in episodes]
    replay = replay_demo_bag(tmp_path / 'p', env_options='sphere_targets')
    assert replay.report.max_drift_m == 0.0 and replay.report.same_anatomy
    assert len(replay.obs) == sum(len(e.alpha) for e in episodes)
    # the last episode's first observation is population-1's, with the sphere's d_max
    env = CatheterNavEnv(EnvConfig(anatomy=sample_anatomy(1), targets='sphere'))
    first, _ = env.reset(options={'start': 1, 'target': episodes[2].target})
    np.testing.assert_array_equal(replay.obs[-len(episodes[2].alpha)], first)
    # an episode that names the wrong anatomy does not replay
    swapped = [dataclasses.replace(episodes[2], anatomy='population-0')]
    write_demo_bag(tmp_path / 's', swapped, anatomy='population', mode='static', dt=0.1,
                   population=True)
    with pytest.raises(DemoError, match=r'\[population-0\]: episode 0: the recorded'):
        replay_demo_bag(tmp_path / 's')
    with pytest.raises(DemoError, match='a population bag re-simulates each episode in its own '
                                        "anatomy: expected no anatomy to re-simulate in, found "
                                        "'default'"):
        replay_demo_bag(tmp_path / 'p', anatomy='default')


def test_a_population_bag_holds_included_built_in_anatomies(tmp_path: Path, capsys):
    from cgail_learning.demos_cli import main, record_population

    episodes, stats = record_population((0,), 2, seed=0, include=('elongated',))
    assert stats['anatomies'] == 2
    assert [(e.anatomy, e.start) for e in episodes] == [('population-0', 0), ('elongated', 1)]
    write_demo_bag(tmp_path / 'p', episodes, anatomy='population', mode='static', dt=0.1,
                   population=True)
    replay = replay_demo_bag(tmp_path / 'p', env_options='sphere_targets')
    assert replay.report.max_drift_m == 0.0 and replay.report.episodes == 2
    with pytest.raises(ValueError, match=r"--include: expected distinct names of built-in or "
                                         r"real training anatomies \['default', 'elongated', "
                                         r"'avt-D2', .*, found \['aorta'\]"):
        record_population((0,), 2, include=('aorta',))
    with pytest.raises(ValueError, match=r"held-out real ones.*found \['avt-D18'\]"):
        record_population((0,), 2, include=('avt-D18',))
    assert main(['--include', 'elongated', '--out', str(tmp_path / 'x')]) == 2
    assert capsys.readouterr().err == ('cgail make-demos: error: --include: expected '
                                       '--population N beside it (it adds built-in anatomies '
                                       'to a population bag)\n')


def test_demonstrations_in_a_population_sample_named_by_its_seed(tmp_path: Path):
    """make_demos --anatomy population-<seed> (the fine-tuning recipe): the bag names the
    sample, records no path, and replays in it by name."""
    from cgail_learning.demos_cli import main

    assert main(['--anatomy', 'population-10003', '--episodes', '1', '--out',
                 str(tmp_path / 'd')]) == 0
    meta, _ = read_demo_bag(tmp_path / 'd')
    assert meta['anatomy'] == 'population-10003' and 'anatomy_path' not in meta
    replay = replay_demo_bag(tmp_path / 'd')
    assert replay.report.same_anatomy and replay.report.max_drift_m == 0.0


def test_a_population_bag_needs_every_episode_in_a_population_anatomy(tmp_path: Path):
    with pytest.raises(DemoError, match=r'population bag: expected every episode in a '
                                        r'population anatomy \(population-<seed>\) or a '
                                        r"built-in one \['default', 'elongated'\], found "
                                        r'episodes \[0\] without one'):
        write_demo_bag(tmp_path / 'x', [_episode()], anatomy='population', mode='static',
                       dt=0.1, population=True)

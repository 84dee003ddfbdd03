"""Demo bags: MCAP round trip, quaternions, errors; expert + re-simulation in the simulator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cgail_planner.learning.demo_bags import (
    DemoEpisode,
    load_demo_bag,
    read_demo_bag,
    rotation_to_quaternion,
    write_demo_bag,
)
from cgail_planner.learning.demos import load_demos
from cgail_planner.learning.errors import DemoError
from cgail_planner.learning.evaluate import kruskal, summarize, Trial


def _episode(n: int = 5, success: bool = True) -> DemoEpisode:
    rng = np.random.default_rng(n)
    q = rng.normal(size=(n, 4))
    return DemoEpisode(1, 3, rng.normal(size=n) * 0.01, rng.normal(size=n) * 0.01,
                       np.full(n, 5e-4), rng.normal(size=(n, 3)) * 0.1,
                       q / np.linalg.norm(q, axis=1, keepdims=True), rng.normal(size=(n, 3)),
                       success)


@pytest.mark.parametrize('compress', [False, True])
def test_demo_bag_round_trip(tmp_path: Path, compress: bool):
    if compress:
        pytest.importorskip('zstandard')
    eps = [_episode(5), _episode(7, success=False)]
    write_demo_bag(tmp_path / 'bag', eps, anatomy='default', mode='static', dt=0.1,
                   compress=compress)
    assert list((tmp_path / 'bag').glob('*.mcap'))
    meta, back = read_demo_bag(tmp_path / 'bag')
    assert meta == {'anatomy': 'default', 'mode': 'static'}
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


@pytest.mark.parametrize('angles', [(0.3, -1.2, 2.0), (3.1, 0.1, -0.2), (0.0, 0.0, 0.0),
                                    (np.pi, 0.0, 0.0)])
def test_rotation_to_quaternion(angles):
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler('xyz', angles).as_matrix()
    q = rotation_to_quaternion(R)
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)


def test_summary_and_kruskal():
    trials = [Trial(True, False, 100, 5.0), Trial(False, True, 40, 30.0),
              Trial(True, False, 120, 7.0)]
    s = summarize(trials)
    assert s['success_rate'] == pytest.approx(2 / 3) and s['T_s_succ'] == 110
    assert s['T_a_all_mm'] == 7.0 and s['collision_rate'] == pytest.approx(1 / 3)
    assert kruskal({'a': [1, 2, 3, 4, 5], 'b': [11, 12, 13, 14, 15]}) < 0.05
    assert np.isnan(kruskal({'a': [1.0], 'b': []}))


@pytest.mark.slow
def test_expert_demos_resimulate_in_the_simulator(tmp_path: Path):
    from cgail_planner.learning.demos_cli import record_episodes
    from cgail_planner.sim.config import EnvConfig
    from cgail_planner.sim.env import CatheterNavEnv

    env = CatheterNavEnv(EnvConfig(mode='static'))
    episodes, stats = record_episodes(env, 2, seed=0)
    assert stats['success_rate'] == 1.0
    write_demo_bag(tmp_path / 'd', episodes, anatomy='default', mode='static', dt=0.1)
    obs, act = load_demo_bag(tmp_path / 'd')
    assert obs.shape == (sum(len(e.alpha) for e in episodes), 41)
    assert np.all(np.abs(act) <= 1.0) and np.all(act[:, 2] > 0)
    episodes[0].tip_position[10] += 0.001
    write_demo_bag(tmp_path / 'e', episodes, anatomy='default', mode='static', dt=0.1)
    with pytest.raises(DemoError, match='episode 0 step 10'):
        load_demo_bag(tmp_path / 'e')

"""evaluate: simulated tracker noise, the observation of a perceived pose, independent trials."""

from __future__ import annotations

import numpy as np
import pytest

from cgail_learning.evaluate import (
    CenterlineFollower,
    observation_at,
    RrtFollower,
    run_trials,
    summarize,
    TrackingNoise,
)
from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv


@pytest.fixture(scope='module')
def static_env():
    return CatheterNavEnv(EnvConfig(mode='static'))


def env_for(mode: str) -> CatheterNavEnv:
    return CatheterNavEnv(EnvConfig(mode=mode))


def _angle(r: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))


@pytest.mark.parametrize('mode', ['static', 'dynamic'])
def test_observation_at_true_pose_is_the_env_observation(mode):
    env = env_for(mode)
    obs, _ = env.reset(seed=3, options={'start': 1, 'target': 2})
    rng = np.random.default_rng(0)
    for step in range(12):
        eng = env.unwrapped.engine
        mine = observation_at(env, eng.catheter.tip_position[0].copy(),
                              eng.catheter.tip_rotation[0].copy())
        np.testing.assert_allclose(mine, obs, atol=2e-6, err_msg=f'step {step}')
        obs, *_ = env.step(np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 1.0],
                                    dtype=np.float32))


def test_observation_of_a_moved_pose_moves_position_and_target_vector(static_env):
    obs, _ = static_env.reset(seed=0, options={'start': 0, 'target': 0})
    eng = static_env.engine
    p, r = eng.catheter.tip_position[0].copy(), eng.catheter.tip_rotation[0].copy()
    shifted = observation_at(static_env, p + np.array([0.001, 0.0, 0.0]), r)
    cfg, sc = eng.config, eng.scenarios
    assert shifted[0] - obs[0] == pytest.approx(0.001 / cfg.position_scale, rel=1e-4)
    assert shifted[13] - obs[13] == pytest.approx(-0.001 / sc.d_max, rel=1e-4)


def test_tracking_noise_has_the_stated_rms():
    noise = TrackingNoise()
    rng = np.random.default_rng(1)
    p, r = np.array([0.01, -0.02, 0.1]), np.eye(3)
    dp, ang = [], []
    for _ in range(4000):
        q, s = noise.perceive(p, r, rng)
        dp.append(np.linalg.norm(q - p))
        ang.append(_angle(s @ r.T))
        np.testing.assert_allclose(s @ s.T, np.eye(3), atol=1e-12)
    assert np.sqrt(np.mean(np.square(dp))) * 1e3 == pytest.approx(0.48, rel=0.05)
    assert np.degrees(np.sqrt(np.mean(np.square(ang)))) == pytest.approx(0.30, rel=0.05)


def test_zero_noise_is_the_true_pose_and_bad_values_are_named():
    p, r = np.array([1.0, 2.0, 3.0]), np.eye(3)
    q, s = TrackingNoise(0.0, 0.0).perceive(p, r, np.random.default_rng(0))
    assert np.array_equal(q, p) and np.array_equal(s, r)
    assert not TrackingNoise(0.0, 0.0).enabled
    with pytest.raises(ValueError, match='position_mm must be in'):
        TrackingNoise(position_mm=-1.0)
    with pytest.raises(ValueError, match='orientation_deg must be in'):
        TrackingNoise(orientation_deg=float('nan'))


def test_noisy_trials_of_one_pair_differ_and_reproduce(static_env):
    follower = CenterlineFollower(static_env)
    # 16 trials: trials 0 and 15 share start 0 x target 0
    a = run_trials(static_env, follower, 16, seed=100, noise=TrackingNoise())
    assert (a[0].timesteps, a[0].targeting_error_mm) != (a[15].timesteps,
                                                         a[15].targeting_error_mm)
    assert summarize(a)['distinct'] == 16
    ticks: list[int] = []  # (the progress bar's update: one tick as each trial ends)
    b = run_trials(static_env, follower, 16, seed=100, noise=TrackingNoise(),
                   on_trial=ticks.append)
    assert a == b and ticks == [1] * 16  # same seed, same trials, with or without progress
    ticks.clear()
    clean = run_trials(static_env, follower, 16, seed=100, reuse_pairs=True,
                       on_trial=ticks.append)
    assert clean[15] == clean[0] and summarize(clean)['distinct'] == 15
    assert ticks == [1] * 16  # a reused pair's trial counts too


def test_the_cli_writes_under_runs_and_can_hide_its_progress():
    from cgail_learning.evaluate import build_parser

    args = build_parser().parse_args([])
    assert str(args.out) == 'runs/evaluate' and not args.no_progress
    assert build_parser().parse_args(['--no-progress']).no_progress


def test_noisy_policy_sees_the_perceived_pose(static_env):
    seen: list[np.ndarray] = []

    def policy(obs: np.ndarray) -> np.ndarray:
        seen.append(obs.copy())
        return np.array([0.0, 0.0, 1.0], dtype=np.float32)

    run_trials(static_env, policy, 1, seed=5, noise=TrackingNoise(position_mm=2.0))
    eng = static_env.engine
    assert len(seen) > 3
    # the first perceived position differs from the start by about the noise, not exactly 0
    start = (eng.scenarios.starts[0].position - eng.scenarios.origin) / eng.config.position_scale
    err_mm = np.linalg.norm(seen[0][0:3] - start) * eng.config.position_scale * 1e3
    assert 0.0 < err_mm < 10.0


def test_rrt_method_follows_its_planned_path_and_reports_planning_time(static_env):
    rrt = RrtFollower(static_env)
    trials = run_trials(static_env, rrt, 3, seed=0, reuse_pairs=True)
    assert sum(t.success for t in trials) >= 2, trials
    # the default budget is host-independent: iterations, with a generous time limit
    assert rrt.rrt_config.time_limit_s >= 30.0
    assert all(t.plan_ms is not None and t.plan_ms > 0.0 for t in trials)
    s = summarize(trials)
    assert 0.0 < s['plan_ms_median'] <= s['plan_ms_max']
    # the path pursued is the plan: from the start to the target
    eng = static_env.engine
    assert rrt.path is not None and rrt.path[0] == pytest.approx(
        eng.scenarios.starts[2].position, abs=1e-9)
    assert np.linalg.norm(rrt.path[-1] - eng.target[0]) < 0.005
    # a method that does not plan reports none
    assert np.isnan(summarize(run_trials(static_env, CenterlineFollower(static_env), 1,
                                         seed=0))['plan_ms_median'])


def test_reuse_pairs_refuses_noise(static_env):
    with pytest.raises(ValueError, match='noise-free'):
        run_trials(static_env, CenterlineFollower(static_env), 2, seed=0, reuse_pairs=True,
                   noise=TrackingNoise())


def test_scenario_seed_selects_the_target_set_and_results_json_records_it(
        tmp_path, monkeypatch):
    import json

    from cgail_learning import evaluate
    import cgail_sim.env as sim_env

    built: list[EnvConfig] = []

    class Spy(CatheterNavEnv):
        def __init__(self, config: EnvConfig) -> None:
            built.append(config)
            super().__init__(config)

    monkeypatch.setattr(sim_env, 'CatheterNavEnv', Spy)
    assert evaluate.main(['--baselines', 'centerline', '--trials', '2', '--scenario-seed', '1',
                          '--out', str(tmp_path)]) == 0
    assert [c.scenario_seed for c in built] == [1]
    data = json.loads((tmp_path / 'results.json').read_text())
    assert (data['scenario_seed'], data['trials'], data['env_options']) == (1, 2, 'ours')
    entry = data['modes']['static']['centerline']
    assert entry['summary']['n'] == 2 and len(entry['trials']) == 2
    assert set(entry['trials'][0]) == {'success', 'collision', 'timesteps',
                                       'targeting_error_mm', 'plan_ms', 'fault'}
    assert 'of target set (scenario seed) 1.' in (tmp_path / 'report.md').read_text()


def test_several_anatomies_are_pooled_with_a_per_anatomy_table(tmp_path, capsys):
    """``--anatomy`` with several (here a shipped real aorta and a built-in one): the trials of
    each, pooled, with the per-anatomy table, as ``--population``; a bad one among them is
    refused in one line before anything runs."""
    import json

    from cgail_learning import evaluate

    assert evaluate.main(['--baselines', 'centerline', '--anatomy', 'avt-D18', 'elongated',
                          '--trials', '2', '--scenario-seed', '1', '--no-failure-pictures',
                          '--out', str(tmp_path)]) == 0
    data = json.loads((tmp_path / 'results.json').read_text())
    assert data['anatomies'] == ['avt-D18', 'elongated'] and 'population_seeds' not in data
    assert len(data['modes']['static']['centerline']['trials']) == 4
    assert set(data['per_anatomy_success']['static']['centerline']) == {'avt-D18', 'elongated'}
    report = (tmp_path / 'report.md').read_text()
    assert '2 anatomies (avt-D18, elongated), 2 trials per method per anatomy' in report
    assert '| avt-D18 |' in report and '| **all** [95% CI over anatomies] |' in report
    assert (tmp_path / 'per_anatomy_static.png').is_file()
    capsys.readouterr()
    assert evaluate.main(['--baselines', 'centerline', '--anatomy', 'avt-D18', 'nowhere',
                          '--out', str(tmp_path / 'bad')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('cgail evaluate: error: ') and err.count('\n') == 1 and 'nowhere' in err
    assert not (tmp_path / 'bad').exists()


def test_a_negative_scenario_seed_is_a_one_line_error(tmp_path, capsys):
    from cgail_learning import evaluate

    assert evaluate.main(['--baselines', '--trials', '1', '--scenario-seed', '-1',
                          '--out', str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err == 'cgail evaluate: error: scenario_seed must be an int >= 0, found -1\n'


def test_drawn_targets_give_every_method_the_same_new_target_per_trial():
    """``drawn``: trial k's target comes from seed + k in the 30 mm sphere (not the fixed
    set), the same for every method; an env with fixed targets refuses it in one line."""
    env = CatheterNavEnv(EnvConfig.from_options('sphere_targets', max_steps=5))
    fixed = {tuple(t.position) for t in env.engine.scenarios.targets}

    class Recorder:
        def __init__(self) -> None:
            self.targets: list[tuple[float, ...]] = []

        def reset(self, seed=None) -> None:
            self.targets.append(tuple(env.engine.target[0]))

        def act(self) -> np.ndarray:
            return np.array([0.0, 0.0, 1.0], np.float32)

    a, b = Recorder(), Recorder()
    trials = run_trials(env, a, 4, seed=11, drawn=True)
    run_trials(env, b, 4, seed=11, drawn=True)
    assert len(trials) == 4 and a.targets == b.targets
    assert len(set(a.targets)) == 4 and not set(a.targets) & fixed
    c = Recorder()
    run_trials(env, c, 4, seed=11)  # (without drawn: the fixed set's targets)
    assert set(c.targets) <= fixed
    with pytest.raises(ValueError, match=r"drawn targets need an env that draws them \(env "
                                         r"options sphere_targets\), found targets 'fixed'"):
        run_trials(CatheterNavEnv(EnvConfig(max_steps=5)), a, 1, seed=0, drawn=True)


def test_the_cli_draws_targets_and_says_so(tmp_path, capsys):
    import json

    from cgail_learning import evaluate

    assert evaluate.main(['--baselines', 'centerline', '--trials', '2', '--drawn-targets',
                          '--env-options', 'sphere_targets', '--out', str(tmp_path)]) == 0
    data = json.loads((tmp_path / 'results.json').read_text())
    assert data['drawn_targets'] is True and data['env_options'] == 'sphere_targets'
    assert "a target drawn anew from seed + k in the anatomy's 30 mm sphere" in (
        tmp_path / 'report.md').read_text()
    capsys.readouterr()
    assert evaluate.main(['--baselines', 'centerline', '--trials', '1', '--drawn-targets',
                          '--out', str(tmp_path / 'x')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('cgail evaluate: error: drawn targets need an env that draws them')
    assert err.count('\n') == 1


def test_trials_keep_their_tip_path_and_failures_are_drawn(static_env, tmp_path):
    """Each trial keeps its true tip path and target (not in results.json); a method that
    fails gets one picture of its first failures, linked at the end of the report; one that
    never fails gets none."""
    from cgail_learning import evaluate

    def into_the_wall(obs: np.ndarray) -> np.ndarray:  # full bend, full insertion
        return np.array([1.0, 0.0, 1.0])

    follower = CenterlineFollower(static_env)
    results = {'wall': run_trials(static_env, into_the_wall, 2, seed=5),
               'centerline': run_trials(static_env, follower, 1, seed=5)}
    for t in results['wall'] + results['centerline']:
        assert t.path.shape == (t.timesteps + 1, 3) and np.all(np.isfinite(t.path))
        assert t.target.shape == (3,)
    assert not any(t.success for t in results['wall']) and results['centerline'][0].success
    shown = evaluate.render_failures(static_env, results, 'static', tmp_path)
    assert [png for _, png in shown] == ['failures_static_default_wall.png']
    assert shown[0][0].startswith('wall, static, default: 2 of 2 trials failed')
    assert (tmp_path / shown[0][1]).stat().st_size > 10_000
    report = evaluate.write_report({'static': results}, tmp_path)
    evaluate._append_failures(report, {'static': shown})
    text = report.read_text()
    assert text.index('## Failures') > text.index('## static')
    assert '(failures_static_default_wall.png)' in text
    assert 'path' not in (tmp_path / 'results.json').read_text()

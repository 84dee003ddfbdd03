"""Training across the population: the disjoint seed split, the per-worker anatomy env, the
generalist preset."""

import dataclasses

import numpy as np
import pytest

from cgail_learning.config import config_to_dict, load_config, PopulationConfig
from cgail_learning.envs import AnatomyCycleEnv, PopulationVecEnv
from cgail_learning.errors import ConfigError
from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv
from cgail_sim.population import (
    check_training_seeds,
    HELD_OUT_SEEDS,
    population_name,
    population_seed,
    split_seeds,
    TRAINING_SEEDS,
)
from cgail_sim.vec_env import CatheterNavVecEnv


# ------------------------------------------------------------------ the split
def test_training_and_held_out_seeds_are_disjoint_named_ranges() -> None:
    assert (TRAINING_SEEDS.start, TRAINING_SEEDS.stop) == (0, 10_000)
    assert (HELD_OUT_SEEDS.start, HELD_OUT_SEEDS.stop) == (10_000, 20_000)
    assert not set(TRAINING_SEEDS) & set(HELD_OUT_SEEDS)
    assert split_seeds("held_out", 3) == (10_000, 10_001, 10_002)
    assert split_seeds("train", 2) == (0, 1)


def test_a_held_out_seed_is_refused_for_training() -> None:
    assert check_training_seeds([0, 9_999]) == (0, 9_999)
    with pytest.raises(ValueError, match=r"training population seeds must lie in \[0, 10000\) "
                                         r"\(the held-out ones are \[10000, 20000\)\), found "
                                         r"\[10005\]"):
        check_training_seeds([3, 10_005])


@pytest.mark.parametrize(("split", "count", "match"), [
    ("test", 1, r"split must be one of \['held_out', 'train'\], found 'test'"),
    ("train", 0, r"count must be an int in \[1, 10000\], found 0"),
    ("held_out", 10_001, r"count must be an int in \[1, 10000\], found 10001"),
])
def test_bad_split_requests_are_one_line(split: str, count: int, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        split_seeds(split, count)


def test_population_names_round_trip() -> None:
    assert population_seed(population_name(17)) == 17
    assert population_seed("default") is None and population_seed("population-x") is None


def test_the_population_config_trains_and_selects_on_training_seeds_only() -> None:
    train, select = PopulationConfig(anatomies=32, eval_anatomies=5).seeds()
    assert train == tuple(range(32)) and select == tuple(range(32, 37))
    assert not (set(train) | set(select)) & set(HELD_OUT_SEEDS)
    assert not PopulationConfig().enabled


@pytest.mark.parametrize(("data", "match"), [
    ({"anatomies": -1}, r"population.anatomies must be in \[0, 1000\], found -1"),
    ({"redraw_every": 0}, r"population.redraw_every must be >= 1, found 0"),
    ({"eval_anatomies": 0}, r"population.eval_anatomies must be in \[1, 100\], found 0"),
    ({"anatomies": 4, "include": ["default", "default"]},
     r"population.include must be distinct names of built-in or real training anatomies "
     r"\['default', 'elongated', 'avt-D2', .*, found \['default', 'default'\]"),
    ({"anatomies": 4, "include": ["population-3"]}, r"population.include must be distinct "
                                                     r"names of built-in or real training"),
    ({"anatomies": 4, "include": ["avt-D4"]},
     r"\(the held-out real ones, \['avt-D4', .*\], never train\), found \['avt-D4'\]"),
    ({"anatomies": 4, "include": [3]}, r"population.include must be of type tuple, found \[3\]"),
    ({"include_weight": 0.5}, r"population.include_weight must be in \[1, 1000\], found 0.5"),
    ({"include": ["elongated"]}, r"population.include must be no anatomies without a population"),
])
def test_bad_population_settings_are_one_line(data: dict, match: str) -> None:
    from cgail_learning.config import config_from_dict

    with pytest.raises(ConfigError, match=match):
        config_from_dict({"population": data})


# ------------------------------------------------------------------ the preset
def test_the_generalist_preset_is_cgail_on_the_population_with_drawn_targets() -> None:
    gen, cgail = load_config("generalist"), load_config("cgail")
    assert gen.env_options == "sphere_targets"
    assert (gen.population.anatomies, gen.population.redraw_every,
            gen.population.eval_anatomies, gen.population.include,
            gen.population.include_weight) == (128, 4, 5, ("default", "elongated"), 20.0)
    assert gen.population.eval_include
    assert (gen.max_steps, gen.eval_every, gen.eval_episodes) == (5_000_000, 204_800, 70)
    # the C-GAIL mechanics (reward signals, strengths, PPO, curriculum) are the cgail preset's;
    # only the run's size and its periodic evaluation differ
    a, b = config_to_dict(gen), config_to_dict(cgail)
    for key in ("name", "env_options", "population", "max_steps", "eval_every",
                "eval_episodes"):
        a.pop(key), b.pop(key)
    assert a == b


def test_the_generalist_real_preset_is_the_generalist_with_the_real_training_aortas() -> None:
    from cgail_sim.anatomy_spec import REAL_HELD_OUT, TRAINING_NAMES

    real, gen = load_config("generalist_real"), load_config("generalist")
    assert real.population.include == TRAINING_NAMES  # built-ins, then every real one not held out
    assert not set(real.population.include) & set(REAL_HELD_OUT)
    a, b = config_to_dict(real), config_to_dict(gen)
    a.pop("name"), b.pop("name"), a["population"].pop("include"), b["population"].pop("include")
    assert a == b


def test_the_finetune_preset_is_the_generalist_in_one_anatomy_for_a_short_run() -> None:
    ft, gen = load_config("finetune"), load_config("generalist")
    assert not ft.population.enabled and ft.env_options == gen.env_options  # same observation
    assert (ft.max_steps, ft.ppo.learning_rate, ft.curriculum.theta_max_deg) == (300_000, 1e-4, ())
    a, b = config_to_dict(ft), config_to_dict(gen)
    for key in ("name", "max_steps", "eval_every", "eval_episodes", "curriculum", "population"):
        a.pop(key), b.pop(key)
    a["ppo"].pop("learning_rate"), b["ppo"].pop("learning_rate")
    assert a == b


# ------------------------------------------------------------------ the env
ANATOMIES = ["default", "elongated"]


def _population_env(redraw_every: int = 1, n: int = 3) -> PopulationVecEnv:
    return PopulationVecEnv(lambda a: CatheterNavVecEnv(EnvConfig(anatomy=a, targets="sphere"), 1),
                            ANATOMIES, n, redraw_every)


def _run(env: PopulationVecEnv, steps: int, seed: int = 7) -> tuple[list, list]:
    obs = [env.reset(seed=seed)]
    moves = []
    rng = np.random.default_rng(0)
    for _ in range(steps):
        act = rng.uniform(-1.0, 1.0, size=(env.num_envs, 3)).astype(np.float32)
        act[:, 2] = 1.0  # forwards: episodes end by collision within ~100 steps
        before = list(env.current)
        o, _, term, trunc, infos = env.step(act)
        obs.append(o)
        for i in np.flatnonzero(term | trunc).tolist():
            assert infos[i]["anatomy"] == before[i]
            moves.append((i, before[i], env.current[i]))
    return obs, moves


def test_workers_draw_their_anatomies_from_the_pool_reproducibly() -> None:
    env = _population_env()
    obs, moves = _run(env, 400)
    assert len(moves) >= 6
    assert {a for _, a, _ in moves} == {0, 1}           # both anatomies were used
    assert any(a != b for _, a, b in moves)             # and workers moved between them
    obs2, moves2 = _run(_population_env(), 400)
    assert moves2 == moves
    for a, b in zip(obs, obs2, strict=True):
        np.testing.assert_array_equal(a, b)


def test_after_a_redraw_a_worker_observes_its_new_anatomy() -> None:
    env = _population_env()
    env.reset(seed=3)
    rng = np.random.default_rng(1)
    for _ in range(400):
        act = rng.uniform(-1.0, 1.0, size=(3, 3)).astype(np.float32)
        act[:, 2] = 1.0
        before = list(env.current)
        obs, _, term, trunc, _ = env.step(act)
        moved = [i for i in np.flatnonzero(term | trunc).tolist() if env.current[i] != before[i]]
        if moved:
            i = moved[0]
            part = env.parts[i]
            assert part.config.anatomy == ANATOMIES[env.current[i]]
            np.testing.assert_array_equal(obs[i], part.engine.observe()[0])
            return
    pytest.fail("no worker moved to another anatomy within 400 steps")


def test_redraw_every_holds_a_worker_in_its_anatomy() -> None:
    env = _population_env(redraw_every=1000)
    _, moves = _run(env, 300)
    assert moves and all(a == b for _, a, b in moves)


def test_theta_max_reaches_the_envs_built_at_later_redraws() -> None:
    env = _population_env()
    env.set_theta_max(1.0)
    _, moves = _run(env, 300, seed=0)
    assert any(a != b for _, a, b in moves)  # (new envs were built)
    assert all(p.engine.catheter.theta_max == 1.0 for p in env.parts)


def test_weights_make_a_worker_draw_an_anatomy_that_much_more_often() -> None:
    env = PopulationVecEnv(lambda a: CatheterNavVecEnv(EnvConfig(anatomy=a, targets="sphere"), 1),
                           ANATOMIES, 1, 1, weights=[1.0, 9.0])
    env.reset(seed=0)
    drawn = []
    for _ in range(400):
        env._redraw(0)
        drawn.append(env.current[0])
    # 9 in 10 draws are elongated: 400 draws give 360 +- 6 (binomial std); 320 is 6.7 std off
    assert 320 < sum(drawn) < 400


def test_bad_population_env_arguments_are_one_line() -> None:
    def make(a):
        return CatheterNavVecEnv(EnvConfig(anatomy=a), 1)

    with pytest.raises(ValueError, match="anatomies must hold at least one anatomy, found none"):
        PopulationVecEnv(make, [], 2)
    with pytest.raises(ValueError, match="redraw_every must be an int >= 1, found 0"):
        PopulationVecEnv(make, ANATOMIES, 2, 0)
    with pytest.raises(ValueError, match="make_part must build a one-env batched env, found 4"):
        PopulationVecEnv(lambda a: CatheterNavVecEnv(EnvConfig(anatomy=a), 2), ANATOMIES, 2)
    with pytest.raises(ValueError, match=r"weights must be 2 finite numbers > 0 \(one per "
                                         r"anatomy\), found \[1.0, 0.0\]"):
        PopulationVecEnv(make, ANATOMIES, 2, 1, weights=[1.0, 0.0])


def test_the_evaluation_env_cycles_through_its_anatomies() -> None:
    env = AnatomyCycleEnv([CatheterNavEnv(EnvConfig(anatomy=a)) for a in ANATOMIES])
    for seed in (10, 11, 12):
        env.reset(seed=seed)
        assert env._env.anatomy.name == ANATOMIES[seed % 2]
    obs, *_ = env.step(np.zeros(3, np.float32))
    assert obs.shape == env.observation_space.shape


def test_a_negative_held_out_count_is_one_line(tmp_path, capsys) -> None:
    from cgail_learning import evaluate

    assert evaluate.main(['--baselines', 'centerline', '--population', '-1',
                          '--out', str(tmp_path)]) == 2
    assert capsys.readouterr().err == ('cgail evaluate: error: --population must be >= 0 '
                                       '(held-out anatomies), found -1\n')


def test_train_refuses_an_anatomy_with_a_population_preset(capsys) -> None:
    from cgail_learning import train

    assert train.main(['--preset', 'generalist', '--anatomy', 'elongated']) == 2
    assert capsys.readouterr().err == (
        "cgail train: error: --anatomy: preset 'generalist' trains on 128 population anatomies "
        "and default and elongated: expected no --anatomy, found 'elongated'\n")


def test_the_pool_holds_the_included_built_in_anatomies(monkeypatch) -> None:
    from cgail_learning.train import make_envs
    from cgail_sim.anatomy_spec import resolve_anatomy
    import cgail_sim.population as population

    built: list[int] = []
    monkeypatch.setattr(population, "sample_anatomy",
                        lambda s: built.append(s) or resolve_anatomy("default"))
    env, _, meta = make_envs("static", "default", 3, "sphere_targets",
                              PopulationConfig(anatomies=2, eval_anatomies=1,
                                               include=("elongated",), include_weight=4))
    assert built == [0, 1, 2]  # 2 training samples, then 1 selection sample
    assert [a.name for a in env.anatomies] == ["default", "default", "elongated"]
    assert meta["population"]["include"] == ["elongated"]
    np.testing.assert_allclose(env._p, [1 / 6, 1 / 6, 4 / 6])


def test_the_selection_can_run_the_included_built_in_anatomies_too(monkeypatch) -> None:
    from cgail_learning.train import make_envs
    from cgail_sim.anatomy_spec import resolve_anatomy
    import cgail_sim.population as population

    monkeypatch.setattr(population, "sample_anatomy", lambda s: resolve_anatomy("default"))
    cfg = PopulationConfig(anatomies=2, eval_anatomies=1, include=("elongated",))
    _, plain, _ = make_envs("static", "default", 2, "sphere_targets", cfg)
    _, both, meta = make_envs("static", "default", 2, "sphere_targets",
                              dataclasses.replace(cfg, eval_include=True))
    assert [e.config.anatomy.name for e in plain.envs] == ["default"]
    assert [e.config.anatomy.name for e in both.envs] == ["default", "elongated"]
    both.reset(seed=7)  # odd evaluation seeds run elongated
    assert both._env is both.envs[1] and meta["population"]["eval_include"] is True
    with pytest.raises(ValueError, match=r"population.eval_include must be false without "
                                         r"population.include, found True"):
        PopulationConfig(anatomies=2, eval_include=True)


def test_demonstrations_refuse_a_held_out_anatomy() -> None:
    from cgail_learning.demos_cli import record_population

    with pytest.raises(ValueError, match=r"training population seeds must lie in \[0, 10000\)"):
        record_population((0, 10_000), 2)

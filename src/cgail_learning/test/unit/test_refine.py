"""``refine``: DAgger refinement of a population run's checkpoint on its own training
distribution (targets drawn per episode), validated like ``train``'s checkpoints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cgail_learning.config import (
    config_from_dict,
    config_to_dict,
    load_config,
    PopulationConfig,
)
from cgail_learning.dagger import expert_labels
from cgail_learning.errors import LearningError
from cgail_learning.refine import label_anatomies, main, refine, RefineOptions
from cgail_sim.anatomy_spec import resolve_anatomy
from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv


def test_labels_in_an_env_that_draws_its_targets_draw_one_per_episode() -> None:
    env = CatheterNavEnv(EnvConfig.from_options('sphere_targets', anatomy='default',
                                                max_steps=30))
    targets = []
    real_reset = env.reset

    def reset(**kw):
        out = real_reset(**kw)
        targets.append((env.engine.target_id[0], env.engine.target[0].copy()))
        return out

    env.reset = reset  # type: ignore[method-assign]
    _, _, stats = expert_labels(env, lambda o: np.array([0.0, 0.0, 1.0], np.float32), 3, seed=2)
    assert stats['episodes'] == 3
    assert [t for t, _ in targets] == [-1, -1, -1]  # drawn, not one of the fixed set
    assert not np.allclose(targets[0][1], targets[1][1])
    # the same seed draws the same targets
    first = [p for _, p in targets]
    targets.clear()
    expert_labels(env, lambda o: np.array([0.0, 0.0, 1.0], np.float32), 3, seed=2)
    np.testing.assert_array_equal(np.stack(first), np.stack([p for _, p in targets]))


def test_the_labelled_anatomies_are_evenly_spaced_training_seeds_and_the_built_ins(
        monkeypatch) -> None:
    import cgail_sim.population as population

    monkeypatch.setattr(population, 'sample_anatomy', lambda s: f'seed-{s}')
    pop = PopulationConfig(anatomies=8, eval_anatomies=1, include=('elongated',),
                           include_weight=4)
    got = label_anatomies(pop, RefineOptions(anatomies=4, episodes=2))
    assert got == [('seed-0', 2), ('seed-2', 2), ('seed-4', 2), ('seed-6', 2),
                   ('elongated', 8)]
    # more than the run has: each of its training seeds once; none: the built-ins only
    assert [a for a, _ in label_anatomies(pop, RefineOptions(anatomies=100))][:8] == [
        f'seed-{s}' for s in range(8)]
    assert label_anatomies(pop, RefineOptions(anatomies=0, episodes=3)) == [('elongated', 12)]


@pytest.mark.parametrize('kw, match', [
    ({'rounds': 0}, r'rounds must be an int in \[1, 10\], found 0'),
    ({'episodes': 0}, r'episodes must be an int in \[1, 1000\], found 0'),
    ({'every': 1.5}, r'every must be an int in \[1, 1000\], found 1.5'),
    ({'validation_episodes': -1}, r'validation_episodes must be an int in \[0, 10000\], '
                                  r'found -1'),
])
def test_bad_options_are_one_line(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        RefineOptions(**kw)


def _population_checkpoint(tmp: Path, monkeypatch, population: bool = True) -> Path:
    """A tiny population run's checkpoint (the smoke preset's networks, 2 training anatomies
    and 1 selection anatomy, all the built-in default one) and random demonstrations."""
    from cgail_learning.train import make_envs
    from cgail_learning.trainer import Trainer
    import cgail_sim.population as pop_mod

    monkeypatch.setattr(pop_mod, 'sample_anatomy', lambda s: resolve_anatomy('default'))
    d = config_to_dict(load_config('smoke'))
    d.update(num_envs=2, eval_episodes=2, env_options='sphere_targets')
    if population:
        d['population'] = {'anatomies': 2, 'eval_anatomies': 1, 'redraw_every': 1}
    cfg = config_from_dict(d)
    env, _, meta = make_envs('static', 'default', cfg.num_envs, cfg.env_options,
                             cfg.population)
    rng = np.random.default_rng(0)
    dim = env.single_observation_space.shape[0]
    demo_obs = rng.uniform(-1, 1, (256, dim)).astype(np.float32)
    demo_act = np.tile([0.0, 0.0, 1.0], (256, 1)).astype(np.float32)
    np.savez(tmp / 'demos.npz', obs=demo_obs, act=demo_act, episodes=4)
    trainer = Trainer(cfg, env, demo_obs=demo_obs, demo_act=demo_act, demo_episodes=4, seed=3,
                      metadata=meta)
    trainer.save(tmp / 'best.pt')
    return tmp / 'best.pt'


def test_refine_labels_the_policys_states_clones_them_and_keeps_the_contract(
        tmp_path, monkeypatch) -> None:
    import torch

    from cgail_learning.checkpoint import load_checkpoint
    from cgail_learning.export import export_checkpoint
    from cgail_planner.core.onnx_policy import OnnxPolicy

    ckpt = _population_checkpoint(tmp_path, monkeypatch)
    out = tmp_path / 'refined'
    summary = refine(ckpt, [str(tmp_path / 'demos.npz')], out,
                     RefineOptions(rounds=2, anatomies=1, episodes=1, every=50, epochs=1),
                     progress=False, log=lambda line: None)
    assert [r['round'] for r in summary['rounds']] == [1, 2]
    first, second = summary['rounds']
    assert 0 < first['labels'] < second['labels']  # DAgger aggregates the rounds' labels
    assert set(first['policy_success']) == {'population'}
    for f in ('round_1.pt', 'round_2.pt', 'refined.pt', 'refine.yaml'):
        assert (out / f).is_file()
    # refined.pt: the best validation of the checkpoint (round 0) and the rounds, latest on ties
    rates = [summary['base_validation'], first['validation'], second['validation']]
    chosen = summary['chosen']
    assert chosen == max(range(3), key=lambda r: (rates[r], r))
    assert summary['validation'] == rates[chosen]
    refined = load_checkpoint(out / 'refined.pt')
    base = load_checkpoint(ckpt)
    assert refined['step'] == base['step'] and refined['config'] == base['config']
    assert chosen, rates  # (the untrained policy validates at 0 %: a round ties or beats it)
    if chosen:
        assert refined['metadata']['refinement']['round'] == chosen
        assert not torch.equal(refined['actor']['mu.weight'], base['actor']['mu.weight'])
        # the run's normaliser is kept: the labels do not move it
        torch.testing.assert_close(refined['normalizer']['mean'], base['normalizer']['mean'])
        onnx_path = export_checkpoint(out / 'refined.pt', tmp_path / 'refined.onnx')
        contract = OnnxPolicy(onnx_path).contract
        assert contract.anatomies == 'population'
        assert contract.training['refinement']['method'] == 'dagger'
    # the same seed refines to the same weights
    again = refine(ckpt, [str(tmp_path / 'demos.npz')], tmp_path / 'again',
                   RefineOptions(rounds=1, anatomies=1, episodes=1, every=50, epochs=1),
                   progress=False, log=lambda line: None)
    assert again['rounds'][0]['labels'] == first['labels']
    torch.testing.assert_close(load_checkpoint(tmp_path / 'again' / 'round_1.pt')['actor'],
                               load_checkpoint(out / 'round_1.pt')['actor'])


def test_labels_cut_into_chunks_equal_the_labels_of_one_call() -> None:
    """``first``: consecutive chunks of a collection label what one call labels (what lets
    ``refine --jobs`` spread an anatomy's episodes over worker processes)."""
    env = CatheterNavEnv(EnvConfig.from_options('sphere_targets', anatomy='default'))
    policy = lambda o: np.array([0.3, -0.2, 1.0], np.float32)  # noqa: E731
    whole = expert_labels(env, policy, 5, seed=7, every=9)
    parts = [expert_labels(env, policy, 2, seed=7, every=9, first=0),
             expert_labels(CatheterNavEnv(EnvConfig.from_options('sphere_targets',
                                                                 anatomy='default')),
                           policy, 3, seed=7, every=9, first=2)]
    np.testing.assert_array_equal(whole[0], np.concatenate([p[0] for p in parts]))
    np.testing.assert_array_equal(whole[1], np.concatenate([p[1] for p in parts]))
    assert whole[2]['episodes'] == 5 == sum(p[2]['episodes'] for p in parts)
    with pytest.raises(ValueError, match=r'first must be an int >= 0, found -1'):
        expert_labels(env, policy, 1, first=-1)


def test_refine_in_worker_processes_labels_and_refines_as_in_one(tmp_path, monkeypatch) -> None:
    """``jobs``: the episodes are driven in worker processes, one chunk of episodes each
    (here one episode per chunk), and the round's labels and weights are those of one process."""
    from cgail_learning.checkpoint import load_checkpoint
    import cgail_learning.refine as refine_mod

    ckpt = _population_checkpoint(tmp_path, monkeypatch)
    monkeypatch.setattr(refine_mod, '_CHUNK', 1)
    runs = {}
    for jobs in (1, 2):
        runs[jobs] = refine(ckpt, [str(tmp_path / 'demos.npz')], tmp_path / f'j{jobs}',
                            RefineOptions(anatomies=1, episodes=3, every=50, epochs=1,
                                          jobs=jobs),
                            progress=False, log=lambda line: None)
    one, two = runs[1]['rounds'][0], runs[2]['rounds'][0]
    assert one['labels'] == two['labels'] > 0
    assert one['policy_success'] == two['policy_success']
    torch_actor = [load_checkpoint(tmp_path / f'j{j}' / 'round_1.pt')['actor'] for j in (1, 2)]
    import torch

    torch.testing.assert_close(torch_actor[0], torch_actor[1])


def test_refine_refuses_what_it_cannot_use_in_one_line(tmp_path, monkeypatch, capsys) -> None:
    assert main([str(tmp_path / 'nope.pt'), '--demos', 'x', '--out', str(tmp_path / 'o')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('cgail refine: error: checkpoint not found: expected a file at ')
    assert err.count('\n') == 1
    one = _population_checkpoint(tmp_path, monkeypatch, population=False)
    assert main([str(one), '--demos', str(tmp_path / 'demos.npz'), '--out',
                 str(tmp_path / 'o')]) == 2
    err = capsys.readouterr().err
    assert 'expected a checkpoint of a population preset (generalist), found preset' in err
    assert err.count('\n') == 1
    assert main([str(one), '--rounds', '0', '--out', str(tmp_path / 'o')]) == 2
    assert 'rounds must be an int in [1, 10], found 0' in capsys.readouterr().err


def _one_anatomy_preset(tmp: Path) -> Path:
    """The smoke preset's networks with drawn targets, as a YAML preset file."""
    import yaml

    d = config_to_dict(load_config('smoke'))
    d.update(num_envs=2, eval_episodes=2, env_options='sphere_targets', name='smoke_sphere')
    path = tmp / 'smoke_sphere.yaml'
    path.write_text(yaml.safe_dump(d))
    return path


def test_refine_in_one_anatomy_fine_tunes_an_exported_policy(tmp_path, monkeypatch) -> None:
    """``--anatomy``: the exported policy's actor and normaliser, refined in that anatomy, give
    a one-anatomy checkpoint of it; a round that validates worse than the policy as it came
    leaves refined.pt that policy."""
    import torch

    from cgail_learning.checkpoint import load_checkpoint
    from cgail_learning.export import export_checkpoint
    import cgail_learning.trainer as trainer_mod
    from cgail_planner.core.onnx_policy import OnnxPolicy

    onnx_path = export_checkpoint(_population_checkpoint(tmp_path, monkeypatch),
                                  tmp_path / 'gen.onnx')
    preset = _one_anatomy_preset(tmp_path)
    demos = [str(tmp_path / 'demos.npz')]
    opts = RefineOptions(episodes=2, every=50, epochs=2)
    summary = refine(onnx_path, demos, tmp_path / 'ft', opts, progress=False,
                     log=lambda line: None, anatomy='elongated', preset=str(preset))
    assert summary['rounds'][0]['labels'] > 0
    assert set(summary['rounds'][0]['policy_success']) == {'elongated'}
    ckpt = load_checkpoint(tmp_path / 'ft' / 'round_1.pt')
    assert ckpt['config']['name'] == 'smoke_sphere'
    contract = ckpt['metadata']['catheter_contract']
    assert contract['anatomy'] == 'elongated' and 'anatomies' not in contract  # (one)
    # worse validation than the policy as it came: refined.pt is that policy, a checkpoint
    rates = iter([1.0, 0.5])
    episodes: list[int] = []

    def fake_validation(policy, env, n, seed):
        episodes.append(n)
        return {'eval/success_rate': next(rates)}

    monkeypatch.setattr(trainer_mod, 'evaluate_policy', fake_validation)
    kept = refine(onnx_path, demos, tmp_path / 'kept',
                  RefineOptions(episodes=2, every=50, epochs=2, validation_episodes=7),
                  progress=False, log=lambda line: None, anatomy='elongated',
                  preset=str(preset))
    assert (kept['chosen'], kept['validation']) == (0, 1.0)
    assert episodes == [7, 7]  # (--validation-episodes: not the preset's eval_episodes, 2)
    refined = load_checkpoint(tmp_path / 'kept' / 'refined.pt')
    assert 'refinement' not in refined['metadata']
    obs = np.random.default_rng(1).uniform(-1, 1, (8, 41)).astype(np.float32)
    export_checkpoint(tmp_path / 'kept' / 'refined.pt', tmp_path / 'kept.onnx')
    np.testing.assert_allclose(OnnxPolicy(tmp_path / 'kept.onnx')(obs),
                               OnnxPolicy(onnx_path)(obs), atol=1e-5)
    assert not torch.equal(load_checkpoint(tmp_path / 'kept' / 'round_1.pt')['actor']['mu.bias'],
                           refined['actor']['mu.bias'])


def test_refine_in_one_anatomy_refuses_what_it_cannot_use_in_one_line(tmp_path,
                                                                        capsys) -> None:
    preset = _one_anatomy_preset(tmp_path)
    base = ['--demos', 'x.npz', '--out', str(tmp_path / 'o')]
    cases = [
        ([str(tmp_path / 'gen.onnx'), '--anatomy', 'default', '--preset', str(preset)],
         'policy not found: expected an exported .onnx at '),
        ([str(tmp_path / 'gen.onnx'), '--anatomy', 'nowhere'], 'nowhere'),
    ]
    for args, want in cases:
        assert main(args + base) == 2
        err = capsys.readouterr().err
        assert err.startswith('cgail refine: error: ') and want in err, err
        assert err.count('\n') == 1, err
    (tmp_path / 'gen.onnx').write_bytes(b'not onnx')
    assert main([str(tmp_path / 'gen.onnx'), '--anatomy', 'default', '--preset',
                 'generalist', *base]) == 2
    err = capsys.readouterr().err
    assert "expected a one-anatomy preset with --anatomy (finetune), found 'generalist'" in err


def test_refine_an_exported_population_policy_in_its_presets_population(tmp_path,
                                                                         monkeypatch) -> None:
    """An exported generalist (no checkpoint) refined without ``--anatomy``: the preset gives
    the population, the labels come from its anatomies, and the result keeps a population
    contract; a one-anatomy preset is refused in one line."""
    import yaml

    from cgail_learning.checkpoint import load_checkpoint
    from cgail_learning.export import export_checkpoint
    from cgail_planner.core.onnx_policy import OnnxPolicy

    ckpt = _population_checkpoint(tmp_path, monkeypatch)
    onnx_path = export_checkpoint(ckpt, tmp_path / 'gen.onnx')
    preset = tmp_path / 'smoke_population.yaml'
    preset.write_text(yaml.safe_dump({**load_checkpoint(ckpt)['config'],
                                      'name': 'smoke_population'}))
    summary = refine(onnx_path, [str(tmp_path / 'demos.npz')], tmp_path / 'r',
                     RefineOptions(anatomies=2, episodes=1, every=50, epochs=2),
                     progress=False, log=lambda line: None, preset=str(preset))
    assert summary['rounds'][0]['labels'] > 0
    assert set(summary['rounds'][0]['policy_success']) == {'population'}
    done = load_checkpoint(tmp_path / 'r' / 'round_1.pt')
    assert done['config']['name'] == 'smoke_population'
    assert done['metadata']['catheter_contract']['anatomies'] == 'population'
    assert done['metadata']['demonstrations'] and done['metadata']['refinement']['round'] == 1
    exported = export_checkpoint(tmp_path / 'r' / 'round_1.pt', tmp_path / 'r.onnx')
    assert OnnxPolicy(exported).contract.anatomies == 'population'
    with pytest.raises(LearningError, match=r'expected a population preset \(generalist\) to '):
        refine(onnx_path, [str(tmp_path / 'demos.npz')], tmp_path / 'x', progress=False,
               log=lambda line: None, preset=str(_one_anatomy_preset(tmp_path)))


def test_refine_labels_episodes_in_the_beating_aorta_too(tmp_path, monkeypatch) -> None:
    """``dynamic_episodes``: that many more episodes per named anatomy, in the beating aorta,
    counted as their own group; 0 (the default) adds none."""
    from cgail_learning.export import export_checkpoint

    onnx_path = export_checkpoint(_population_checkpoint(tmp_path, monkeypatch),
                                  tmp_path / 'gen.onnx')
    preset = _one_anatomy_preset(tmp_path)
    demos = [str(tmp_path / 'demos.npz')]
    both = refine(onnx_path, demos, tmp_path / 'dyn',
                  RefineOptions(episodes=1, every=50, epochs=1, dynamic_episodes=1),
                  progress=False, log=lambda line: None, anatomy='default', preset=str(preset))
    static = refine(onnx_path, demos, tmp_path / 'static',
                    RefineOptions(episodes=1, every=50, epochs=1),
                    progress=False, log=lambda line: None, anatomy='default', preset=str(preset))
    assert set(both['rounds'][0]['policy_success']) == {'default', 'default dynamic'}
    assert set(static['rounds'][0]['policy_success']) == {'default'}
    assert both['rounds'][0]['labels'] > static['rounds'][0]['labels']
    with pytest.raises(ValueError, match=r'dynamic_episodes must be an int in \[0, 1000\]'):
        RefineOptions(dynamic_episodes=-1)

"""Every command line takes an anatomy as a name or a path (issue 12): cgail make-demos, train,
evaluate, export-onnx, render and session; a bad one is one line and exit status 2 (the nodes:
test/node/test_anatomy_nodes.py)."""

from __future__ import annotations

import json
from pathlib import Path
import shutil

import onnx
import pytest

from cgail_learning import demos_cli, evaluate, export, train
from cgail_learning.demos import load_demos
from cgail_learning.errors import DemoError
from cgail_rig import session
from cgail_sim import render
from cgail_sim.anatomy import build_anatomy
from cgail_sim.anatomy_spec import resolve_anatomy
from cgail_sim.config import EnvConfig
from cgail_sim.ftl_model import CONTRACT_KEY, PolicyContract

FIXTURES = Path(__file__).resolve().parents[3] / 'cgail_planner' / 'test' / 'fixtures'


PREPARED_FROM = 'elongated'  # (the prepared fixture's aorta, cgail_sim.testing)


def _commands(tmp_path: Path) -> dict[str, tuple]:
    out = tmp_path / 'out'
    return {
        'make-demos': (demos_cli.main, ['--episodes', '1', '--out', str(out)]),
        'train': (train.main, ['--preset', 'smoke', '--no-progress', '--out', str(out)]),
        'evaluate': (evaluate.main, ['--trials', '1', '--out', str(out)]),
        'export-onnx': (export.main, [str(FIXTURES / 'straight_policy.onnx'), '--add-contract',
                                      '--out', str(tmp_path / 'p.onnx')]),
        'render': (render.main, ['--out', str(tmp_path / 'a.png')]),
        'session': (session.main, ['--trials', '1', '--out', str(out)]),
    }


@pytest.mark.parametrize('verb', ['make-demos', 'train', 'evaluate', 'export-onnx', 'render',
                                  'session'])
def test_a_bad_anatomy_is_one_line_and_exit_status_2(tmp_path, capsys, bad_anatomy,
                                                     verb) -> None:
    spec, text = bad_anatomy
    main, argv = _commands(tmp_path)[verb]
    assert main([*argv, '--anatomy', str(spec)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith(f'cgail {verb}: error: ') and text in err, err
    assert not (tmp_path / 'out').exists()


def test_make_demos_records_the_label_hash_and_path_and_replays_there(prepared, tmp_path,
                                                                      capsys) -> None:
    bag = tmp_path / 'demos'
    assert demos_cli.main(['--anatomy', str(prepared), '--episodes', '1', '--out',
                           str(bag)]) == 0
    assert json.loads(capsys.readouterr().out)['anatomy'] == 'p07'
    from cgail_learning.demo_bags import read_demo_bag

    meta, _ = read_demo_bag(bag)
    anatomy = resolve_anatomy(prepared)
    assert (meta['anatomy'], meta['anatomy_hash'], meta['anatomy_path']) == (
        'p07', anatomy.content_hash, str(prepared.resolve()))
    lines: list[str] = []
    obs, act, episodes = load_demos([bag], report=lines.append)
    assert len(obs) == len(act) > 0 and episodes is not None and 1 <= episodes <= 15
    assert f'anatomy {anatomy.content_hash}, as recorded' in lines[0]
    moved = tmp_path / 'p07_moved'
    shutil.copytree(prepared, moved)
    shutil.move(str(prepared), str(tmp_path / 'gone'))
    try:
        with pytest.raises(DemoError, match=(
                rf"^{bag}: expected the anatomy it was recorded in, 'p07' \(content hash "
                rf"{anatomy.content_hash}\) at {prepared.resolve()}, found no such path: give "
                r"its prepared directory \(train --anatomy DIR\)$")):
            load_demos([bag])
        obs2, _, _ = load_demos([bag], anatomy=moved)  # (train passes its path --anatomy)
        assert (obs2 == obs).all()
    finally:
        shutil.move(str(tmp_path / 'gone'), str(prepared))


def test_a_path_trained_contract_holds_the_label_and_content_hash(prepared) -> None:
    meta = train.sim_metadata(EnvConfig(anatomy=prepared))
    contract = PolicyContract.from_dict(meta[CONTRACT_KEY])
    anatomy = resolve_anatomy(prepared)
    assert (contract.anatomy, contract.anatomy_hash) == ('p07', anatomy.content_hash)
    assert (meta['anatomy'], meta['anatomy_hash']) == ('p07', anatomy.content_hash)
    builtin = train.sim_metadata(EnvConfig(anatomy='elongated'))
    assert builtin[CONTRACT_KEY]['anatomy'] == 'elongated'
    assert 'anatomy_hash' not in builtin[CONTRACT_KEY] and 'anatomy_hash' not in builtin
    same = train.sim_metadata(EnvConfig(anatomy=build_anatomy('elongated')))
    assert same[CONTRACT_KEY] == builtin[CONTRACT_KEY]


def test_export_onnx_adds_a_path_anatomy_contract(prepared, tmp_path, capsys) -> None:
    out = tmp_path / 'p07.onnx'
    assert export.main([str(FIXTURES / 'straight_policy.onnx'), '--add-contract', '--anatomy',
                        str(prepared), '--out', str(out)]) == 0
    props = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    contract = PolicyContract.from_json(props[CONTRACT_KEY])
    assert (contract.anatomy, contract.anatomy_hash) == ('p07',
                                                         resolve_anatomy(prepared).content_hash)
    capsys.readouterr()
    # a model whose metadata names a path anatomy's label needs --anatomy to re-contract
    model = onnx.load(str(out))
    kept = [(p.key, p.value) for p in model.metadata_props if p.key != 'anatomy']
    del model.metadata_props[:]
    for key, value in [*kept, ('anatomy', json.dumps('p07'))]:
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(out))
    assert export.main([str(out), '--add-contract']) == 2
    err = capsys.readouterr().err
    assert err == (f"cgail export-onnx: error: --add-contract: the metadata of {out} names "
                   "anatomy 'p07', not a named one: give its prepared directory with "
                   "--anatomy\n")
    assert export.main([str(FIXTURES / 'straight_policy.onnx'), '--anatomy', 'default']) == 2
    assert '--anatomy: expected with --add-contract' in capsys.readouterr().err


def test_evaluate_and_sim_render_take_a_prepared_directory(prepared, tmp_path, capsys,
                                                           monkeypatch) -> None:
    h = resolve_anatomy(prepared).content_hash
    assert evaluate.main(['--anatomy', str(prepared), '--trials', '1', '--baselines',
                          'centerline', '--out', str(tmp_path / 'eval')]) == 0
    report = (tmp_path / 'eval' / 'report.md').read_text()
    assert f"Anatomy 'p07' (content hash {h}), 1 trials per method" in report
    monkeypatch.chdir(tmp_path)
    assert render.main(['--anatomy', str(prepared), '--dpi', '30', '--no-centerlines']) == 0
    assert (tmp_path / 'runs' / 'render' / 'anatomy_p07.png').is_file()
    capsys.readouterr()


def test_invitro_session_in_a_path_anatomy_needs_a_policy(prepared, tmp_path, capsys) -> None:
    assert session.main(['--out', str(tmp_path / 's'), '--anatomy', str(prepared)]) == 2
    assert capsys.readouterr().err == (
        f'cgail session: error: the cgail condition needs --policy <model.onnx> for anatomy '
        f'{prepared.resolve()}: expected a policy trained on it (there is a committed one only '
        'for the built-in anatomies), found no --policy\n')

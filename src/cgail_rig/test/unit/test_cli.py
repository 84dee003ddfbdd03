"""``cgail <verb>``: the verb table, the dispatch, the old names, and complete, plain help.

Every verb's ``--help`` runs in process: it exits 0, names ``cgail <verb>``, documents every
option (with its default) and shows no reStructuredText markup.
"""

from __future__ import annotations

import argparse
import importlib.metadata
from pathlib import Path
import re
import subprocess
import sys

import numpy as np
import pytest

from cgail_rig import cli
from cgail_rig.cli import Verb, VERBS
from cgail_sim import cli_help

SRC = Path(__file__).resolve().parents[3]
#: The packages whose tools are verbs (every cgail package; cgail_rig holds the command line).
TOOL_PACKAGES = ('cgail_sim', 'cgail_planner', 'cgail_bags', 'cgail_gui', 'cgail_learning',
                 'cgail_patient', 'cgail_rig')
#: What reStructuredText leaves in plain text: literals, roles, emphasis, ``::``, directives.
RST = re.compile(r'`|:[a-z]+:(?=`)|\*\*|::\s*$|^\s*\.\. ', re.MULTILINE)


def _ids(verb: Verb) -> str:
    return verb.name.replace(' ', '-')


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``cgail argv`` in this process: (exit status, stdout, stderr)."""
    try:
        status = cli.main(argv)
    except SystemExit as exc:  # argparse's --help and usage errors
        status = exc.code if isinstance(exc.code, int) else 1
    out, err = capsys.readouterr()
    return status, out, err


def _documents_default(parser: argparse.ArgumentParser, action: argparse.Action) -> bool:
    """Whether ``action`` has a default worth showing, and its help (as printed) shows it."""
    if cli_help._no_default(action.default):
        return True
    return 'default' in parser._get_formatter()._expand_help(action)


@pytest.mark.parametrize('verb', VERBS, ids=_ids)
def test_every_verb_has_complete_plain_help(verb: Verb, capsys) -> None:
    status, out, err = _run([*verb.name.split(), '--help'], capsys)
    assert status == 0 and not err, err
    assert out.startswith(f'usage: cgail {verb.name} '), out[:200]
    assert not [m.group(0) for m in RST.finditer(out)], \
        f'cgail {verb.name} --help: expected plain text, found markup: ' \
        f'{[out[max(0, m.start() - 30):m.end() + 30] for m in RST.finditer(out)][:3]}'
    parser = cli.parser_of(verb)
    assert parser.prog == f'cgail {verb.name}'
    assert parser.description and parser.description[0].isupper(), parser.description
    actions = [a for a in parser._actions if not isinstance(a, argparse._HelpAction)]
    assert actions
    undocumented = [a.option_strings or a.dest for a in actions
                    if not a.help or a.help == argparse.SUPPRESS]
    assert not undocumented, f'cgail {verb.name}: expected help for every option, found ' \
                             f'none for {undocumented}'
    hidden = [a.option_strings for a in actions if not _documents_default(parser, a)]
    assert not hidden, f'cgail {verb.name}: expected every default shown, found it hidden ' \
                       f'for {hidden}'


def test_cgail_help_lists_every_verb_under_its_group(capsys) -> None:
    status, out, err = _run(['--help'], capsys)
    assert status == 0 and not err
    assert out.startswith('usage: cgail ')
    headings = [line[:-1] for line in out.splitlines() if line.endswith(':')]
    assert [h for h in headings if h in cli.GROUPS] == list(cli.GROUPS)
    for verb in VERBS:
        section = out.split(f'\n{verb.group}:\n')[1].split('\n\n')[0]
        assert re.search(rf'^  {re.escape(verb.name)} +{re.escape(verb.summary)}$', section,
                         re.MULTILINE), f'{verb.name!r} not listed under {verb.group!r}'
    assert max(len(line) for line in out.splitlines()) <= 99


def test_the_verb_table_is_consistent() -> None:
    names = [v.name for v in VERBS]
    assert len(set(names)) == len(names) and all(v.group in cli.GROUPS for v in VERBS)
    olds = [v.old for v in VERBS if v.old]
    assert len(set(olds)) == len(olds)
    for verb in VERBS:
        assert re.fullmatch(r'[a-z]+(-[a-z]+)*( [a-z]+(-[a-z]+)*)?', verb.name), verb.name
        assert verb.summary and not verb.summary.endswith('.'), verb.summary


def test_every_tool_parser_in_the_package_is_a_verb() -> None:
    """A new tool built with ``tool_parser('x', ...)`` must be in :data:`VERBS` (and each verb
    must name the module that builds its parser)."""
    found = {}
    for package in TOOL_PACKAGES:
        for path in (SRC / package / package).rglob('*.py'):
            for name in re.findall(r"tool_parser\(\s*['\"]([^'\"]+)['\"]", path.read_text()):
                module = '.'.join(path.relative_to(SRC / package).with_suffix('').parts)
                found[name] = module
    assert found == {v.name: v.module for v in VERBS}


def test_cgail_help_imports_no_tool(tmp_path) -> None:
    """``cgail --help`` is quick: it imports no tool module and no torch."""
    code = ('import sys\nfrom cgail_rig import cli\ncli.main(["--help"])\n'
            f'extra = sorted(m for m in sys.modules if m.split(".")[0] in {TOOL_PACKAGES!r} '
            'and m not in ("cgail_rig", "cgail_rig.cli") or m in ("torch", "numpy", "rclpy"))\n'
            'assert not extra, extra\n')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=60, cwd=tmp_path)
    assert result.returncode == 0, result.stderr


def test_bag_lists_its_commands(capsys) -> None:
    status, out, _ = _run(['bag', '--help'], capsys)
    assert status == 0 and out.startswith('usage: cgail bag <command>')
    for verb in VERBS:
        if verb.name.startswith('bag '):
            assert re.search(rf'^  {verb.name[4:]} +{re.escape(verb.summary)}$', out,
                             re.MULTILINE), verb.name
    status, out, err = _run(['bag'], capsys)
    assert status == 2 and not out and err.startswith('usage: cgail bag <command>')


@pytest.mark.parametrize(('argv', 'line'), [
    (['trian'], "cgail: error: unknown verb 'trian'; the closest: train (cgail --help lists "
                'the verbs)\n'),
    (['bag_play'], "cgail: error: unknown verb 'bag_play'; the closest: bag play (cgail --help "
                   'lists the verbs)\n'),
    (['invitro_session'], "cgail: error: unknown verb 'invitro_session'; the closest: session "
                          '(cgail --help lists the verbs)\n'),
    (['bag', 'ply'], "cgail: error: unknown verb 'bag ply'; the closest: bag play (cgail --help "
                     'lists the verbs)\n'),
    (['xyzzy'], "cgail: error: unknown verb 'xyzzy' (cgail --help lists the verbs)\n"),
    (['--verbose'], "cgail: error: unknown option '--verbose' (cgail --help lists the "
                    'options)\n'),
])
def test_an_unknown_verb_is_one_line_naming_the_closest(argv, line, capsys) -> None:
    assert _run(argv, capsys) == (2, '', line)


def test_no_verb_prints_the_verbs_and_fails(capsys) -> None:
    status, out, err = _run([], capsys)
    assert status == 2 and not out and err == cli.format_help()


def test_version(capsys) -> None:
    status, out, _ = _run(['--version'], capsys)
    assert status == 0 and out == f"cgail {importlib.metadata.version('cgail_rig')}\n"


def test_a_verb_passes_its_arguments_and_exit_status_through(tmp_path, capsys) -> None:
    status, _, err = _run(['bag', 'recover', str(tmp_path / 'nowhere'), '-o',
                           str(tmp_path / 'out')], capsys)
    assert status == 2 and err.startswith('cgail bag recover: error: ') and err.count('\n') == 1
    status, _, err = _run(['bag', 'recover'], capsys)  # a usage error: argparse's status 2
    assert status == 2 and 'cgail bag recover: error: the following arguments are required' in err


def test_an_old_name_says_it_is_deprecated_then_runs_the_verb(tmp_path, capsys) -> None:
    status = cli.legacy_bag_recover([str(tmp_path / 'nowhere'), '-o', str(tmp_path / 'out')])
    err = capsys.readouterr().err.splitlines()
    assert status == 2 and len(err) == 2, err
    assert err[0] == ("bag_recover: deprecated: use 'cgail bag recover' (the name 'bag_recover' "
                      'goes in the next release)')
    assert err[1].startswith('cgail bag recover: error: ')
    with pytest.raises(AttributeError, match="has no attribute 'legacy_nothing'"):
        cli.legacy_nothing  # noqa: B018


def test_every_old_console_script_runs_its_verb() -> None:
    """The installed entry points: ``cgail`` and each old name through ``legacy_<old>`` (one
    release) in cgail_rig, and each node in the package that owns it, nothing else."""
    def scripts_of(package: str) -> dict[str, str]:
        return {ep.name: ep.value for ep in importlib.metadata.distribution(package).entry_points
                if ep.group == 'console_scripts'}

    assert scripts_of('cgail_planner') == {
        'planner_node': 'cgail_planner.nodes.planner_node:main',
        'operator_node': 'cgail_planner.nodes.operator_node:main',
        'autonomy_node': 'cgail_planner.nodes.autonomy_node:main'}
    assert scripts_of('cgail_gui') == {
        'gui_node': 'cgail_gui.nodes.gui_node:main',
        'igtl_bridge': 'cgail_gui.nodes.igtl_bridge:main',
        'foxglove_bridge': 'cgail_gui.nodes.foxglove_bridge:main'}
    for package in ('cgail_sim', 'cgail_bags', 'cgail_learning', 'cgail_patient'):
        assert scripts_of(package) == {}, package
    scripts = scripts_of('cgail_rig')
    assert scripts.pop('cgail') == 'cgail_rig.cli:main'
    nodes = {k: v for k, v in scripts.items() if v.startswith('cgail_rig.nodes.')}
    assert nodes == {'phantom_node': 'cgail_rig.nodes.phantom_node:main'}
    olds = {k: v for k, v in scripts.items() if k not in nodes}
    assert olds == {v.old: f'cgail_rig.cli:legacy_{v.old}' for v in VERBS if v.old}
    for name in olds:
        assert callable(getattr(cli, f'legacy_{name}'))


@pytest.mark.parametrize(('rst', 'plain'), [
    ('``train``: see :mod:`cgail_sim` and **why**::',
     'train: see cgail_sim and why:'),
    (':class:`~cgail_sim.wall.\n    WallError` ends it', 'WallError ends it'),
    (':func:`load <cgail_sim.anatomy.load_anatomy_mesh>`', 'load'),
    ('a *new* bag, `x` and `y`_', 'a new bag, x and y'),
    ('k * rate / HZ and 3 starts x 5 targets', 'k * rate / HZ and 3 starts x 5 targets'),
    ('Usage::\n\n    cgail train', 'Usage:\n\n    cgail train'),
    ('text\n\n::\n\n    block', 'text\n\n\n    block'),
])
def test_plain_text_removes_the_markup(rst, plain) -> None:
    assert cli_help.plain_text(rst) == plain


def test_the_help_formatter_flows_prose_keeps_blocks_and_shows_defaults(monkeypatch) -> None:
    monkeypatch.setenv('COLUMNS', '60')  # (argparse wraps to the terminal, less 2)
    doc = ('``cgail x``: do a thing.\n\nA long paragraph with ``markup`` that is re-flowed to '
           'the width of the terminal,\nwhatever its lines were.\n\n'
           '* one item that is long enough to wrap onto a second line of the help\n'
           '* two\n\nExamples::\n\n    cgail x --n 3 --flag --anatomy elongated    # kept as '
           'written\n')
    p = cli_help.tool_parser('x', doc, details=True)
    p.add_argument('--n', type=int, default=3, help='count')
    p.add_argument('--m', type=int, default=2, help='count (default 2)')
    p.add_argument('--anatomy', default='default', help='name (default, elongated)')
    p.add_argument('--modes', nargs='+', default=['static', 'dynamic'], help='modes')
    p.add_argument('--flag', action='store_true', help='a flag')
    text = p.format_help()
    assert text.startswith('usage: cgail x ') and '\nDo a thing.\n' in text
    flat = ' '.join(text.split())
    assert 'name (default, elongated) (default: default)' in flat
    assert 'modes (default: static dynamic)' in flat
    assert '--flag a flag' in flat and 'a flag (default' not in flat
    assert 'count (default 2)' in flat and 'count (default 2) (default' not in flat
    # prose and list items re-flowed to the width (58), the literal block kept as written
    assert '\nA long paragraph with markup that is re-flowed to the\nwidth' in text
    assert '    cgail x --n 3 --flag --anatomy elongated    # kept as written\n' in text
    assert '* one item that is long enough to wrap onto a second line\n  of the help\n* two\n' \
        in text
    assert max(len(line) for line in text.splitlines() if not line.startswith('    cgail')) <= 58
    assert 'Examples:\n' in text and '``' not in text and '::' not in text


def test_examples_only_by_default() -> None:
    doc = '``cgail x``: do it.\n\nDetails nobody reads.\n\n    cgail x --go\n'
    text = cli_help.tool_parser('x', doc).format_help()
    assert 'examples:\n  cgail x --go\n' in text and 'Details' not in text


def test_the_rig_calibration_verbs_run_em_trackers_commands(tmp_path, capsys) -> None:
    """``cgail pivot-calibrate`` is ``em_tracker``'s ``pivot_calibrate``: the same result from
    the same recording; a bad input is one line under the verb's name."""
    from em_tracker.cli import pivot_calibrate
    from em_tracker.sim.procedures import (
        example_truth,
        read_calibration,
        record_pivot,
        SimulatedRig,
    )

    with SimulatedRig(example_truth(1)) as rig:
        csv = record_pivot(rig, tmp_path / 'pivot.csv', frames=200)
    status, out, _ = _run(['pivot-calibrate', str(csv), '-o', str(tmp_path / 'verb.yaml')],
                          capsys)
    assert status == 0 and 'residual' in out.lower(), out
    assert pivot_calibrate.main([str(csv), '-o', str(tmp_path / 'script.yaml')]) == 0
    capsys.readouterr()
    verb = read_calibration(tmp_path / 'verb.yaml')['tool_transform']
    script = read_calibration(tmp_path / 'script.yaml')['tool_transform']
    assert np.array_equal(verb.matrix, script.matrix)
    for argv in (['pivot-calibrate', str(tmp_path / 'nowhere.csv'), '-o', str(tmp_path / 'x')],
                 ['register-phantom', str(tmp_path / 'nowhere.csv'), '-o', str(tmp_path / 'x')]):
        status, _, err = _run(argv, capsys)
        assert status == 2 and err.startswith(f'cgail {argv[0]}: error: ') \
            and err.count('\n') == 1, err
    assert not (tmp_path / 'x').exists()

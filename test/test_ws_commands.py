"""The documented ``scripts/ws <command>`` forms resolve, and package executables run through it.

Needs the colcon install (``bash scripts/setup.sh``): the package executables are the console
scripts in ``install/<pkg>/lib/<pkg>/``, which ``scripts/env.sh`` puts on ``PATH``. The
commands run with those directories taken off the inherited ``PATH``, so that it is
``scripts/ws`` that finds them.
"""

from __future__ import annotations

import os
from pathlib import Path
import re
import subprocess

import pytest

ROOT = Path(__file__).resolve().parents[1]
WS = ROOT / 'scripts' / 'ws'
DOCUMENTED = re.compile(r'scripts/ws ([A-Za-z_][\w.-]*)')
PROSE = {'or'}  # "run the tests through scripts/ws or scripts/test.sh"


def _documents() -> list[Path]:
    """README, CONTRIBUTING, the docs site, bag READMEs, scripts, benchmarks, and every
    package's modules/configs."""
    files = [ROOT / 'README.md', ROOT / 'CONTRIBUTING.md', *sorted((ROOT / 'docs').rglob('*.md')),
             *sorted((ROOT / 'bags').rglob('README.md')),
             *sorted(p for p in (ROOT / 'scripts').iterdir() if p.is_file()),
             *sorted((ROOT / 'bench').glob('*.py'))]
    for pkg in sorted(p for p in (ROOT / 'src').iterdir() if (p / p.name).is_dir()):
        files += sorted((pkg / pkg.name).rglob('*.py')) + sorted((pkg / 'config').rglob('*.yaml'))
    return files


def _documented_commands() -> dict[str, list[str]]:
    """``command -> files`` for every ``scripts/ws <command>`` shown in the documents."""
    found: dict[str, list[str]] = {}
    for path in _documents():
        for command in DOCUMENTED.findall(path.read_text(errors='replace')):
            if command not in PROSE:
                found.setdefault(command, []).append(str(path.relative_to(ROOT)))
    return found


def _env_without_install_on_path() -> dict[str, str]:
    install = str(ROOT / 'install')
    path = [p for p in os.environ.get('PATH', '').split(os.pathsep)
            if not os.path.realpath(p).startswith(os.path.realpath(install) + os.sep)
            and not p.startswith(install + os.sep)]
    return {**os.environ, 'PATH': os.pathsep.join(path)}


def _run(argv: list[str]) -> subprocess.CompletedProcess[str]:
    assert (ROOT / 'install' / 'setup.bash').is_file(), \
        'expected the colcon install in install/, found none: run bash scripts/setup.sh'
    return subprocess.run(argv, cwd=ROOT, env=_env_without_install_on_path(),
                          capture_output=True, text=True, timeout=120)


def test_every_documented_scripts_ws_command_resolves() -> None:
    commands = _documented_commands()
    assert {'python', 'cgail', 'aurora_node'} <= commands.keys()
    result = _run(['bash', str(WS), 'bash', '-c',
                   'for c in "$@"; do command -v "$c" >/dev/null || echo "$c"; done', '_',
                   *commands])
    missing = result.stdout.split()
    assert result.returncode == 0 and not missing, \
        f'expected every documented command on the PATH of scripts/ws, found missing: ' \
        f'{ {c: commands[c] for c in missing} }'


def test_documents_run_the_tools_as_cgail_verbs() -> None:
    """The README, docs, scripts and benchmarks invoke tools as ``cgail <verb>``, never by the
    previous release's console-script names (which only remain for one release)."""
    from cgail_rig.cli import VERBS

    olds = '|'.join(sorted((v.old for v in VERBS if v.old), key=len, reverse=True))
    invocation = re.compile(rf'(?:scripts/ws|scripts/ros2run \w+|ros2 run \w+|\$R) ({olds})\b')
    found = [f'{path.relative_to(ROOT)}: {m.group(0)}' for path in _documents()
             for m in invocation.finditer(path.read_text(errors='replace'))]
    assert not found, f'expected cgail <verb> commands, found the old names: {found}'


def test_scripts_ws_finds_the_installed_node_executable() -> None:
    result = _run(['bash', str(WS), 'bash', '-c', 'command -v aurora_node'])
    assert result.returncode == 0, result.stderr
    assert os.path.samefile(result.stdout.strip(),
                            ROOT / 'install' / 'em_tracker' / 'lib' / 'em_tracker' / 'aurora_node')


@pytest.mark.parametrize(('argv', 'usage'), [
    (['scripts/ws', 'cgail', 'make-demos', '--help'], 'cgail make-demos'),  # bags/demos/README
    (['scripts/ws', 'sim_aurora', '--help'], 'sim_aurora'),
    (['scripts/ros2run', 'em_tracker', 'sim_aurora', '--help'], 'sim_aurora'),
    (['scripts/ros2run', 'cgail_rig', 'cgail', 'bag', 'play', '--help'], 'cgail bag play'),
])
def test_package_executables_run_through_the_scripts(argv: list[str], usage: str) -> None:
    result = _run(['bash', *argv])
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f'usage: {usage} ')


def test_an_old_tool_name_still_runs_with_a_deprecation_line() -> None:
    """The console scripts of the last release run their ``cgail`` verb for one more."""
    result = _run(['bash', 'scripts/ws', 'make_demos', '--help'])
    assert result.returncode == 0, result.stderr
    assert result.stderr == ("make_demos: deprecated: use 'cgail make-demos' (the name "
                             "'make_demos' goes in the next release)\n")
    assert result.stdout.startswith('usage: cgail make-demos ')

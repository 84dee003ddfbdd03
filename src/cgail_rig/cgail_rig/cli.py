"""``cgail``: one command line for the workspace's tools, shaped like ``ros2 <verb>``.

    cgail --help                      # the verbs, grouped
    cgail train --help                # a verb's full help
    cgail train --preset cgail --mode static --demos bags/demos/default
    cgail bag play bags/fixtures/cgail_trial --clock

Each verb is a tool module with ``build_parser()`` (its parser, ``prog`` ``cgail <verb>``, built
with :func:`cgail_sim.cli_help.tool_parser`) and ``main(argv) -> int``; :data:`VERBS` is the
one table of them. Modules are imported only when their verb runs, so ``cgail --help`` is quick
and needs no torch. Nodes are not verbs: they stay ROS executables (``ros2 run <pkg> <node>``;
``scripts/ros2run`` in the pip-only workspace).

The console scripts of the last release (``train``, ``bag_play``, ...) still run, through
``legacy_<old name>`` here: one deprecation line on stderr naming the new command, then the
verb with the same arguments and exit status.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
import difflib
import functools
import importlib
import importlib.metadata
import sys
from types import ModuleType

__all__ = ['GROUPS', 'VERBS', 'Verb', 'format_help', 'main', 'parser_of', 'run']


@dataclass(frozen=True)
class Verb:
    """One tool of the command line."""

    name: str
    """The verb as typed after ``cgail``: ``train``, or ``bag play`` for a bag command."""
    module: str
    """The tool's module: it has ``build_parser()`` and ``main(argv) -> int``."""
    summary: str
    """One line for ``cgail --help``."""
    group: str
    """Its heading in ``cgail --help`` (one of :data:`GROUPS`)."""
    old: str = ''
    """The console script of the last release, kept one release with a deprecation line."""


#: Headings of ``cgail --help``, in order.
GROUPS: tuple[str, ...] = ('patients', 'learning', 'rig and sessions', 'bags', 'tools')

#: Every verb, in the order ``cgail --help`` lists them.
VERBS: tuple[Verb, ...] = (
    Verb('prepare-anatomy', 'cgail_patient.prepare_cli',
         "a patient's CT label map or lumen surface in, a prepared anatomy out",
         'patients', 'prepare_anatomy'),
    Verb('plan-patient', 'cgail_patient.plan',
         'from a prepared anatomy to a trained, evaluated planner', 'patients', 'plan_patient'),
    Verb('synthetic-ct', 'cgail_patient.synthetic',
         'synthetic CT label maps or lumen surfaces of the built-in aortas', 'patients',
         'synthetic_ct'),
    Verb('make-demos', 'cgail_learning.demos_cli',
         'scripted-expert (or teleoperated) demonstrations into bags', 'learning',
         'make_demos'),
    Verb('record-demos', 'cgail_rig.record_demos',
         'record your own demonstrations in the simulator (gamepad, keyboard)', 'learning',
         'record_demos'),
    Verb('train', 'cgail_learning.train',
         'train a policy (C-GAIL, GAIL or an ablation) in the simulator', 'learning', 'train'),
    Verb('refine', 'cgail_learning.refine',
         'DAgger refinement of a trained policy with the scripted expert', 'learning',
         'refine'),
    Verb('evaluate', 'cgail_learning.evaluate',
         "the paper's in-silico experiments: a markdown report with box plots", 'learning',
         'evaluate'),
    Verb('export-onnx', 'cgail_learning.export',
         'a trained policy as an ONNX model for the planner node', 'learning', 'export_onnx'),
    Verb('launch', 'cgail_rig.launcher',
         "start a launch file's nodes (ROS 2 YAML launch format)", 'rig and sessions',
         'rig_launch'),
    Verb('session', 'cgail_rig.session',
         'the simulated in-vitro session of the paper, end to end', 'rig and sessions',
         'invitro_session'),
    Verb('identify-pam', 'cgail_rig.identify_pam',
         "identify the PAM controller's bending model on the bench", 'rig and sessions',
         'identify_pam'),
    Verb('pivot-calibrate', 'cgail_rig.pivot_calibrate',
         "the EM sensor's tool transform from a recorded pivoting motion",
         'rig and sessions'),
    Verb('register-phantom', 'cgail_rig.register_phantom',
         'the tracker-to-phantom registration from touched fiducials (and a traced wall)',
         'rig and sessions'),
    Verb('bag record', 'cgail_bags.record', 'record ROS 2 topics to a rosbag2 MCAP bag', 'bags',
         'bag_record'),
    Verb('bag play', 'cgail_bags.play', 'play a bag back into live topics', 'bags', 'bag_play'),
    Verb('bag metrics', 'cgail_bags.metrics_cli',
         "the paper's in-vitro metrics of trial bags: table and box plots", 'bags',
         'bag_metrics'),
    Verb('bag compare', 'cgail_bags.compare_cli',
         'several in-vitro sessions side by side', 'bags', 'session_compare'),
    Verb('bag recover', 'cgail_bags.recover',
         'recover the messages of a bag whose recorder was killed', 'bags', 'bag_recover'),
    Verb('render', 'cgail_sim.render',
         'an anatomy (or a population grid) as a PNG', 'tools', 'sim_render'),
)

_BY_NAME = {v.name: v for v in VERBS}
_BY_OLD = {v.old: v for v in VERBS if v.old}
#: Verbs that take a command of their own (``cgail bag play``), with their description.
_SUBCOMMANDS = {'bag': 'Record, play back, measure and repair rosbag2 MCAP bags.'}


def _version() -> str:
    try:
        return importlib.metadata.version('cgail_rig')
    except importlib.metadata.PackageNotFoundError:  # run from a source tree
        return 'unknown (not installed)'


def _usage(prefix: str = '') -> str:
    if prefix:
        return f'usage: cgail {prefix} <command> [<args>]'
    return 'usage: cgail [-h] [--version] <verb> [<args>]'


def _table(rows: Sequence[tuple[str, str]], width: int = 0) -> list[str]:
    width = max(width, *(len(name) + 2 for name, _ in rows))
    return [f'  {name:<{width}}{summary}' for name, summary in rows]


def format_help() -> str:
    """What ``cgail --help`` prints: every verb under its group, then how to run nodes."""
    lines = [_usage(), '',
             'The tools of the C-GAIL catheter workspace, one verb each (like ros2 <verb>).']
    width = max(len(v.name) for v in VERBS) + 2
    for group in GROUPS:
        lines += ['', f'{group}:']
        lines += _table([(v.name, v.summary) for v in VERBS if v.group == group], width)
    lines += ['', 'options:', *_table([('-h, --help', 'show this help and exit'),
                                       ('--version', "show cgail's version and exit")], width),
              '',
              "'cgail <verb> --help' shows a verb's options. Nodes are not verbs: they are ROS",
              "executables, 'scripts/ros2run <package> <node>' in this workspace ('ros2 run",
              "<package> <node>' on a full ROS install); 'cgail launch' starts a launch file."]
    return '\n'.join(lines) + '\n'


def _format_subcommand_help(prefix: str) -> str:
    rows = [(v.name[len(prefix) + 1:], v.summary) for v in VERBS
            if v.name.startswith(prefix + ' ')]
    lines = [_usage(prefix), '', _SUBCOMMANDS[prefix], '', 'commands:', *_table(rows), '',
             f"'cgail {prefix} <command> --help' shows a command's options."]
    return '\n'.join(lines) + '\n'


def _unknown(name: str) -> int:
    """One line naming the unknown verb and the closest ones; exit status 2."""
    # An old console-script name is close to the verb that replaced it.
    names = {**{v.name: v.name for v in VERBS}, **{v.old: v.name for v in VERBS if v.old}}
    close = dict.fromkeys(names[c] for c in difflib.get_close_matches(name, names, n=6,
                                                                      cutoff=0.6))
    hint = f"; the closest: {', '.join(list(close)[:3])}" if close else ''
    print(f"cgail: error: unknown verb '{name}'{hint} (cgail --help lists the verbs)",
          file=sys.stderr)
    return 2


def _tool(verb: Verb) -> ModuleType:
    return importlib.import_module(verb.module)


def parser_of(verb: Verb) -> argparse.ArgumentParser:
    """The tool's argument parser (imports its module)."""
    parser: argparse.ArgumentParser = _tool(verb).build_parser()
    return parser


def run(verb: Verb, argv: Sequence[str]) -> int:
    """Run ``verb`` with ``argv`` (its own arguments); returns the tool's exit status."""
    status = _tool(verb).main(list(argv))
    return int(status or 0)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail``: dispatch to the verb, or print the verbs."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:
        sys.stderr.write(format_help())
        return 2
    head, rest = args[0], args[1:]
    if head in ('-h', '--help'):
        sys.stdout.write(format_help())
        return 0
    if head == '--version':
        print(f'cgail {_version()}')
        return 0
    if head.startswith('-'):
        print(f"cgail: error: unknown option '{head}' (cgail --help lists the options)",
              file=sys.stderr)
        return 2
    if head in _SUBCOMMANDS:
        if not rest or rest[0] in ('-h', '--help'):
            (sys.stdout if rest else sys.stderr).write(_format_subcommand_help(head))
            return 0 if rest else 2
        head, rest = f'{head} {rest[0]}', rest[1:]
    verb = _BY_NAME.get(head)
    if verb is None:
        return _unknown(head)
    return run(verb, rest)


def _run_old_name(verb: Verb, argv: Sequence[str] | None = None) -> int:
    print(f"{verb.old}: deprecated: use 'cgail {verb.name}' (the name '{verb.old}' goes in the "
          'next release)', file=sys.stderr)
    return run(verb, sys.argv[1:] if argv is None else argv)


def __getattr__(name: str) -> Callable[..., int]:
    """``legacy_<old name>``: the entry point of a last-release console script (setup.py)."""
    old = name.removeprefix('legacy_')
    if name.startswith('legacy_') and old in _BY_OLD:
        return functools.partial(_run_old_name, _BY_OLD[old])
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


if __name__ == '__main__':
    sys.exit(main())

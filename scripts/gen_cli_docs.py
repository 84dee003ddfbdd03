"""The CLI reference of the docs site, generated from the ``cgail`` verbs' argparse parsers.

    scripts/ws python scripts/gen_cli_docs.py                  # markdown on stdout
    scripts/ws python scripts/gen_cli_docs.py -o /tmp/cli.md   # into a file

``mkdocs build`` runs it through ``scripts/mkdocs_hooks.py`` (the page ``reference/cli.md``), so
the reference is never committed and never stale: it is what ``cgail <verb> --help`` prints, for
every verb of :data:`cgail_rig.cli.VERBS`, at a fixed width of 100 columns. It needs the workspace
environment (``scripts/ws``): the parsers are built by importing each tool's module.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys

WIDTH = 100


def _anchor(name: str) -> str:
    return 'cgail-' + name.replace(' ', '-')


def cli_reference() -> str:
    """The markdown page: ``cgail --help``, then every verb's ``--help``, grouped."""
    os.environ['COLUMNS'] = str(WIDTH)  # argparse wraps to $COLUMNS: one width on every machine
    from cgail_rig.cli import format_help, GROUPS, parser_of, VERBS

    lines = ['# CLI reference: `cgail <verb>`', '',
             'Generated at every docs build from the argparse parser of each verb '
             '(`scripts/gen_cli_docs.py`): what `cgail <verb> --help` prints. In this '
             'workspace run a verb as `scripts/ws cgail <verb>` (or after '
             '`source scripts/env.sh`); on a full ROS install, '
             '`ros2 run cgail_rig cgail <verb>`. Nodes are not verbs: their parameters and '
             'topics are in the [node reference](../interfaces.md).', '',
             '```text', format_help().rstrip('\n'), '```', '']
    for group in GROUPS:
        verbs = [v for v in VERBS if v.group == group]
        lines += [f'## {group[:1].upper() + group[1:]}', '']
        lines += [f'- [`cgail {v.name}`](#{_anchor(v.name)}): {v.summary}' for v in verbs]
        lines.append('')
        for verb in verbs:
            text = parser_of(verb).format_help().rstrip('\n')
            lines += [f'### `cgail {verb.name}` {{ #{_anchor(verb.name)} }}', '',
                      verb.summary[:1].upper() + verb.summary[1:] + '.', '',
                      '```text', text.replace('```', "'''"), '```', '']
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='gen_cli_docs.py', description=__doc__.split('\n\n')[0])
    parser.add_argument('-o', '--out', type=Path, help='write here (default: stdout)')
    args = parser.parse_args(argv)
    text = cli_reference()
    if args.out:
        args.out.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""Help text of the ``cgail <verb>`` tools: plain text from docstrings, defaults shown.

Every tool of the ``cgail`` command line (:mod:`cgail_rig.cli`) builds its parser with
:func:`tool_parser`: ``prog`` is ``cgail <verb>``, the description is the first paragraph of the
tool's module docstring and the epilog its examples (or the whole docstring, for tools whose
docstring is written for users). Docstrings are reStructuredText for the API docs;
:class:`HelpFormatter` turns them into plain text (``literal``, roles, emphasis, ``::``) so a
terminal never shows markup, re-flows prose to the terminal width, keeps example blocks as
they are, and appends ``(default: X)`` to an option whose help does not mention its default.

This module imports nothing of the workspace, so every layer may use it.
"""

from __future__ import annotations

import argparse
import inspect
import re
import textwrap
from typing import Any

__all__ = ['HelpFormatter', 'plain_text', 'split_docstring', 'tool_parser']

#: ``:role:`text``` and ``:domain:role:`text``` (Sphinx cross-references), text group 1.
_ROLE = re.compile(r':(?:[A-Za-z]+:)?[A-Za-z]+:`([^`]+)`')
_LITERAL = re.compile(r'``(.+?)``', re.DOTALL)
_DEFAULT_ROLE = re.compile(r'(?<![`\w])`([^`\n]+)`_{0,2}(?![`\w])')
_STRONG = re.compile(r'\*\*([^*\n]+?)\*\*')
_EMPHASIS = re.compile(r'(?<![\w*\\])\*([^\s*][^*\n]*?)\*(?![\w*])')
_LITERAL_MARK = re.compile(r'(\S)\s*::[ \t]*$', re.MULTILINE)
_BARE_LITERAL_MARK = re.compile(r'^[ \t]*::[ \t]*\n', re.MULTILINE)
#: The old console-script name some docstrings open with: ```train``: train a policy ...``.
_BULLET = re.compile(r'(?:[*-]|\d+\.) ')
_NAME_PREFIX = re.compile(r'^(?:Console script )?``[\w .-]+``:\s*')
#: An option's help names its default (``default 1``, ``default: x``, ``%(default)s``); a
#: built-in anatomy list such as ``(default, elongated)`` or ``('default', ...)`` does not.
_NAMES_DEFAULT = re.compile(r"%\(default\)|(?<!['\w])defaults?\b(?![,/'])")


def _role_text(match: re.Match[str]) -> str:
    """The text a reader sees of one role: ``~a.b.C`` -> ``C``, ``Title <target>`` -> ``Title``."""
    text = re.sub(r'\s*\n\s*', '', match.group(1))  # a target broken over two lines
    title = re.fullmatch(r'(.+?)\s*<[^>]+>', text)
    if title:
        return title.group(1)
    if text.startswith('~'):
        return text[1:].rsplit('.', 1)[-1]
    return text.lstrip('!')


def plain_text(text: str) -> str:
    """``text`` (reStructuredText) as a terminal shows it: markup removed, layout kept.

    Cross-references (``:mod:`a.b```) become their target (``~`` keeps the last name), inline
    literals and emphasis lose their marks, and a paragraph ending in ``::`` ends in ``:``.

    Example:
        >>> plain_text('``train``: see :mod:`cgail_sim` and **why**::')
        'train: see cgail_sim and why:'
    """
    text = _ROLE.sub(_role_text, text)
    text = _LITERAL.sub(lambda m: m.group(1), text)
    text = _DEFAULT_ROLE.sub(lambda m: m.group(1), text)
    text = _STRONG.sub(lambda m: m.group(1), text)
    text = _EMPHASIS.sub(lambda m: m.group(1), text)
    text = _BARE_LITERAL_MARK.sub('', text)
    return _LITERAL_MARK.sub(lambda m: m.group(1) + ':', text)


def split_docstring(doc: str | None) -> tuple[str, str]:
    """A module docstring as ``(summary, rest)``: its first paragraph and everything after.

    The summary loses the old console-script name it may open with (```train``: train ...`` ->
    ``Train ...``), since the tool is now ``cgail <verb>``.
    """
    text = inspect.cleandoc(doc or '')
    summary, _, rest = text.partition('\n\n')
    summary = _NAME_PREFIX.sub('', summary.strip())
    return summary[:1].upper() + summary[1:], rest.strip('\n')


def _examples(rest: str) -> str:
    """The literal blocks (indented paragraphs) of a docstring's body, one after another."""
    blocks = [b for b in re.split(r'\n[ \t]*\n', rest) if b.strip() and b[:1] in ' \t']
    if not blocks:
        return ''
    return 'examples:\n' + '\n'.join(textwrap.indent(textwrap.dedent(b), '  ') for b in blocks)


def _no_default(default: object) -> bool:
    """Whether an option's default is no value to show (None, a flag's False, empty)."""
    return (default is None or default is False or default is argparse.SUPPRESS
            or (isinstance(default, (str, list, tuple)) and not default))


def _hang(item: str) -> int:
    """The width of a list item's bullet (``* ``, ``1. ``), 0 for prose."""
    bullet = _BULLET.match(item)
    return len(bullet.group(0)) if bullet else 0


def _fill(text: str, width: int, indent: str, hang: int) -> str:
    """``text`` re-flowed to ``width``; lines after the first indented ``hang`` more."""
    return textwrap.fill(' '.join(text.split()), width, initial_indent=indent,
                         subsequent_indent=indent + ' ' * hang, break_on_hyphens=False)


class HelpFormatter(argparse.HelpFormatter):
    """Plain-text help from reStructuredText: prose re-flowed, literal blocks and tables kept.

    A paragraph (lines between blank lines) is kept line by line when one of its lines is
    indented or it is a table (``===``); a bulleted or numbered list is re-flowed item by item
    with a hanging indent; any other paragraph is re-flowed to the width.
    """

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        out: list[str] = []
        for para in re.split(r'\n[ \t]*\n', plain_text(textwrap.dedent(text).strip('\n'))):
            lines = para.split('\n')
            if _BULLET.match(para):  # a list: each item re-flowed under its bullet
                items = re.split(r'\n(?=(?:[*-]|\d+\.) )', para)
                out.append('\n'.join(_fill(item, width, indent, _hang(item)) for item in items))
            elif any(line[:1] in ' \t' for line in lines) or para.lstrip().startswith('=='):
                out.append('\n'.join(indent + line.rstrip() for line in lines))
            else:
                out.append(_fill(para, width, indent, 0))
        return '\n\n'.join(out)

    def _split_lines(self, text: str, width: int) -> list[str]:
        # (argparse's own breaks ``--lv-label`` and ``cgail prepare-anatomy`` at the hyphen)
        return textwrap.wrap(' '.join(plain_text(text).split()), width, break_on_hyphens=False)

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ''
        if (action.option_strings and not _no_default(action.default)
                and not _NAMES_DEFAULT.search(text)):
            default = action.default
            shown = (' '.join(map(str, default)) if isinstance(default, (list, tuple))
                     else str(default))
            text += f" (default: {shown.replace('%', '%%')})"
        return text


def tool_parser(verb: str, doc: str | None, *, description: str | None = None,
                details: bool = False, **kwargs: Any) -> argparse.ArgumentParser:
    """The argument parser of ``cgail <verb>``, its help taken from the module docstring ``doc``.

    Args:
        verb: The verb (``train``, ``bag play``): the parser's ``prog`` is ``cgail <verb>``.
        doc: The tool's module docstring (reStructuredText).
        description: The description, if not the docstring's first paragraph.
        details: Whether the epilog is the whole rest of the docstring (a docstring written
            for the tool's users) instead of its examples only.
        **kwargs: Further ``argparse.ArgumentParser`` arguments.
    """
    summary, rest = split_docstring(doc)
    if details and rest[:1] in (' ', '\t'):  # the docstring's body opens with examples
        rest = 'examples:\n' + rest
    return argparse.ArgumentParser(
        prog=f'cgail {verb}', description=description or summary,
        epilog=(rest if details else _examples(rest)) or None,
        formatter_class=HelpFormatter, **kwargs)

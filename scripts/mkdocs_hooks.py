"""MkDocs hooks of the docs site (``mkdocs.yml``: ``hooks:``).

- The CLI reference, ``reference/cli.md``, is generated at every build from the ``cgail`` verbs'
  argparse parsers (``scripts/gen_cli_docs.py``), so it is never committed and never stale.
- The repository's own top-level documents join the site: ``CHANGELOG.md`` as ``changelog.md``,
  ``CONTRIBUTING.md`` as ``contributing.md``, ``THIRD_PARTY_NOTICES.md`` as ``notices.md`` and
  ``LICENSE`` as ``license.md``.
- A page may link to any file of the repository outside ``docs/`` (a report committed beside its
  policies, a config, a module) with its relative path, as on a code host: the file is copied
  into the site under ``repo/<path>`` (a markdown file becomes a page, whose own links are
  followed the same way) and the link is rewritten to it. A link to a file that exists nowhere
  is left alone, so ``mkdocs build --strict`` fails on it like on any broken link.

Run the build in the workspace environment: ``scripts/ws mkdocs build --strict`` (the CLI
reference imports the tools).
"""

from __future__ import annotations

import importlib.util
import logging
import os
from pathlib import Path, PurePosixPath
import posixpath
import re
from typing import Any
from urllib.parse import unquote

from mkdocs.structure.files import File, Files

log = logging.getLogger('mkdocs.hooks.cgail')

ROOT = Path(__file__).resolve().parents[1]
#: Top-level files of the repository and the page each becomes.
ROOT_PAGES = {'CHANGELOG.md': 'changelog.md', 'CONTRIBUTING.md': 'contributing.md',
              'THIRD_PARTY_NOTICES.md': 'notices.md'}
CLI_PAGE = 'reference/cli.md'
_FENCE = re.compile(r'^(```|~~~).*?^\1[ \t]*$', re.MULTILINE | re.DOTALL)
_LINK = re.compile(r'(\]\()([^)\s]+)')

#: src_uri of every page -> its path in the repository (posix, relative to ROOT).
_origin: dict[str, str] = {}


def _load_generator() -> Any:
    path = ROOT / 'scripts' / 'gen_cli_docs.py'
    spec = importlib.util.spec_from_file_location('gen_cli_docs', path)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _cli_page() -> str:
    try:
        return str(_load_generator().cli_reference())
    except ImportError as exc:
        raise SystemExit(
            f'mkdocs: the CLI reference imports the cgail tools and could not ({exc}): build '
            f'the docs in the workspace environment, scripts/ws mkdocs build') from exc


def _outside_text(markdown: str) -> list[tuple[int, int]]:
    """The spans of ``markdown`` outside fenced code blocks."""
    spans, start = [], 0
    for fence in _FENCE.finditer(markdown):
        spans.append((start, fence.start()))
        start = fence.end()
    spans.append((start, len(markdown)))
    return spans


def _targets(markdown: str) -> list[tuple[int, int, str]]:
    """``(start, end, target)`` of every inline link or image target outside code blocks."""
    found = []
    for lo, hi in _outside_text(markdown):
        for m in _LINK.finditer(markdown, lo, hi):
            found.append((m.start(2), m.end(2), m.group(2)))
    return found


def _repo_path(page_origin: str, target: str) -> str | None:
    """The repository path a relative link of the page at ``page_origin`` points to, if any."""
    if re.match(r'^[a-z][a-z0-9+.-]*:', target, re.IGNORECASE) or target.startswith(('#', '/')):
        return None
    path = unquote(target.split('#', 1)[0])
    if not path:
        return None
    resolved = posixpath.normpath(posixpath.join(posixpath.dirname(page_origin), path))
    if resolved.startswith('..'):
        return None
    if (ROOT / resolved).is_dir() and (ROOT / resolved / 'README.md').is_file():
        resolved = posixpath.join(resolved, 'README.md')
    return resolved if (ROOT / resolved).is_file() else None


def _site_uri(repo_path: str) -> str:
    if repo_path.startswith('docs/'):
        return repo_path[len('docs/'):]
    return ROOT_PAGES.get(repo_path, f'repo/{repo_path}')


def _add(files: Files, config: Any, src_uri: str, origin: str, content: str | None = None) -> None:
    if files.get_file_from_path(src_uri) is None:
        if content is None:
            files.append(File.generated(config, src_uri, abs_src_path=str(ROOT / origin)))
        else:
            files.append(File.generated(config, src_uri, content=content))
    _origin[src_uri] = origin


def on_files(files: Files, config: Any) -> Files:
    _origin.clear()
    docs = PurePosixPath(os.path.relpath(config['docs_dir'], ROOT)).as_posix()
    for f in files.documentation_pages():
        _origin[f.src_uri] = f'{docs}/{f.src_uri}'
    _add(files, config, CLI_PAGE, f'{docs}/{CLI_PAGE}', content=_cli_page())
    for name, uri in ROOT_PAGES.items():
        _add(files, config, uri, name)
    licence = (ROOT / 'LICENSE').read_text()
    _add(files, config, 'license.md', 'LICENSE',
         content=f'# License\n\n```text\n{licence}\n```\n')
    # Follow links out of docs/ into the repository, transitively through included pages.
    todo = [uri for uri in _origin if uri.endswith('.md')]
    while todo:
        uri = todo.pop()
        file = files.get_file_from_path(uri)
        assert file is not None
        for _, _, target in _targets(file.content_string):
            repo_path = _repo_path(_origin[uri], target)
            if repo_path is None or repo_path.startswith(f'{docs}/'):
                continue
            site = _site_uri(repo_path)
            if site not in _origin:
                _add(files, config, site, repo_path)
                if site.endswith('.md'):
                    todo.append(site)
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Files) -> str:
    uri = page.file.src_uri
    origin = _origin.get(uri)
    if origin is None:
        return markdown
    here = posixpath.dirname(uri)
    out, last = [], 0
    for start, end, target in _targets(markdown):
        repo_path = _repo_path(origin, target)
        if repo_path is None:
            continue
        fragment = '#' + target.split('#', 1)[1] if '#' in target else ''
        new = posixpath.relpath(_site_uri(repo_path), here or '.') + fragment
        if new != target:
            out += [markdown[last:start], new]
            last = end
    out.append(markdown[last:])
    return ''.join(out)

"""The static files the GUI server may send: a fixed table built at start-up.

Requests are looked up in the table by their exact URL path; nothing from a request ever
reaches the file system, so ``..``, encoded slashes and absolute paths cannot name another
file. The table holds the regular files directly inside the web
directory (``index.html``, ``app.js``, ``style.css``...) and three.js from its npm package:

* ``/vendor/three.module.js`` and ``/vendor/three.core.js`` <- ``node_modules/three/build/``
* ``/vendor/OrbitControls.js`` <- ``node_modules/three/examples/jsm/controls/``
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

CONTENT_TYPES = {
    '.html': 'text/html; charset=utf-8',
    '.js': 'text/javascript; charset=utf-8',
    '.css': 'text/css; charset=utf-8',
    '.png': 'image/png',
    '.svg': 'image/svg+xml',
}
"""Served extensions and their Content-Type."""

VENDOR = {
    '/vendor/three.module.js': 'node_modules/three/build/three.module.js',
    '/vendor/three.core.js': 'node_modules/three/build/three.core.js',
    '/vendor/OrbitControls.js': 'node_modules/three/examples/jsm/controls/OrbitControls.js',
}
"""URL -> path under the web directory of the third-party modules."""


@dataclass(frozen=True)
class StaticFile:
    """One servable file."""

    path: Path
    """Resolved location on disk."""
    content_type: str
    """Content-Type header."""


def find_web_root() -> Path:
    """The ``web`` directory: the source tree's (develop install) or the installed share one.

    Raises:
        FileNotFoundError: neither exists.
    """
    here = Path(__file__).resolve()
    candidates = [here.parents[1] / 'web']
    try:
        from ament_index_python.packages import get_package_share_directory, PackageNotFoundError
        with contextlib.suppress(PackageNotFoundError):
            candidates.append(Path(get_package_share_directory('cgail_gui')) / 'web')
    except ImportError:
        pass
    for c in candidates:
        if (c / 'index.html').is_file():
            return c
    raise FileNotFoundError(f'expected the GUI page at one of {[str(c) for c in candidates]}, '
                            f'found none')


def build_table(web_root: Path) -> dict[str, StaticFile]:
    """URL path -> file for every servable file under ``web_root``.

    Missing vendor files (``npm ci`` not run) are left out; :func:`missing_vendor` names them.
    """
    root = Path(web_root)
    table: dict[str, StaticFile] = {}
    for entry in sorted(root.iterdir()):
        ctype = CONTENT_TYPES.get(entry.suffix)
        # regular files, or links to them (a colcon --symlink-install share directory)
        if ctype and not entry.name.startswith('.') and entry.is_file():
            table['/' + entry.name] = StaticFile(entry.resolve(), ctype)
    for url, rel in VENDOR.items():
        p = root / rel
        if p.is_file():
            table[url] = StaticFile(p.resolve(), CONTENT_TYPES['.js'])
    if '/index.html' in table:
        table['/'] = table['/index.html']
    return table


def missing_vendor(table: dict[str, StaticFile]) -> list[str]:
    """Vendor URLs the table lacks (three.js not installed)."""
    return [url for url in VENDOR if url not in table]


def lookup(table: dict[str, StaticFile], request_path: str) -> StaticFile | None:
    """The file for a request target (query string ignored), or None (-> 404)."""
    path = request_path.split('?', 1)[0].split('#', 1)[0]
    return table.get(path)

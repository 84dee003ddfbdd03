"""Bags the page may replay: a listing under one directory, chosen by name only."""

from __future__ import annotations

from pathlib import Path


def list_bags(root: str | Path, max_depth: int = 3) -> dict[str, Path]:
    """Name -> path of every rosbag2 under ``root``, names relative with ``/``.

    A bag is a directory holding ``metadata.yaml`` (rosbag2 layout) or a lone ``.mcap`` file
    not inside such a directory. Hidden entries and symlinks are skipped. The page can only
    ask for a name from this listing, never for a path.

    Args:
        root: directory to search ('' or a missing directory: no bags).
        max_depth: directory levels searched below ``root``.
    """
    if not str(root):
        return {}
    base = Path(root)
    if not base.is_dir():
        return {}
    found: dict[str, Path] = {}

    def walk(d: Path, depth: int) -> None:
        try:
            entries = sorted(d.iterdir())
        except OSError:
            return
        if (d / 'metadata.yaml').is_file() and d != base:
            found[d.relative_to(base).as_posix()] = d
            return
        for e in entries:
            if e.name.startswith('.') or e.is_symlink():
                continue
            if e.is_file() and e.suffix == '.mcap':
                found[e.relative_to(base).as_posix()] = e
            elif e.is_dir() and depth < max_depth:
                walk(e, depth + 1)

    walk(base, 0)
    return found

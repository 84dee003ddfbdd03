"""Versioned store of what the page shows (:class:`GuiState`), safe across threads.

Each item (``path``, ``tip``, ``mesh``...) is a JSON-ready dict. Every :meth:`GuiState.set`
bumps a global counter and records it as the item's version, so each page connection keeps the
versions it has sent and asks for :meth:`GuiState.changes_since` them: items that changed several
times in between go out once with their newest value (coalescing), and a fresh connection (empty
versions) gets the full state.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
import threading
from typing import Any

ITEMS = ('config', 'mesh', 'deform', 'path', 'target', 'tip', 'guide', 'waypoint', 'bend',
         'diagnostics', 'trial', 'replay', 'record')
"""Known item names, in the order a full state lists them."""


class GuiState:
    """Latest value of every item with a version counter.

    Args:
        on_change: called (from the setting thread, outside the lock) after every change;
            the server uses it to wake its senders.
    """

    def __init__(self, on_change: Callable[[], None] | None = None) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, Any] = {}
        self._versions: dict[str, int] = {}
        self._counter = 0
        self.on_change = on_change

    def set(self, name: str, value: Any) -> int:
        """Store ``value`` (JSON-ready; None clears the item) and return its new version."""
        if name not in ITEMS:
            raise ValueError(f'item must be one of {ITEMS}, found {name!r}')
        with self._lock:
            self._counter += 1
            self._values[name] = value
            self._versions[name] = self._counter
            version = self._counter
        if self.on_change is not None:
            self.on_change()
        return version

    def get(self, name: str) -> Any:
        """The current value of an item (None when never set)."""
        with self._lock:
            return self._values.get(name)

    @property
    def version(self) -> int:
        """The newest version of any item (0 when nothing was set)."""
        with self._lock:
            return self._counter

    def changes_since(self, sent: Mapping[str, int]) -> tuple[dict[str, Any], dict[str, int]]:
        """Items newer than the versions in ``sent``.

        Returns:
            ``(items, versions)``: the changed items (in :data:`ITEMS` order) and the versions
            to remember for the next call.
        """
        with self._lock:
            changed = {name: self._values[name] for name in ITEMS
                       if name in self._versions and self._versions[name] > sent.get(name, 0)}
            return changed, dict(self._versions)

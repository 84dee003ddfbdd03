"""Exceptions of the bag tools (recorder, player, metrics)."""

from __future__ import annotations


class BagError(ValueError):
    """A bag cannot be read or written: missing, truncated, corrupt, or without a needed topic.

    The message names the bag path and what is wrong, e.g.
    ``bags/x: truncated or corrupt MCAP file bags/x/x.mcap (expected ..., found ...)``.
    """

"""In-process node tests: the ``ros`` fixture of :mod:`cgail_node_utils.testing` (its docstring
holds the rules that keep these tests true on a loaded machine)."""

from cgail_node_utils.testing import ros  # noqa: F401

"""Guidance GUI: browser page + WebSocket state stream (pure python, no rclpy).

* :mod:`.config` - :class:`GuiConfig` (bind address, port, rates, limits).
* :mod:`.guidance` - tip-frame maths shown in the internal view (numpy).
* :mod:`.state` - :class:`GuiState`, the latest value of every item, with change tracking.
* :mod:`.protocol` - the JSON messages between the node and the page.
* :mod:`.static` - the fixed table of static files the server may send (no path traversal).
* :mod:`.server` - :class:`GuiServer`, HTTP + WebSocket on one port, asyncio in a thread.

The rclpy wrapper is :mod:`cgail_gui.nodes.gui_node`.
"""

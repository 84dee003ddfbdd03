"""A node that owns a viewer server (:mod:`cgail_gui.hw`): the one place its shutdown lives."""

from __future__ import annotations

from typing import Any

from rclpy.node import Node


class ServerNode(Node):
    """A :class:`~rclpy.node.Node` with a ``server`` (anything with ``close()``: the
    OpenIGTLink or the Foxglove server) that is closed, threads and sockets, before the node is
    destroyed; a node whose constructor failed before the server existed is destroyed as is."""

    server: Any

    def destroy_node(self) -> None:
        """Stop the server (its threads and connections), then the node."""
        server = getattr(self, 'server', None)
        if server is not None:
            server.close()
        super().destroy_node()

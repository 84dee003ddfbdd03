"""The Foxglove WebSocket server of ``foxglove_bridge``: foxglove-sdk, ros2msg/cdr channels.

:class:`FoxgloveServer` owns a foxglove-sdk context of its own (so two bridges in one process,
or a test beside a node, never share channels), its WebSocket server and one channel per
topic, each with the ``ros2msg`` schema of its type as the trial bags store it
(:data:`cgail_bags.bagio.TYPESTORE`, ROS 2 Jazzy's definitions) and ``cdr`` messages: the
bytes as published. foxglove-sdk speaks the ``foxglove.sdk.v1`` WebSocket subprotocol;
messages go only to the clients subscribed to their channel, and a slow client loses its
oldest messages, never the rig's time.

A client that subscribes to a channel is remembered (:meth:`FoxgloveServer.take_subscribed`)
so that the node sends it the latched state it kept; the listener runs on the server's own
thread and only records the topic.
"""

from __future__ import annotations

import threading
from typing import Any

import foxglove
from foxglove.websocket import ChannelView, Client, ServerListener

from cgail_bags.bagio import TYPESTORE

#: Message encoding and schema encoding of every channel.
MESSAGE_ENCODING = 'cdr'
SCHEMA_ENCODING = 'ros2msg'


class FoxgloveServerError(OSError):
    """The WebSocket server could not start (port in use, address not on this machine)."""


def ros2msg_schema(msg_type: str) -> bytes:
    """The ``ros2msg`` schema of ``pkg/msg/Name``: its definition followed by every nested
    type's (``MSG: pkg/Name`` sections), as MCAP files and Foxglove read it.

    Raises:
        KeyError: a type ROS 2 Jazzy does not define.
    """
    text, _ = TYPESTORE.generate_msgdef(msg_type, ros_version=2)
    return text.encode()


class _Listener(ServerListener):
    """foxglove-sdk's ServerListener: records each channel a client subscribes to."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.subscribed: set[str] = set()
        self.subscriptions = 0

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        with self.lock:
            self.subscribed.add(channel.topic)
            self.subscriptions += 1


class FoxgloveServer:
    """A foxglove-sdk WebSocket server on ``host:port`` with ros2msg/cdr channels.

    Raises:
        FoxgloveServerError: the server cannot listen there (one line: where and why).
    """

    def __init__(self, host: str, port: int, name: str = 'cgail rig') -> None:
        self._context = foxglove.Context()
        self._listener = _Listener()
        try:
            self._server = foxglove.start_server(
                name=name, host=host, port=port, context=self._context,
                server_listener=self._listener)
        except RuntimeError as exc:  # foxglove-sdk's FoxgloveError
            reason = str(exc).removeprefix('FoxgloveError: ')
            raise FoxgloveServerError(f'expected to serve Foxglove on {host}:{port}, found: '
                                      f'{reason}') from None
        self.host = host
        self._channels: dict[str, Any] = {}

    @property
    def port(self) -> int:
        """The port listened on (the one chosen when ``port`` was 0)."""
        return int(self._server.port)

    @property
    def url(self) -> str:
        """The WebSocket URL a client opens."""
        host = f'[{self.host}]' if ':' in self.host else self.host
        return f'ws://{host}:{self.port}'

    @property
    def subscriptions(self) -> int:
        """Channel subscriptions made by clients so far."""
        with self._listener.lock:
            return self._listener.subscriptions

    def add_channel(self, topic: str, msg_type: str) -> None:
        """Advertise ``topic`` (absolute) carrying ``msg_type`` to every client.

        Raises:
            KeyError: a type ROS 2 Jazzy does not define.
        """
        schema = foxglove.Schema(name=msg_type, encoding=SCHEMA_ENCODING,
                                 data=ros2msg_schema(msg_type))
        self._channels[topic] = foxglove.Channel(topic, schema=schema,
                                                 message_encoding=MESSAGE_ENCODING,
                                                 context=self._context)

    def log(self, topic: str, data: bytes, log_time_ns: int) -> None:
        """Send a message (its CDR bytes) to the clients subscribed to ``topic``."""
        self._channels[topic].log(bytes(data), log_time=log_time_ns)

    def take_subscribed(self) -> set[str]:
        """The topics clients subscribed to since the last call."""
        with self._listener.lock:
            topics, self._listener.subscribed = self._listener.subscribed, set()
        return topics

    def close(self) -> None:
        """Stop the server (its connections and threads); the channels close with it."""
        self._server.stop()
        for channel in self._channels.values():
            channel.close()
        self._channels.clear()

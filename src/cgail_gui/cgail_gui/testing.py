"""Test helpers of cgail_gui (imported by tests only): a Foxglove WebSocket client.

:class:`FoxgloveClient` stands in for the Foxglove app in front of ``foxglove_bridge``: it
opens the WebSocket with the ``foxglove.sdk.v1`` subprotocol, reads ``serverInfo`` and the
``advertise`` of each channel, subscribes to topics and decodes every message as the app does,
from the channel's advertised ``ros2msg`` schema (rosbags parses it; nothing of the bridge's
own type store is used) and its CDR bytes. It runs on a thread of its own, so a test can spin
ROS or run a session meanwhile.

Binary frames of the protocol: opcode ``0x01`` (message data), then the subscription id
(uint32 LE), the log time (uint64 LE, ns) and the payload.
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import ExitStack
import json
import struct
import threading
import time
from typing import Any

from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
from websockets.typing import Subprotocol

SUBPROTOCOL = Subprotocol('foxglove.sdk.v1')
MESSAGE_DATA = 0x01
_HEADER = struct.Struct('<BIQ')


class FoxgloveClient:
    """A Foxglove WebSocket client on ``url`` that keeps every decoded message of ``topics``.

    Attributes:
        channels: topic -> the channel's advertisement (``id``, ``encoding``, ``schemaName``,
            ``schemaEncoding``, ``schema``).
        messages: topic -> ``(log_time_ns, decoded message)`` in arrival order.
        server_info: the ``serverInfo`` message.
    """

    def __init__(self, url: str, topics: Sequence[str], connect_timeout_s: float = 30.0) -> None:
        self.url, self.wanted = url, set(topics)
        self.channels: dict[str, dict[str, Any]] = {}
        self.messages: dict[str, list[tuple[int, Any]]] = {}
        self.server_info: dict[str, Any] = {}
        self.errors: list[str] = []
        self._subscriptions: dict[int, str] = {}
        self._typestore = get_typestore(Stores.EMPTY)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._exit = ExitStack()
        deadline = time.monotonic() + connect_timeout_s
        while True:  # (the server may still be starting)
            try:
                self._ws = self._exit.enter_context(connect(
                    url, subprotocols=[SUBPROTOCOL], open_timeout=5.0, max_size=None))
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        self._thread = threading.Thread(target=self._run, name='foxglove_client', daemon=True)
        self._thread.start()

    def received(self, topic: str) -> list[tuple[int, Any]]:
        """The messages of ``topic`` so far (a copy)."""
        with self._lock:
            return list(self.messages.get(topic, ()))

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    frame = self._ws.recv(timeout=0.1)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    self._on_text(json.loads(frame))
                else:
                    self._on_binary(frame)
        except ConnectionClosed:
            pass
        except Exception as exc:  # kept for the test to report
            self.errors.append(f'{type(exc).__name__}: {exc}')

    def _on_text(self, msg: dict[str, Any]) -> None:
        if msg['op'] == 'serverInfo':
            self.server_info = msg
        elif msg['op'] == 'advertise':
            subscribe = []
            for channel in msg['channels']:
                self.channels[channel['topic']] = channel
                if channel['topic'] in self.wanted:
                    self._typestore.register(get_types_from_msg(channel['schema'],
                                                                channel['schemaName']))
                    sub_id = len(self._subscriptions) + 1
                    self._subscriptions[sub_id] = channel['topic']
                    subscribe.append({'id': sub_id, 'channelId': channel['id']})
            if subscribe:
                self._ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subscribe}))

    def _on_binary(self, frame: bytes) -> None:
        opcode, sub_id, log_time = _HEADER.unpack_from(frame)
        if opcode != MESSAGE_DATA:
            return
        topic = self._subscriptions[sub_id]
        channel = self.channels[topic]
        assert channel['encoding'] == 'cdr', channel['encoding']
        message = self._typestore.deserialize_cdr(frame[_HEADER.size:], channel['schemaName'])
        with self._lock:
            self.messages.setdefault(topic, []).append((log_time, message))

    def close(self) -> None:
        """Stop the reader thread and close the connection."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._exit.close()

"""An OpenIGTLink server for one client at a time (3D Slicer's OpenIGTLinkIF), on pyigtl.

pyigtl 0.3.4 packs the messages and keeps the outgoing queue (:class:`pyigtl.comm.
OpenIGTLinkBase`); this module serves them. It does not use :class:`pyigtl.OpenIGTLinkServer`
itself, which (in 0.3.4) replaces the process's SIGINT/SIGTERM handlers (rclpy's among them),
binds only 127.0.0.1 or the address of a network interface, spins on a socket its client has
closed, and prints a traceback for every disconnect. Here:

* the server listens on ``host:port`` (port 0: any free port, :attr:`IgtlServer.port`);
* one client at a time (a second one waits in the listen backlog until the first leaves);
* :meth:`IgtlServer.send` queues a message only while a client is connected, and a new client
  starts with an empty queue: nothing piles up without a client, and a client never gets
  stale poses (the queue holds at most 100 messages, pyigtl's bound);
* a client that leaves, resets the connection, sends garbage or stalls a send for
  :data:`SEND_TIMEOUT_S` is dropped (its reason kept in :attr:`IgtlServer.last_error`), and the
  server waits for the next one;
* :meth:`IgtlServer.close` stops the serving thread and closes the sockets, within about
  :data:`POLL_S` when no send is under way.

What a client sends is read (the stream must be drained) and dropped.
"""

from __future__ import annotations

import socket
import socketserver
import struct
import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pyigtl import MessageBase, PointMessage, PolyDataMessage, TransformMessage
from pyigtl.comm import OpenIGTLinkBase

#: Poll period of the serving thread (receive timeout, and how often the queue is looked at), s.
POLL_S = 0.01
#: Longest a single message may take to go out before the client is dropped, s.
SEND_TIMEOUT_S = 5.0
#: Longest :meth:`IgtlServer.close` waits for the serving thread, s.
CLOSE_TIMEOUT_S = 10.0


class _Handler(socketserver.BaseRequestHandler):
    """Serves one client until it leaves or the server closes."""

    server: _TcpServer

    def handle(self) -> None:
        srv = self.server
        sock: socket.socket = self.request
        sock.settimeout(POLL_S)
        srv.begin_client(self.client_address)
        try:
            while not srv.communication_thread_stop_requested:
                try:
                    ahead = sock.recv(1, socket.MSG_PEEK)
                except TimeoutError:
                    ahead = None
                if ahead == b"":
                    srv.last_error = "the client closed the connection"
                    break
                if ahead:
                    srv.receive_and_drop(sock)
                srv.send_queued(sock)
        except (OSError, ValueError, TypeError, struct.error) as exc:  # (pyigtl's unpack)
            srv.last_error = f"{type(exc).__name__}: {exc}"
        finally:
            srv.end_client()


class _TcpServer(socketserver.TCPServer, OpenIGTLinkBase):
    """pyigtl's queue and framing on a plain TCP server (module docstring)."""

    allow_reuse_address = True  # (restart at once on the same port: TIME_WAIT is no obstacle)

    def __init__(self, host: str, port: int) -> None:
        OpenIGTLinkBase.__init__(self)
        if ":" in host:
            self.address_family = socket.AF_INET6
        socketserver.TCPServer.__init__(self, (host, port), _Handler)
        self.connections = 0
        self.client: tuple[Any, ...] | None = None
        self.last_error = ""

    def begin_client(self, address: tuple[Any, ...]) -> None:
        with self.lock_outgoing_messages:
            self.outgoing_messages.clear()
        self.client = address
        self.connections += 1
        self._connected = True

    def end_client(self) -> None:
        self._connected = False
        self.client = None
        with self.lock_outgoing_messages:
            self.outgoing_messages.clear()

    def receive_and_drop(self, sock: socket.socket) -> None:
        while self._receive_message_from_socket(sock):
            pass
        with self.lock_incoming_messages:
            self.incoming_messages.clear()

    def send_queued(self, sock: socket.socket) -> None:
        while True:
            with self.lock_outgoing_messages:
                if not self.outgoing_messages:
                    return
                message = self.outgoing_messages.popleft()
            data = message.pack()
            sock.settimeout(SEND_TIMEOUT_S)
            try:
                sock.sendall(data)
            finally:
                sock.settimeout(POLL_S)


class IgtlServer:
    """An OpenIGTLink server on ``host:port`` serving one client at a time.

    Args:
        host: address to listen on (``127.0.0.1``: this machine only).
        port: TCP port; 0 picks a free one (:attr:`port`).

    Raises:
        OSError: the address cannot be bound (port in use, no such address).
    """

    def __init__(self, host: str, port: int) -> None:
        self._server = _TcpServer(host, port)
        self.host = host
        self.port = int(self._server.server_address[1])
        """The port listened on (the one picked when 0 was asked for)."""
        self._closed = False
        self._thread = threading.Thread(target=self._server.serve_forever,
                                        kwargs={"poll_interval": 0.1},
                                        name=f"igtl-server-{self.port}", daemon=True)
        self._thread.start()

    @property
    def connected(self) -> bool:
        """A client is connected."""
        return bool(self._server._connected)

    @property
    def connections(self) -> int:
        """Clients accepted so far (a new value: a new client, who needs the full picture)."""
        return self._server.connections

    @property
    def client(self) -> tuple[Any, ...] | None:
        """The connected client's address."""
        return self._server.client

    @property
    def last_error(self) -> str:
        """Why the last client was dropped ('' before any)."""
        return self._server.last_error

    @property
    def queued(self) -> int:
        """Messages waiting to go out."""
        with self._server.lock_outgoing_messages:
            return len(self._server.outgoing_messages)

    @property
    def running(self) -> bool:
        """The serving thread is alive."""
        return self._thread.is_alive()

    def send(self, message: MessageBase) -> bool:
        """Queue ``message`` for the connected client; False (dropped) when there is none."""
        if self._closed or not self._server._connected:
            return False
        return bool(self._server.send_message(message, wait=False))

    def close(self) -> None:
        """Drop the client, stop the serving thread and close the listening socket."""
        if self._closed:
            return
        self._closed = True
        self._server.communication_thread_stop_requested = True
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(CLOSE_TIMEOUT_S)


# ------------------------------------------------------------------------------ messages
def transform_message(device: str, matrix: NDArray[np.float64],
                      timestamp: float) -> TransformMessage:
    """A TRANSFORM (4x4; OpenIGTLink carries its 3x4 upper part as float32)."""
    return TransformMessage(np.asarray(matrix, dtype=np.float64), timestamp=timestamp,
                            device_name=device)


def point_message(device: str, positions: NDArray[np.float64], names: list[str],
                  timestamp: float, diameter: float = 0.0,
                  rgba: tuple[int, int, int, int] = (255, 40, 40, 255)) -> PointMessage:
    """A POINT message of (N, 3) positions, one name each."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    return PointMessage(positions=p, names=list(names), rgba_colors=list(rgba),
                        diameters=float(diameter), timestamp=timestamp, device_name=device)


def polydata_message(device: str, points: NDArray[np.float64], timestamp: float, *,
                     lines: NDArray[np.uint32] | None = None,
                     polygons: NDArray[np.uint32] | None = None) -> PolyDataMessage:
    """A POLYDATA of (N, 3) points with VTK cell arrays (:func:`cgail_gui.core.igtl.
    polygon_cells`, :func:`~cgail_gui.core.igtl.line_cells`); empty arrays are left out."""
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    return PolyDataMessage(points=p,
                           lines=lines if lines is not None and len(lines) else None,
                           polygons=polygons if polygons is not None and len(polygons) else None,
                           timestamp=timestamp, device_name=device)


class PolyDataReader(MessageBase):
    """POLYDATA as a Python client reads it: pyigtl 0.3.4 packs POLYDATA but cannot unpack it
    (3D Slicer can). :func:`read_polydata_in_clients` registers it with pyigtl's parser, after
    which a ``pyigtl.OpenIGTLinkClient`` hands out POLYDATA messages with ``points`` (N, 3) and
    the VTK cell arrays ``vertices``, ``lines``, ``polygons`` and ``strips``."""

    def __init__(self, timestamp: float | None = None, device_name: str | None = None) -> None:
        super().__init__(timestamp=timestamp, device_name=device_name)
        self._message_type = 'POLYDATA'
        self._valid_message = True

    def _unpack_content(self, content: bytes) -> None:
        head = struct.unpack('>10I', content[:40])
        n, offset = head[0], 40
        self.points = np.frombuffer(content[offset:offset + 12 * n], '>f4').reshape(n, 3)
        offset += 12 * n
        cells = []
        for size in head[2:9:2]:  # vertices, lines, polygons, strips
            cells.append(np.frombuffer(content[offset:offset + size], '>u4').astype(np.int64))
            offset += size
        self.vertices, self.lines, self.polygons, self.strips = cells


def read_polydata_in_clients() -> None:
    """Let pyigtl's clients in this process unpack POLYDATA (:class:`PolyDataReader`)."""
    import pyigtl.messages

    pyigtl.messages.message_type_to_class_constructor['POLYDATA'] = PolyDataReader

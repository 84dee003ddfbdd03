"""HTTP + WebSocket server of the guidance page (:class:`GuiServer`), asyncio in a thread.

One port serves both: ``GET /ws`` upgrades to the WebSocket, any other ``GET`` is answered
from the fixed static table (:mod:`cgail_gui.static`) or 404. Each page connection
runs a sender that wakes when the active :class:`~cgail_gui.state.GuiState` changes,
sends the items newer than what that page has (the full state on connect, on ``resync`` and
when the source switches between live and replay), waits for the page's ``ack`` (one state
in flight) and until ``1 / max_rate_hz`` has passed since its last send, so bursts are merged
and a page that draws slowly never builds a queue.
Client messages are parsed by :func:`~cgail_gui.protocol.parse_client_message`;
malformed ones are logged and ignored. A WebSocket handshake from another web origin, or
with a Host header that is not an IP literal or ``localhost`` (DNS rebinding), is refused
(403), so a foreign page open in the same browser cannot drive the GUI.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
import contextlib
from dataclasses import dataclass
from http import HTTPStatus
import ipaddress
import logging
import threading
import time
from urllib.parse import urlsplit

from websockets.asyncio.server import serve, Server, ServerConnection
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from cgail_gui.config import GuiConfig
from cgail_gui.errors import ProtocolError, ServerError
from cgail_gui.protocol import (
    ClientCommand,
    encode_state,
    MAX_CLIENT_MESSAGE,
    parse_client_message,
)
from cgail_gui.state import GuiState
from cgail_gui.static import StaticFile

ACK_TIMEOUT_S = 1.0
"""Longest wait for a page's ack before the next state is sent anyway, s."""

Log = Callable[[str, str], None]
"""``log(level, text)`` with level ``info``, ``warn`` or ``error``."""


@dataclass
class ServerStats:
    """Counters reported in the node's diagnostics."""

    clients: int = 0
    connections_total: int = 0
    messages_sent: int = 0
    malformed_messages: int = 0
    last_malformed: str = ''
    http_requests: int = 0
    http_not_found: int = 0


class GuiServer:
    """Serves the page and streams the active state to every connected page.

    Args:
        config: bind address, port and update rate.
        files: URL path -> static file (see :func:`~cgail_gui.static.build_table`).
        on_command: called in the server thread with each valid page command (``resync`` is
            handled here); exceptions it raises are logged, never fatal.
        log: log sink.
    """

    def __init__(self, config: GuiConfig, files: dict[str, StaticFile],
                 on_command: Callable[[ClientCommand], None], log: Log) -> None:
        self.config = config
        self._bodies = {url: (f.path.read_bytes(), f.content_type) for url, f in files.items()}
        self._on_command = on_command
        self._log = log
        self.stats = ServerStats()
        self._state = GuiState()
        self._source = 'live'
        self._epoch = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Server | None = None
        self._thread: threading.Thread | None = None
        self._wakers: set[asyncio.Event] = set()
        self._wake_pending = threading.Event()
        self.port: int | None = None

    # -- control (any thread) ------------------------------------------------------------------
    def set_source(self, source: str, state: GuiState) -> None:
        """Stream ``state`` from now on (pages get it in full), labelled ``source``."""
        self._state, self._source = state, source
        self._epoch += 1
        self.notify()

    @property
    def source(self) -> str:
        """Label of the state being streamed (``live`` or ``replay``)."""
        return self._source

    def notify_from(self, state: GuiState) -> None:
        """Wake the senders if ``state`` is the one streamed (GuiState.on_change hook)."""
        if state is self._state:
            self.notify()

    def notify(self) -> None:
        """Wake every sender (thread-safe, cheap when a wake-up is already pending)."""
        loop = self._loop
        if loop is None or self._wake_pending.is_set():
            return
        self._wake_pending.set()
        with contextlib.suppress(RuntimeError):  # loop closed while stopping
            loop.call_soon_threadsafe(self._wake_all)

    def start(self, timeout: float = 10.0) -> int:
        """Bind and serve in a daemon thread; returns the bound port.

        Raises:
            ServerError: the address could not be bound (in use, not local...).
        """
        ready = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            loop = asyncio.new_event_loop()
            asyncio.set_event_loop(loop)
            try:
                self._server = loop.run_until_complete(self._open())
                sock = next(iter(self._server.sockets))
                self.port = int(sock.getsockname()[1])
                self._loop = loop
            except OSError as exc:
                failure.append(exc)
                ready.set()
                loop.close()
                return
            ready.set()
            try:
                loop.run_forever()
            finally:
                loop.run_until_complete(loop.shutdown_asyncgens())
                loop.close()

        self._thread = threading.Thread(target=run, name='gui_server', daemon=True)
        self._thread.start()
        if not ready.wait(timeout):
            raise ServerError(f'expected the server to start within {timeout} s, it did not')
        if failure:
            self._thread.join(1.0)
            raise ServerError(f'cannot serve on {self.config.host}:{self.config.port}: '
                              f'{failure[0]}')
        assert self.port is not None
        return self.port

    def stop(self) -> None:
        """Close every connection and the listening socket, end the thread."""
        loop, server = self._loop, self._server
        if loop is None or server is None:
            return

        async def shutdown() -> None:
            server.close()
            await server.wait_closed()
            loop.stop()

        with contextlib.suppress(RuntimeError):
            asyncio.run_coroutine_threadsafe(shutdown(), loop)
        if self._thread is not None:
            self._thread.join(5.0)
        self._loop = None

    # -- asyncio side ----------------------------------------------------------------------------
    async def _open(self) -> Server:
        return await serve(self._handle, self.config.host, self.config.port,
                           process_request=self._process_request, max_size=MAX_CLIENT_MESSAGE,
                           compression=None, ping_interval=5.0, ping_timeout=10.0,
                           logger=logging.getLogger('cgail_gui.websockets'))

    def _wake_all(self) -> None:
        self._wake_pending.clear()
        for event in self._wakers:
            event.set()

    def _process_request(self, connection: ServerConnection, request: Request
                         ) -> Response | None:
        self.stats.http_requests += 1
        path = request.path
        if path.split('?', 1)[0] == '/ws':
            origin = request.headers.get('Origin')
            host = request.headers.get('Host', '')
            if not _local_host(host):
                self._log('warn', f'refused a WebSocket for host {host[:80]!r} (DNS rebinding?)')
                return _response(HTTPStatus.FORBIDDEN, b'host refused\n',
                                 'text/plain; charset=utf-8')
            if origin is not None and urlsplit(origin).netloc != host:
                self._log('warn', f'refused a WebSocket from origin {origin[:80]!r} '
                                  f'(page served as {host[:80]!r})')
                return _response(HTTPStatus.FORBIDDEN, b'cross-origin WebSocket refused\n',
                                 'text/plain; charset=utf-8')
            return None
        entry = lookup_body(self._bodies, path)
        if entry is None:
            self.stats.http_not_found += 1
            return _response(HTTPStatus.NOT_FOUND, b'not found\n', 'text/plain; charset=utf-8')
        return _response(HTTPStatus.OK, *entry)

    async def _handle(self, ws: ServerConnection) -> None:
        self.stats.clients += 1
        self.stats.connections_total += 1
        peer = ws.remote_address
        self._log('info', f'page connected from {peer}')
        wake = asyncio.Event()
        wake.set()
        acked = asyncio.Event()
        resync = [True, False]   # [send the full state next, connection closed]
        self._wakers.add(wake)
        reader = asyncio.create_task(self._read(ws, wake, resync, acked))
        reader.add_done_callback(self._reader_done)
        try:
            await self._send_loop(ws, wake, resync, acked)
        except ConnectionClosed:
            pass
        finally:
            reader.cancel()
            self._wakers.discard(wake)
            self.stats.clients -= 1
            self._log('info', f'page disconnected ({peer})')

    async def _send_loop(self, ws: ServerConnection, wake: asyncio.Event,
                         resync: list[bool], acked: asyncio.Event) -> None:
        sent: dict[str, int] = {}
        epoch = -1
        period = 1.0 / self.config.max_rate_hz
        last = 0.0
        while True:
            await wake.wait()
            if resync[1]:
                return
            wait = last + period - time.monotonic()
            if wait > 0.0:
                await asyncio.sleep(wait)
            wake.clear()
            state, source, current = self._state, self._source, self._epoch
            full = resync[0] or current != epoch
            if full:
                sent, resync[0] = {}, False
            items, versions = state.changes_since(sent)
            if not items and not full:
                continue
            acked.clear()
            await ws.send(encode_state(items, full=full, source=source, epoch=current))
            self.stats.messages_sent += 1
            sent, epoch, last = versions, current, time.monotonic()
            # one state in flight: wait for the page's ack (or ACK_TIMEOUT_S for a page that
            # does not ack), so a page that draws slowly gets merged states, never a queue
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(acked.wait(), ACK_TIMEOUT_S)

    def _reader_done(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            self._log('error', f'page reader stopped: {task.exception()!r}')

    async def _read(self, ws: ServerConnection, wake: asyncio.Event,
                    resync: list[bool], acked: asyncio.Event) -> None:
        try:
            async for data in ws:
                try:
                    command = parse_client_message(data)
                except ProtocolError as exc:
                    self.stats.malformed_messages += 1
                    self.stats.last_malformed = str(exc)[:200]
                    self._log('warn', f'ignored a malformed page message: {exc}')
                    continue
                if command.kind == 'ack':
                    acked.set()
                    continue
                if command.kind == 'resync':
                    resync[0] = True
                    wake.set()
                    continue
                try:
                    self._on_command(command)
                except (ValueError, OSError, RuntimeError) as exc:
                    self._log('error', f'page command {command} failed: {exc}')
        except ConnectionClosed:
            pass
        finally:  # wake the sender so that it ends with the connection
            resync[1] = True
            wake.set()
            acked.set()


def _local_host(host: str) -> bool:
    """True when a Host header names an IP literal or localhost (not a DNS name that a
    foreign page could have rebound to this machine)."""
    name = urlsplit(f'//{host}').hostname or ''
    if name == 'localhost':
        return True
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def lookup_body(bodies: dict[str, tuple[bytes, str]], path: str) -> tuple[bytes, str] | None:
    """Body and Content-Type for a request path (exact table match, query ignored)."""
    return bodies.get(path.split('?', 1)[0].split('#', 1)[0])


def _response(status: HTTPStatus, body: bytes, content_type: str) -> Response:
    headers = Headers()
    headers['Content-Type'] = content_type
    headers['Content-Length'] = str(len(body))
    headers['Cache-Control'] = 'no-store'
    headers['X-Content-Type-Options'] = 'nosniff'
    headers['Connection'] = 'close'
    return Response(int(status), status.phrase, headers, body)

"""Headless Chromium driven over the Chrome DevTools Protocol (tests and the GUI benchmark).

Uses only the ``websockets`` package (already a dependency) and the Debian ``chromium``
binary; never downloads a browser. Chromium is started with no outside connections
(``--headless --no-sandbox --disable-gpu --disable-background-networking
--disable-component-update --no-first-run --disable-sync --disable-quic``), a fresh
user-data directory and the DevTools endpoint on 127.0.0.1 only::

    with Chromium.launch() as browser:
        page = browser.open('http://127.0.0.1:8780/')
        page.wait_for('window.gui && window.gui.connected', timeout=20)
        png = page.screenshot()
"""

from __future__ import annotations

import base64
import contextlib
import itertools
import json
import os
from pathlib import Path
import shutil
import subprocess
import tempfile
import time
from types import TracebackType
from typing import Any
import urllib.request

from websockets.sync.client import ClientConnection, connect

from cgail_gui.errors import GuiError

FLAGS = ('--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking',
         '--disable-component-update', '--no-first-run', '--disable-sync', '--disable-quic',
         '--disable-default-apps', '--disable-extensions', '--no-default-browser-check',
         '--metrics-recording-only', '--password-store=basic', '--use-mock-keychain',
         '--enable-unsafe-swiftshader', '--remote-debugging-address=127.0.0.1',
         '--remote-debugging-port=0')
"""Command-line flags: no outside connections, software WebGL, DevTools on loopback."""


class BrowserError(GuiError, RuntimeError):
    """Chromium missing, failed to start, or a DevTools call failed."""


def find_chromium() -> str | None:
    """Path of a Chromium binary (``$CHROMIUM``, ``chromium``, ``chromium-browser``) or None."""
    env = os.environ.get('CHROMIUM')
    if env and Path(env).is_file():
        return env
    for name in ('chromium', 'chromium-browser'):
        found = shutil.which(name)
        if found:
            return found
    return None


class Page:
    """One page target, driven through its DevTools WebSocket."""

    def __init__(self, ws: ClientConnection) -> None:
        self._ws = ws
        self._ids = itertools.count(1)

    def call(self, method: str, timeout: float = 30.0, **params: Any) -> dict[str, Any]:
        """Send one DevTools command and return its ``result`` (events are skipped)."""
        ident = next(self._ids)
        self._ws.send(json.dumps({'id': ident, 'method': method, 'params': params}))
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError(f'{method}: expected a reply within {timeout} s, found none')
            msg = json.loads(self._ws.recv(timeout=left))
            if msg.get('id') == ident:
                if 'error' in msg:
                    raise BrowserError(f'{method} failed: {msg["error"]}')
                return dict(msg.get('result', {}))

    def evaluate(self, expression: str) -> Any:
        """Value of a JavaScript expression (JSON-serialisable; promises are awaited)."""
        result = self.call('Runtime.evaluate', expression=expression, returnByValue=True,
                           awaitPromise=True)
        if 'exceptionDetails' in result:
            raise BrowserError(f'{expression!r} raised {result["exceptionDetails"]}')
        return result.get('result', {}).get('value')

    def wait_for(self, expression: str, timeout: float = 20.0, period: float = 0.05) -> Any:
        """Poll ``expression`` until it is truthy; returns its value.

        Raises:
            BrowserError: still falsy after ``timeout`` s.
        """
        deadline = time.monotonic() + timeout
        value = None
        while time.monotonic() < deadline:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(period)
        raise BrowserError(f'expected {expression!r} to become true within {timeout} s, '
                           f'last value {value!r}')

    def screenshot(self) -> bytes:
        """PNG of the viewport."""
        return base64.b64decode(self.call('Page.captureScreenshot', format='png')['data'])

    def close(self) -> None:
        """Close the DevTools connection."""
        with contextlib.suppress(Exception):
            self._ws.close()


class Chromium:
    """A headless Chromium process with a throw-away profile."""

    def __init__(self, proc: subprocess.Popen[bytes], profile: str, port: int) -> None:
        self._proc, self._profile, self.port = proc, profile, port
        self._connections = contextlib.ExitStack()

    @classmethod
    def launch(cls, width: int = 1600, height: int = 980, timeout: float = 30.0) -> Chromium:
        """Start Chromium and wait for its DevTools endpoint.

        Raises:
            BrowserError: no Chromium binary (install: ``apt-get install chromium``) or it
                did not start within ``timeout`` s.
        """
        binary = find_chromium()
        if binary is None:
            raise BrowserError('expected a chromium binary on PATH, found none '
                               '(Debian: apt-get install -y chromium)')
        profile = tempfile.mkdtemp(prefix='gui-chromium-')
        proc = subprocess.Popen(
            [binary, *FLAGS, f'--user-data-dir={profile}', f'--window-size={width},{height}',
             'about:blank'],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True)
        port_file = Path(profile) / 'DevToolsActivePort'
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                shutil.rmtree(profile, ignore_errors=True)
                raise BrowserError(f'chromium exited at start with status {proc.returncode}')
            with contextlib.suppress(OSError, ValueError, IndexError):
                port = int(port_file.read_text().split()[0])
                return cls(proc, profile, port)
            time.sleep(0.05)
        proc.kill()
        proc.wait()
        shutil.rmtree(profile, ignore_errors=True)
        raise BrowserError(f'expected chromium DevTools within {timeout} s, found none')

    def _json(self, path: str) -> Any:
        with urllib.request.urlopen(f'http://127.0.0.1:{self.port}{path}', timeout=10) as r:
            return json.loads(r.read())

    def open(self, url: str) -> Page:
        """Navigate the first page target to ``url`` and return it."""
        targets = [t for t in self._json('/json/list') if t.get('type') == 'page']
        if not targets:
            raise BrowserError('expected a page target, found none')
        ws = self._connections.enter_context(
            connect(targets[0]['webSocketDebuggerUrl'], max_size=None, open_timeout=10))
        page = Page(ws)
        page.call('Page.enable')
        page.call('Page.navigate', url=url)
        return page

    def close(self) -> None:
        """Kill Chromium (its whole process group) and delete the profile."""
        with contextlib.suppress(Exception):
            self._connections.close()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self._proc.pid, 9)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._proc.wait(10)
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

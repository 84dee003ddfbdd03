"""The recording page of ``record_demos`` in headless Chromium: no path, the keyboard drives.

Skipped only when no Chromium binary is installed (Debian: ``apt-get install -y chromium``).
The screenshot goes to ``$CGAIL_RECORD_SCREENSHOT`` when set (the demonstrations tutorial's
``docs/img/record_demos.png`` is made with ``CGAIL_RECORD_SCREENSHOT=docs/img/record_demos.png``),
else to the test's tmp dir.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import time

import numpy as np
import pytest
from test_record_demos import read_until, start

from cgail_gui.cdp import Chromium, find_chromium, Page

pytestmark = pytest.mark.skipif(find_chromium() is None,
                                reason='chromium not installed (apt-get install -y chromium)')

KEYS = {' ': ('Space', 32), 'e': ('KeyE', 69), 'w': ('KeyW', 87), 'a': ('KeyA', 65),
        'Escape': ('Escape', 27)}


def key(page: Page, name: str, down: bool) -> None:
    code, vk = KEYS[name]
    page.call('Input.dispatchKeyEvent', type='keyDown' if down else 'keyUp', key=name,
              code=code, windowsVirtualKeyCode=vk)


def test_keyboard_drives_the_catheter_on_a_page_without_a_path(tmp_path: Path) -> None:
    out = tmp_path / 'demos'
    proc = start(['--out', str(out), '--driver', 'keyboard', '--episodes', '2', '--time-scale',
                  '2', '--port', '0', '--who', 'browser test', '--pause', '1'])
    try:
        _, url = read_until(proc, r'http://127\.0\.0\.1:\d+/', 120)
        with Chromium.launch() as browser:
            page = browser.open(url)
            page.wait_for('window.gui && window.gui.connected', timeout=30)
            page.wait_for('window.gui.drawn.meshVertices > 0 && window.gui.drawn.target',
                          timeout=60)
            page.wait_for('document.body.classList.contains("recording")', timeout=10)
            state = page.evaluate(
                '({path: window.gui.drawn.pathPoints, title: document.getElementById("title")'
                '.textContent, replay: getComputedStyle(document.getElementById("replay-panel"))'
                '.display, legend: [...document.querySelectorAll(".legend span")].filter('
                's => getComputedStyle(s).display !== "none").map(s => s.textContent), '
                'phase: document.getElementById("rec-phase").textContent})')
            assert state['path'] == 0
            assert state['title'].startswith('Record demonstrations')
            assert state['replay'] == 'none'
            assert 'planned path' not in state['legend'] and 'target' in ' '.join(state['legend'])
            assert state['phase'] == 'Waiting for the first insertion'
            before = np.array(page.evaluate('window.gui.drawn.tipMm'))
            # deadman + insert, then bend up a little while inserting
            key(page, ' ', True)
            key(page, 'e', True)
            time.sleep(1.0)
            key(page, 'w', True)
            time.sleep(0.15)
            key(page, 'w', False)
            key(page, 'a', True)
            time.sleep(0.1)
            key(page, 'a', False)
            time.sleep(1.5)
            key(page, 'e', False)
            key(page, ' ', False)
            page.wait_for('window.gui.drawn.tipMm !== null', timeout=5)
            after = np.array(page.evaluate('window.gui.drawn.tipMm'))
            moved = float(np.linalg.norm(after - before))
            assert moved > 10.0, moved  # mm: ~2.8 s x 2 x 5 mm/s, less the start
            sent = page.evaluate('window.gui.keyboard.sent')
            assert sent >= 10
            phase = page.evaluate('document.getElementById("rec-phase").textContent')
            assert phase.startswith('Recording'), phase
            assert page.evaluate('document.getElementById("ro-bend-k").textContent') \
                == 'Commanded bend'
            page.wait_for('window.gui.renderScale === undefined || window.gui.renderScale === 1',
                          timeout=10)
            time.sleep(0.5)
            png = page.screenshot()
            # Esc discards the episode: the same start and target come again
            key(page, 'Escape', True)
            key(page, 'Escape', False)
            page.wait_for('document.getElementById("rec-phase").textContent'
                          '.startsWith("DISCARDED")', timeout=10)
            page.wait_for('document.getElementById("rec-phase").textContent'
                          ' === "Waiting for the first insertion"', timeout=20)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, rest
    summary = json.loads(rest.strip().splitlines()[-1])
    assert summary['discarded'] == 1 and summary['saved'] == 0 and summary['interrupted']
    assert not out.exists()  # nothing saved, nothing written
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 20_000
    shot = Path(os.environ.get('CGAIL_RECORD_SCREENSHOT') or tmp_path / 'record_demos.png')
    shot.parent.mkdir(parents=True, exist_ok=True)
    shot.write_bytes(png)

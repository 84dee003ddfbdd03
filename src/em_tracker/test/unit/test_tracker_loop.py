"""The tracker link's state machine, stepped by a clock (lockstep) and by its reader thread."""

from __future__ import annotations

import math
import time

import pytest

from em_tracker.core.config import TrackerConfig
from em_tracker.core.errors import DeviceDisconnected, DeviceTimeout, ProtocolError
from em_tracker.core.tracking import LinkState
from em_tracker.hw.aurora import ToolReading, TrackingReply
from em_tracker.hw.tracker_loop import TrackerLoop

VALID = dict(handle=0x0A, visible=True, quat_wxyz=(1.0, 0.0, 0.0, 0.0),
             position_mm=(10.0, -20.0, -150.0), error_mm=0.3, port_status=0x31)


class Device:
    """Scripted device: connect failures, then replies (a frame per read unless repeated)."""

    def __init__(self, fail_connects=0, replies=()):
        self.fail_connects = fail_connects
        self.replies = list(replies)
        self.connect_at: list[float] = []
        self.closed = 0
        self.frame = 0
        self.reads = 0
        self.clock = time.monotonic
        self.reply_time = lambda: -1.0  # ignored in clock mode

    def connect(self):
        self.connect_at.append(self.clock())
        if self.fail_connects:
            self.fail_connects -= 1
            raise DeviceDisconnected('no such port')
        return [0x0A]

    def read(self):
        self.reads += 1
        item = self.replies.pop(0) if self.replies else 'new'
        if isinstance(item, Exception):
            raise item
        if item == 'new':
            self.frame += 1
        return TrackingReply((ToolReading(frame_number=self.frame, **VALID),), 0,
                             self.reply_time())

    def close(self):
        self.closed += 1


def config(**kw):
    return TrackerConfig(port='/dev/null', rate_hz=40.0, reconnect_initial_s=0.5,
                         reconnect_max_s=2.0, max_consecutive_errors=2, **kw)


def test_clock_mode_backoff_is_in_the_callers_seconds() -> None:
    dev = Device(fail_connects=4)
    loop = TrackerLoop(dev, config(poll_mode='clock'), lambda pose, t: None)
    t = 100.0
    dev.clock = lambda: t
    while not loop.tracking:
        due = loop.step(t)
        t = round(t + 0.025, 6)  # a 40 Hz timer of the node clock
        assert due >= t - 0.025
    # failures at 100, then retries after 0.5, 1.0, 2.0, 2.0 (capped) seconds of that clock
    assert [round(a - dev.connect_at[0], 3) for a in dev.connect_at] == \
        [0.0, 0.5, 1.5, 3.5, 5.5]
    assert loop.health.reconnects == 4 and loop.health.link is LinkState.TRACKING


def test_clock_mode_one_poll_per_step_stamped_with_the_callers_time() -> None:
    got: list[tuple[float, float]] = []
    dev = Device(replies=['new', 'repeat', 'new'])
    loop = TrackerLoop(dev, config(poll_mode='clock'),
                       lambda pose, t: got.append((t, pose.position_m[0])))
    assert loop.step(5.0) == 5.0  # connected: poll at once
    assert loop.step(5.0) == pytest.approx(5.0 + 0.95 / 40.0)  # a new frame
    assert loop.step(5.025) == pytest.approx(5.027)  # the same frame again: nothing published
    loop.step(5.05)
    assert got == [(5.0, pytest.approx(0.010)), (5.05, pytest.approx(0.010))]
    assert loop.health.frames.repeated == 1 and loop.health.last_frame_time == 5.05
    assert loop.health.bad_replies == 0  # one period after the frame: early, not stale


def test_a_stale_frame_is_a_bad_reply_and_polled_at_most_at_the_frame_rate() -> None:
    # ndicapi hands back the last frame again (a truncated reply whose CRC was valid): the
    # reader thread, which sleeps until each step's due time, must not poll every 2 ms.
    got: list[float] = []
    dev = Device(replies=['new'] + ['repeat'] * 1000)
    loop = TrackerLoop(dev, config(), lambda pose, t: got.append(t))
    t = loop.step(0.0)  # connected: poll at once
    while t < 2.0:
        t = loop.step(t)
    # 1 new frame at 0; early retries every 2 ms from 0.95 period (23.75 ms) while under 1.5
    # periods (37.5 ms): 7; then stale, once a period from 37.75 ms: 79 up to 2 s
    assert dev.reads == 1 + 7 + 79
    assert loop.health.bad_replies == 79 and loop.health.frames.repeated == 7 + 79
    assert loop.health.last_error == ('stale reply: expected a new frame within 0.038 s, '
                                      'found frame 1 again after 1.988 s')
    assert loop.tracking and len(got) == 1
    dev.replies.clear()  # the device recovers: new frames again, no more bad replies
    t = loop.step(t)
    assert len(got) == 2 and loop.health.bad_replies == 79


def test_thread_mode_polls_a_stale_frame_once_a_period() -> None:
    dev = Device(replies=['new'] + ['repeat'] * 1000)
    dev.reply_time = time.monotonic
    loop = TrackerLoop(dev, config(), lambda pose, t: None)
    t0 = time.monotonic()
    loop.start()
    time.sleep(0.5)
    loop.stop(timeout_s=10.0)
    elapsed = time.monotonic() - t0  # >= 0.5 s; more on a loaded machine
    # at most: 1 new frame, 7 early retries, one poll a period (25 ms) for the rest of the run,
    # +1 for a poll under way at stop (ndicapi's stale frames used to be polled every 2 ms:
    # ~250 reads in 0.5 s); the bound follows the time the loop really ran, not the sleep
    assert dev.reads <= 1 + 7 + math.ceil(elapsed / 0.025) + 1, (dev.reads, elapsed)
    assert loop.health.bad_replies >= 1


def test_bad_replies_then_reconnect() -> None:
    dev = Device(replies=[ProtocolError('bad CRC'), ProtocolError('bad CRC'), 'new'])
    loop = TrackerLoop(dev, config(poll_mode='clock'), lambda pose, t: None)
    loop.step(0.0)
    assert loop.step(0.0) == pytest.approx(0.25 / 40.0)  # one bad reply: retry soon
    assert loop.step(0.1) == pytest.approx(0.6)  # two in a row: link lost, reconnect later
    assert not loop.tracking and dev.closed == 1 and loop.health.bad_replies == 2
    assert loop.step(0.3) == pytest.approx(0.6)  # not yet
    loop.step(0.6)
    assert loop.tracking and len(dev.connect_at) == 2


def test_timeout_loses_the_link_and_stop_closes_it() -> None:
    dev = Device(replies=[DeviceTimeout('no reply')])
    loop = TrackerLoop(dev, config(poll_mode='clock'), lambda pose, t: None)
    loop.step(0.0)
    loop.step(0.0)
    assert loop.health.link is LinkState.DISCONNECTED and 'DeviceTimeout' in \
        loop.health.last_error
    loop.stop()
    assert loop.health.link is LinkState.STOPPED and loop.step(10.0) == float('inf')


def test_thread_mode_waits_the_backoff_on_the_steady_clock() -> None:
    dev = Device(fail_connects=2)
    got: list[float] = []
    cfg = TrackerConfig(port='/dev/null', reconnect_initial_s=0.05, reconnect_max_s=0.1)
    loop = TrackerLoop(dev, cfg, lambda pose, t: got.append(t))
    loop.start()
    deadline = time.monotonic() + 30.0
    while not got and time.monotonic() < deadline:
        time.sleep(0.01)
    loop.stop(timeout_s=10.0)
    assert got, 'no pose within 30 s'
    gaps = [b - a for a, b in zip(dev.connect_at, dev.connect_at[1:], strict=False)]
    assert gaps[0] >= 0.05 and gaps[1] >= 0.1
    assert loop.health.link is LinkState.STOPPED and dev.closed >= 3

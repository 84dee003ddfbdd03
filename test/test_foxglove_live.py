"""The live Foxglove view of a simulated trial (``cgail session --foxglove``): a Foxglove
WebSocket client stands in for the app, subscribes to the rig's topics while the trial runs and
decodes every message from the schema the bridge advertised (cgail_gui.testing.FoxgloveClient):
the tip moves, TF links the tip to the phantom, the markers show the lumen and the plan, the
pressures are the four chambers', and the path and the diagnostics arrive."""

from __future__ import annotations

import socket
import threading

import numpy as np

from cgail_rig.session import main

TOPICS = ('/em_tracker/tip_pose', '/tf', '/tf_static', '/phantom/lumen', '/phantom/markers',
          '/planner/markers', '/pam/pressures', '/planner/path', '/diagnostics')


def test_foxglove_follows_a_simulated_trial_live(tmp_path, monkeypatch) -> None:
    from cgail_gui.testing import FoxgloveClient

    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)  # (the session reserves its own)
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        port = probe.getsockname()[1]
    clients: list[FoxgloveClient] = []

    def app() -> None:  # connects as soon as the trial's rig serves the port
        clients.append(FoxgloveClient(f'ws://127.0.0.1:{port}', TOPICS, connect_timeout_s=90.0))

    thread = threading.Thread(target=app, daemon=True)
    thread.start()
    try:
        assert main(['--trials', '1', '--plant', 'nominal', '--conditions', 'centerline',
                     '--time-limit', '8', '--time-scale', '2', '--foxglove', '--foxglove-port',
                     str(port), '--out', str(tmp_path / 'session')]) == 0
    finally:
        thread.join(timeout=10)
        for client in clients:
            client.close()
    assert clients, f'no Foxglove connection to 127.0.0.1:{port} during the trial'
    client = clients[0]
    assert not client.errors, client.errors
    got = {topic: client.received(topic) for topic in TOPICS}
    assert all(got.values()), {t: len(m) for t, m in got.items()}

    tips = got['/em_tracker/tip_pose']
    assert len(tips) >= 10 and {m.header.frame_id for _, m in tips} == {'phantom'}
    first, last = (np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
                   for _, m in (tips[0], tips[-1]))
    assert np.linalg.norm(last - first) > 1e-3  # m: the tip moved during the trial
    times = [t for t, _ in tips]
    assert times == sorted(times)  # stamped on the session's (simulated) clock, in order

    frames = {(tf.header.frame_id, tf.child_frame_id) for _, m in got['/tf']
              for tf in m.transforms}
    assert ('phantom', 'catheter_tip') in frames, frames
    assert {(tf.header.frame_id, tf.child_frame_id) for _, m in got['/tf_static']
            for tf in m.transforms} == {('aurora', 'phantom')}
    assert {mk.ns for _, m in got['/phantom/lumen'] for mk in m.markers} == {'', 'lumen'}
    assert 'catheter_body' in {mk.ns for _, m in got['/phantom/markers'] for mk in m.markers}
    assert 'path' in {mk.ns for _, m in got['/planner/markers'] for mk in m.markers}
    _, pressures = got['/pam/pressures'][-1]
    assert len(pressures.data) == 4 and pressures.layout.dim[0].label == \
        'alpha_pos,alpha_neg,gamma_pos,gamma_neg'
    _, path = got['/planner/path'][-1]
    assert path.header.frame_id == 'phantom' and len(path.poses) >= 2
    assert {s.name for _, m in got['/diagnostics'] for s in m.status}

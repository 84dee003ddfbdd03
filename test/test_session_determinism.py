"""The simulated session is a function of its seed and configuration, never of the host.

* One short trial run twice in this process, the second time with every core busy with a
  spinning process, gives the same outcome, the same bag (message counts and content) and the
  same metrics (fast). The whole command, once idle with ``--jobs 1`` and once loaded with
  ``--jobs 2``, gives the same bags and metrics too (slow).
* Two sessions started at the same time on one machine pick different ROS domains, receive
  nothing from each other, and give identical results.
* A session refuses to start on a domain where a rig's device node answers.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path
import re
import subprocess
import sys

import pytest

from cgail_bags.bagio import content_digest

ARGS = ['--trials', '1', '--time-limit', '12', '--seed', '3', '--plant', 'nominal']


def test_one_trial_twice_idle_then_loaded_gives_the_same_bag_and_metrics(tmp_path) -> None:
    from cgail_bags.metrics_cli import evaluate_bags
    from cgail_rig.domain import reserve_domain
    from cgail_rig.session import (
        default_policy,
        plan_trials,
        run_trial,
        SessionSettings,
    )

    settings = SessionSettings(policy=str(default_policy()), time_limit=6.0)
    results, metrics = [], []
    with reserve_domain(env={}) as lease:
        for run, load in (('idle', 0), ('loaded', os.cpu_count() or 2)):
            spec = plan_trials(['cgail'], 2, 5, tmp_path / run / 'bags')[1]  # start 1, target 1
            busy = _busy_loops(load)
            try:
                results.append(run_trial(settings, spec, lease.domain_id))
            finally:
                for p in busy:
                    p.kill()
                    p.wait()
            metrics.append(evaluate_bags([Path(spec.bag)], condition='cgail')[0])
    a, b = results
    assert not a.failed and a.outcome == b.outcome == 'time limit 6 s reached', a.outcome
    assert a.callback_errors == b.callback_errors == [] and a.unscheduled == b.unscheduled == 0
    assert a.messages['/em_tracker/tip_pose'] > 250 and a.messages == b.messages
    assert (a.ticks, a.sim_s) == (b.ticks, b.sim_s)
    assert content_digest(a.spec.bag) == content_digest(b.spec.bag)
    for field in ('tracking_mean', 'targeting_error', 'duration'):
        assert getattr(metrics[0], field) == pytest.approx(getattr(metrics[1], field), abs=1e-6)


def _run(out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != 'ROS_DOMAIN_ID'}
    return subprocess.run(
        [sys.executable, '-m', 'cgail_rig.session', '--out', str(out), *ARGS,
         *extra], env=env, capture_output=True, text=True, timeout=600, check=False)


def _bags(out: Path) -> dict[str, dict[str, tuple[int, str]]]:
    return {bag.name: content_digest(bag) for bag in sorted((out / 'bags').glob('*/*'))}


def _metrics(out: Path) -> dict[str, dict[str, str]]:
    with (out / 'metrics.csv').open() as stream:
        return {row['name']: row for row in csv.DictReader(stream)}


def _normal_priority() -> None:
    # a busy loop must not inherit a real-time policy (chrt -f) from the test process
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def _busy_loops(n: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, '-c', 'while True: pass'],
                             preexec_fn=_normal_priority) for _ in range(n)]


@pytest.mark.slow
def test_same_bags_and_metrics_idle_in_one_job_and_loaded_in_two(tmp_path) -> None:
    idle = _run(tmp_path / 'idle', '--jobs', '1')
    assert idle.returncode == 0, idle.stdout + idle.stderr
    busy = _busy_loops(os.cpu_count() or 2)
    try:
        loaded = _run(tmp_path / 'loaded', '--jobs', '2')
    finally:
        for p in busy:
            p.kill()
            p.wait()
    assert loaded.returncode == 0, loaded.stdout + loaded.stderr
    a, b = _bags(tmp_path / 'idle'), _bags(tmp_path / 'loaded')
    assert sorted(a) == ['centerline_01', 'cgail_01']
    for name in a:
        counts = {topic: n for topic, (n, _) in a[name].items()}
        assert counts['/em_tracker/tip_pose'] > 300, counts  # 12 s of 40 Hz tracking
        assert counts == {topic: n for topic, (n, _) in b[name].items()}, name
        assert a[name] == b[name], name  # the same messages, bit for bit
    ma, mb = _metrics(tmp_path / 'idle'), _metrics(tmp_path / 'loaded')
    for name in ma:
        assert ma[name]['success'] == mb[name]['success']
        for field in ('tracking_mean', 'targeting_error', 'duration'):
            assert float(ma[name][field]) == pytest.approx(float(mb[name][field]), abs=1e-6)
    # one line per trial, then the table: no node log lines, no rcl warnings on the console
    lines = idle.stdout.splitlines()
    assert sum(1 for line in lines if re.match(r'\[\d/2\] ', line)) == 2
    assert not [line for line in idle.stdout.splitlines() + idle.stderr.splitlines()
                if line.startswith(('[INFO]', '[WARN]', '[ERROR]'))]
    assert list((tmp_path / 'idle' / 'logs').glob('*.log'))


def test_two_concurrent_sessions_pick_their_own_domains_and_do_not_mix(tmp_path) -> None:
    env = {k: v for k, v in os.environ.items() if k != 'ROS_DOMAIN_ID'}
    cmd = [sys.executable, '-m', 'cgail_rig.session', '--trials', '1',
           '--plant', 'nominal', '--time-limit', '4', '--jobs', '1', '--conditions', 'cgail']
    procs = [subprocess.Popen([*cmd, '--out', str(tmp_path / name)], env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
             for name in ('one', 'two')]
    outputs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outputs
    domains = [int(re.search(r'on ROS domain (\d+) \(automatic\)', o).group(1))
               for o in outputs]
    assert domains[0] != domains[1], outputs
    assert not any('from outside the rig' in o for o in outputs), outputs
    assert _bags(tmp_path / 'one') == _bags(tmp_path / 'two')


def test_refuses_to_start_next_to_a_foreign_device_node(tmp_path, monkeypatch, capsys) -> None:
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from cgail_rig import domain
    from cgail_rig.session import main

    # from the top of the range: a rig of an earlier test in this process may have just
    # closed on the lowest free domain, and its node names can linger in discovery for a
    # second or two
    free = domain.reserve_domain(env={}, candidates=range(101, 0, -1), listen_s=0.2)
    domain_id = free.domain_id
    free.release()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    try:
        rig_node = rclpy.create_node('sleeve_driver', context=ctx)  # "the real sleeve driver"
        monkeypatch.setenv('ROS_DOMAIN_ID', str(domain_id))
        monkeypatch.setattr(domain, 'PROBE_S', 3.0)
        code = main(['--out', str(tmp_path / 'out'), '--trials', '1'])
        assert code == 2
        text = capsys.readouterr().err
        assert f'ROS_DOMAIN_ID={domain_id} already has device node(s) /sleeve_driver' in text
        assert not (tmp_path / 'out' / 'bags').exists()
        rig_node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)

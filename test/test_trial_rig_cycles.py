"""Trial after trial in one process (bench/bench_autonomy_soak.py, ``cgail session --jobs 1``):
a closed rig leaves nothing behind (issue 36).

Each :class:`cgail_rig.session.TrialRig` is built and closed a few times; after the first
(which loads the caches) the live rclpy nodes, contexts, executors, Python threads, OS threads
and file descriptors return to the same counts after every close (object counts, not memory:
deterministic), the rig's context is shut down, the heap it freed is handed back to the OS, and
glibc's heap arenas are capped before the rig starts its threads.
No node of the rig serves type descriptions (the service leaves heap behind per node in Jazzy's
rclpy: ``cgail_rig.launcher.LEAN_PARAMETERS``).
"""

from collections import Counter
import gc
import os
from pathlib import Path
import threading

from cgail_rig import session as s


def _live() -> dict[str, int]:
    from rclpy.context import Context
    from rclpy.executors import Executor
    from rclpy.node import Node

    from cgail_rig.lockstep import LockstepExecutor

    gc.collect()
    kinds: Counter[str] = Counter()
    for obj in gc.get_objects():
        for name, cls in (('nodes', Node), ('contexts', Context), ('executors', Executor),
                          ('lockstep executors', LockstepExecutor)):
            if isinstance(obj, cls):
                kinds[name] += 1
    return {**kinds, 'threads': threading.active_count(),
            'os threads': len(os.listdir('/proc/self/task')),
            'fds': len(os.listdir('/proc/self/fd'))}


def _ok(context) -> bool:
    from rclpy.exceptions import InvalidHandle

    try:
        return context.ok()
    except InvalidHandle:  # shut down and destroyed
        return False


def test_a_closed_rig_leaves_no_nodes_contexts_threads_or_fds(tmp_path: Path,
                                                              monkeypatch) -> None:
    from cgail_rig.domain import reserve_domain

    trimmed: list[int] = []
    release = s.release_freed_heap

    def counted() -> None:
        trimmed.append(1)
        release()

    monkeypatch.setattr(s, 'release_freed_heap', counted)
    capped: list[int] = []
    limit = s.limit_heap_arenas
    monkeypatch.setattr(s, 'limit_heap_arenas', lambda: (capped.append(1), limit()))
    settings = s.SessionSettings(policy=str(s.default_policy()), plant='true', plant_seed=0)
    autonomous, shared = (s.plan_trials([c], 2, 0, tmp_path / 'bags')
                          for c in ('autonomous', 'shared'))
    specs = [autonomous[0], shared[0], autonomous[1]]  # (the operator node in between)
    lease = reserve_domain(env={})
    try:
        counts = []
        for spec in specs:
            rig = s.TrialRig(settings, spec, lease.domain_id)
            context = rig.context
            assert rig.executor.nodes  # (the rig was built)
            # no node serves type descriptions: rclpy keeps ~1 KB of heap per node that did,
            # after it is destroyed (launcher.LEAN_PARAMETERS)
            assert not [n.get_name() for n in rig.executor.nodes if any(
                srv.srv_name.endswith('/get_type_description') for srv in n.services)]
            rig.close()
            assert not _ok(context)
            del rig, context
            counts.append(_live())
    finally:
        lease.release()
    assert counts[1] == counts[0] and counts[2] == counts[0], counts
    assert counts[0].get('nodes', 0) == 0 and counts[0].get('lockstep executors', 0) == 0
    assert trimmed == [1, 1, 1]  # the freed heap went back after every close
    assert capped == [1, 1, 1]  # glibc's arenas capped before each rig's middleware threads

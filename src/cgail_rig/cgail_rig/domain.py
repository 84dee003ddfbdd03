"""ROS domains of simulated sessions: a free one each, and never next to a rig's device nodes.

DDS splits a machine's ROS graph into domains (``ROS_DOMAIN_ID``, 0 by default). A simulated
session must neither hear nor command anything outside itself: on a rig PC, a session on the
rig's domain could send the real sleeve driver and PAMs its scripted operator's commands.

* :func:`reserve_domain` gives a process a domain of its own. If the user set ``ROS_DOMAIN_ID``
  that one is used; otherwise the first domain of 1..101 (0 is where every ROS program starts
  by default, a rig included) that no other session of this workspace holds and on which no
  ROS node answers. "Holds" is an exclusive ``flock`` on
  ``$XDG_RUNTIME_DIR/cgail_ros_domains/<id>.lock`` (``/tmp`` without XDG_RUNTIME_DIR), released
  when the process ends, however it ends; ``bash`` can take the same lock with ``flock``
  (``scripts/test.sh`` does).
* :func:`foreign_device_nodes` lists the device nodes (``aurora``, ``pam_controller``,
  ``sleeve_driver``) seen on a domain; a session refuses to start next to one.

Discovery stays on this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), so the probes
see this machine's nodes only.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable, Mapping, Sequence
import concurrent.futures
import contextlib
from dataclasses import dataclass, field
import errno
import fcntl
import os
from pathlib import Path
import sys
import time
from typing import TypeVar

_T = TypeVar('_T')

#: Node names of the rig's devices: a session never shares a domain with one it did not start.
DEVICE_NODES = ('aurora', 'pam_controller', 'sleeve_driver')
#: Domains picked automatically (Linux: 0..101 map to free UDP ports; 0 is everyone's default).
AUTO_DOMAINS = range(1, 102)
#: How long a probe listens for the nodes of a domain, s (localhost discovery takes ~0.1 s on
#: an idle machine, seconds on an overloaded one); ``CGAIL_DOMAIN_PROBE_S`` overrides it.
PROBE_S = float(os.environ.get('CGAIL_DOMAIN_PROBE_S', '1.0'))


class DomainError(RuntimeError):
    """No usable ROS domain: a bad ROS_DOMAIN_ID, all held, or a foreign device node."""


def lock_dir() -> Path:
    """Directory of the per-domain lock files (created on demand)."""
    base = os.environ.get('XDG_RUNTIME_DIR') or '/tmp'
    path = Path(base) / 'cgail_ros_domains'
    path.mkdir(mode=0o777, parents=True, exist_ok=True)
    return path


def _try_lock(domain_id: int) -> int | None:
    """An open fd holding the exclusive lock of ``domain_id``, or None if another holds it."""
    path = lock_dir() / f'{domain_id}.lock'
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        if exc.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
            return None
        raise
    os.ftruncate(fd, 0)
    os.write(fd, f'{os.getpid()}\n'.encode())
    return fd


def lock_holder(domain_id: int) -> str:
    """The pid written by the process that holds (or last held) ``domain_id``'s lock."""
    with contextlib.suppress(OSError):
        return (lock_dir() / f'{domain_id}.lock').read_text().strip()
    return ''


@dataclass
class DomainLease:
    """A ROS domain held by this process until :meth:`release` or the process ends.

    Attributes:
        domain_id: the domain.
        source: ``'ROS_DOMAIN_ID'`` (the user's) or ``'automatic'``.
        nodes: the nodes seen on the domain when it was probed (``/ns/name``).
    """

    domain_id: int
    source: str
    nodes: list[str] = field(default_factory=list)
    _fd: int | None = None

    def release(self) -> None:
        """Let another session take the domain (idempotent)."""
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None

    def __enter__(self) -> DomainLease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def graph_nodes(domain_id: int, listen_s: float | None = None) -> list[str]:
    """Names (``/namespace/name``) of the nodes that answer on ``domain_id`` within
    ``listen_s`` seconds (default :data:`PROBE_S`), other than the probe itself."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node(f'cgail_domain_probe_{os.getpid()}', context=context,
                                 start_parameter_services=False, enable_rosout=False)
        time.sleep(PROBE_S if listen_s is None else listen_s)
        found = sorted(f'{ns.rstrip("/")}/{name}'
                       for name, ns in node.get_node_names_and_namespaces()
                       if name != node.get_name())
        node.destroy_node()
        return found
    finally:
        rclpy.try_shutdown(context=context)


def device_nodes_in(nodes: Iterable[str], devices: Sequence[str] = DEVICE_NODES) -> list[str]:
    """The entries of ``nodes`` (``/ns/name``) whose name is one of ``devices``."""
    return [n for n in nodes if n.rsplit('/', 1)[-1] in devices]


def foreign_device_nodes(domain_id: int, listen_s: float | None = None) -> list[str]:
    """Device nodes (:data:`DEVICE_NODES`) that answer on ``domain_id``."""
    return device_nodes_in(graph_nodes(domain_id, listen_s))


def requested_domain(env: Mapping[str, str] | None = None) -> int | None:
    """The user's ``ROS_DOMAIN_ID``, or None when unset or empty.

    Raises:
        DomainError: not an integer in 0..232.
    """
    env = os.environ if env is None else env
    text = env.get('ROS_DOMAIN_ID', '').strip()
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 232:
        raise DomainError(f'ROS_DOMAIN_ID must be an integer in 0..232, found {text!r}')
    return value


def reserve_domain(*, env: Mapping[str, str] | None = None,
                   candidates: Iterable[int] = AUTO_DOMAINS,
                   listen_s: float | None = None) -> DomainLease:
    """Hold a ROS domain for this process (module docstring).

    The user's ``ROS_DOMAIN_ID`` is taken as it is, unless another session of this workspace
    holds it or a device node answers there. Otherwise the first candidate that nobody holds
    and where no node answers.

    Raises:
        DomainError: the user's domain is held by another session or has a device node on it,
            or every candidate is taken.
    """
    wanted = requested_domain(env)
    if wanted is not None:
        fd = _try_lock(wanted)
        if fd is None:
            raise DomainError(f'ROS_DOMAIN_ID={wanted} is held by another simulated session '
                              f'(pid {lock_holder(wanted) or "?"}); expected a domain of its '
                              f'own: unset ROS_DOMAIN_ID to pick a free one')
        lease = DomainLease(wanted, 'ROS_DOMAIN_ID', _fd=fd)
        lease.nodes = graph_nodes(wanted, listen_s)
        devices = device_nodes_in(lease.nodes)
        if devices:
            lease.release()
            raise DomainError(
                f'ROS_DOMAIN_ID={wanted} already has device node(s) {", ".join(devices)} that '
                f'this session did not start (a real rig?); a simulated session must never '
                f'reach them: expected a domain without them, unset ROS_DOMAIN_ID to pick a '
                f'free one')
        return lease
    tried = 0
    for domain_id in candidates:
        fd = _try_lock(domain_id)
        if fd is None:
            continue
        tried += 1
        lease = DomainLease(domain_id, 'automatic', _fd=fd)
        lease.nodes = graph_nodes(domain_id, listen_s)
        if not lease.nodes:
            return lease
        lease.release()
    raise DomainError(f'expected a free ROS domain among {candidates!r}, found every one held '
                      f'by another session or in use ({tried} probed)')


def reserve_domain_during(work: Callable[[], _T], *, env: Mapping[str, str] | None = None
                          ) -> tuple[DomainLease, _T]:
    """:func:`reserve_domain` in a thread while ``work()`` runs in this one; returns the lease
    and what ``work`` returned.

    A probe mostly waits (:data:`PROBE_S` for the nodes of the domain to answer), so a process
    about to build a rig can do its other preparation meanwhile (``cgail identify-pam`` and
    every worker of ``cgail session`` import the nodes' modules: ~1 s of CPU each). ``work``
    must not touch any ROS domain: the one it would use is not known yet. The check itself is
    unchanged: nothing runs on the domain before the probe has found it free.

    Raises:
        DomainError: as :func:`reserve_domain` (after ``work`` returned).
    """
    import rclpy  # noqa: F401  (imported here first: the probe's thread imports nothing heavy)

    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix='domain_probe') as pool:
        pending = pool.submit(reserve_domain, env=env)
        try:
            value = work()
        except BaseException:
            with contextlib.suppress(DomainError):
                pending.result().release()
            raise
        return pending.result(), value


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cgail_rig.domain``: print a free domain, or the nodes of one."""
    parser = argparse.ArgumentParser(prog='cgail_domain', description=__doc__.split('\n')[0])
    parser.add_argument('--probe', type=int, default=None, metavar='ID',
                        help='list the nodes that answer on domain ID and exit')
    parser.add_argument('--free', action='store_true',
                        help='print the first domain of 1..101 that no session holds and no '
                             'node answers on (the caller takes its lock with flock)')
    args = parser.parse_args(argv)
    if args.probe is not None:
        for name in graph_nodes(args.probe):
            print(name)
        return 0
    if args.free:
        try:
            lease = reserve_domain(env={})
        except DomainError as exc:
            print(f'cgail_domain: {exc}', file=sys.stderr)
            return 1
        print(lease.domain_id)
        lease.release()
        return 0
    parser.print_help()
    return 2


if __name__ == '__main__':
    sys.exit(main())

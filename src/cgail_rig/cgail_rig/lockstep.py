"""Lockstep: a closed, in-process ROS graph on one simulated clock, stepped deterministically.

The simulated rig (``invitro_session``) runs every node in one process. Stepped by this
executor instead of rclpy's, simulated time is the only time, and a run is a function of its
seed and configuration, whatever the host's speed or load:

* **One time source.** Every node's clock is attached to one :class:`rclpy.time_source.
  TimeSource` (no ``/clock`` subscription per node, no ``use_sim_time``): the executor sets
  the simulated time on all of them at once, so their timers, stamps and node-clock watchdogs
  read simulated seconds.
* **Ticks.** :meth:`LockstepExecutor.tick` advances the clock by one period, calls the world
  hooks (the phantom: physics and simulated devices, ``dt`` of simulated time), then fires the
  timers that are due, in a fixed order (nodes in the order they were added, timers in the
  order they were created). The clock advances again only when every message published in the
  tick has been handled: it is a barrier on all messages of the tick, like Gazebo's lockstep
  mode, not on a list of expected topics.
* **Causal, ordered delivery.** Every publisher of the graph is instrumented: a publish queues
  the graph's subscriptions of that topic (first in, first out; for one publish, in creation
  order), and the executor takes and handles them one by one. This relies on DDS delivering a
  message to a subscription of the same process inside the ``publish`` call (Fast DDS and
  Cyclone DDS intra-process delivery, synchronous publication); :meth:`LockstepExecutor.seal`
  checks it and refuses to run otherwise. A message that arrives from outside the graph (a
  publisher of another process) is picked up by a sweep at the end of the tick and counted
  (``Stats.unscheduled``).
* **No threads racing the clock.** Devices are stepped by the world hooks; a node that talks to
  a device does so synchronously inside its timer callback (the Aurora node's ``poll_mode:
  clock``). Guard conditions (how a thread wakes an executor) are refused, and so are waitables
  other than QoS event handlers. Services are served in the end-of-tick sweep; clients are not
  supported.

rclpy's executors cannot give this: their order of ready callbacks depends on object
addresses (a set of nodes), and they rebuild a wait set on every wait (~0.3 ms with the rig's
~100 entities). This executor takes messages directly from the subscriptions it knows have
data, so one tick of the whole rig costs a fraction of a millisecond of its own.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
import inspect
import time
import traceback
from typing import Any

from rclpy.exceptions import InvalidHandle


class LockstepError(RuntimeError):
    """The graph cannot be run in lockstep (unsupported entity, unmatched topics, ...)."""


@dataclass
class Stats:
    """Counters of a lockstep run."""

    ticks: int = 0
    """Clock ticks."""
    timers: int = 0
    """Timer callbacks run."""
    messages: int = 0
    """Subscription callbacks run for messages published inside the graph."""
    unscheduled: int = 0
    """Messages found by the end-of-tick sweep (published outside the graph)."""
    services: int = 0
    """Service requests served."""
    published: int = 0
    """Messages published by the graph's instrumented publishers."""


class LockstepExecutor:
    """Runs the nodes of one process on one simulated clock (module docstring).

    Args:
        period_s: simulated seconds per tick; > 0.
        start_s: simulated time before the first tick, s; >= 0.
        on_error: called with the traceback text of a callback that raised (the run goes on);
            default: the traceback is kept in :attr:`errors` only.

    Raises:
        ValueError: a non-positive period or a negative start time.
    """

    def __init__(self, *, period_s: float, start_s: float = 0.0,
                 on_error: Callable[[str], None] | None = None) -> None:
        from rclpy.time_source import TimeSource

        if not period_s > 0.0:
            raise ValueError(f'period_s must be > 0, found {period_s!r}')
        if not start_s >= 0.0:
            raise ValueError(f'start_s must be >= 0, found {start_s!r}')
        self.period_ns = round(period_s * 1e9)
        self._now_ns = round(start_s * 1e9)
        self.time_source = TimeSource()
        self.time_source.ros_time_is_active = True
        self.nodes: list[Any] = []
        self.hooks: list[Callable[[float], None]] = []
        self.stats = Stats()
        self.errors: list[str] = []
        self._on_error = on_error
        self._subs_by_topic: dict[str, list[Any]] = {}
        self._timers: list[Any] = []
        self._subscriptions: list[Any] = []
        self._services: list[Any] = []
        self._pending: deque[Any] = deque()
        self._wrapped: set[int] = set()
        self._set_clocks()

    # ------------------------------------------------------------------ time
    @property
    def now_ns(self) -> int:
        """Simulated time, ns."""
        return self._now_ns

    @property
    def now_s(self) -> float:
        """Simulated time, s."""
        return self._now_ns * 1e-9

    @property
    def period_s(self) -> float:
        """Simulated seconds per tick."""
        return self.period_ns * 1e-9

    def _set_clocks(self) -> None:
        from rclpy.time import Time
        from rosgraph_msgs.msg import Clock

        self.time_source.clock_callback(Clock(clock=Time(nanoseconds=self._now_ns).to_msg()))

    # ------------------------------------------------------------------ graph
    def add_node(self, node: Any) -> None:
        """Put ``node`` on the simulated clock and in the graph (its entities: :meth:`seal`)."""
        if node in self.nodes:
            return
        self.time_source.attach_clock(node.get_clock())
        self.nodes.append(node)

    def add_hook(self, hook: Callable[[float], None]) -> None:
        """Call ``hook(dt)`` at the start of every tick, after the clock has advanced by ``dt``
        (the world: physics and simulated devices step from ``now - dt`` to ``now``)."""
        self.hooks.append(hook)

    def seal(self, timeout_s: float = 15.0) -> None:
        """Index every node's entities, instrument the publishers, and wait (wall clock, no
        simulated time passes) until each publisher is matched with every compatible
        subscription of the graph; then deliver what late joiners received (latched samples).

        Call it after the last node was added and whenever nodes created entities.

        Raises:
            LockstepError: a guard condition, a client or an unsupported waitable; topics not
                matched within ``timeout_s``; or a message not delivered inside ``publish``.
        """
        from rclpy.event_handler import EventHandler
        from rclpy.qos import qos_check_compatible, QoSCompatibility

        timers, subs, services, pubs = [], [], [], []
        for node in self.nodes:
            name = node.get_fully_qualified_name()
            if list(node.guards):
                raise LockstepError(f'{name}: expected no guard conditions in a lockstep graph '
                                    f'(threads must not wake the executor), found '
                                    f'{len(list(node.guards))}')
            if list(node.clients):
                raise LockstepError(f'{name}: expected no service clients in a lockstep graph, '
                                    f'found {[c.srv_name for c in node.clients]}')
            for waitable in node.waitables:
                if not isinstance(waitable, EventHandler):
                    raise LockstepError(f'{name}: unsupported waitable '
                                        f'{type(waitable).__name__} in a lockstep graph')
            timers += list(node.timers)
            subs += list(node.subscriptions)
            services += list(node.services)
            pubs += list(node.publishers)
        self._timers, self._subscriptions, self._services = timers, subs, services
        by_topic: dict[str, list[Any]] = {}
        for sub in subs:
            by_topic.setdefault(sub.topic_name, []).append(sub)
        # keep the lists the instrumented publishers hold: update them in place
        for topic, lst in self._subs_by_topic.items():
            lst[:] = by_topic.pop(topic, [])
        self._subs_by_topic.update(by_topic)
        for pub in pubs:
            self._instrument(pub)

        def expected(pub: Any) -> int:
            return sum(1 for s in self._subs_by_topic.get(pub.topic_name, ())
                       if qos_check_compatible(pub.qos_profile, s.qos_profile)[0]
                       != QoSCompatibility.ERROR)

        want = [(pub, expected(pub)) for pub in pubs]
        deadline = time.monotonic() + timeout_s
        while True:
            missing = [(p.topic_name, p.get_subscription_count(), n) for p, n in want
                       if p.get_subscription_count() < n]
            if not missing:
                break
            if time.monotonic() > deadline:
                raise LockstepError(f'expected every publisher matched with the graph\'s '
                                    f'subscriptions within {timeout_s} s, found (topic, matched, '
                                    f'expected) {missing[:5]}')
            time.sleep(0.005)
        time.sleep(0.02)  # transient-local history reaches late joiners on matching
        self._sweep()
        self._check_synchronous_delivery(want)

    def settle(self, predicate: Callable[[], bool], timeout_s: float = 30.0) -> None:
        """Handle what arrives from outside the instrumented publishes (latched samples that
        reach late joiners on matching, asynchronously) until ``predicate()`` holds, with no
        simulated time passing: what a graph must have before its first tick, however slowly
        the middleware delivers it on a loaded machine.

        Raises:
            LockstepError: ``predicate()`` still false after ``timeout_s`` wall seconds.
        """
        deadline = time.monotonic() + timeout_s
        self._sweep()
        while not predicate():
            if time.monotonic() > deadline:
                raise LockstepError(f'expected the latched samples of the graph delivered '
                                    f'within {timeout_s} s, found them missing')
            time.sleep(0.002)
            self._sweep()

    def _check_synchronous_delivery(self, want: Iterable[tuple[Any, int]]) -> None:
        """Refuse a middleware that does not deliver inside ``publish`` (checked once, on a
        private topic, so the graph's own topics see nothing)."""
        if getattr(self, '_delivery_checked', False) or not self.nodes:
            return
        from std_msgs.msg import Empty

        node = self.nodes[0]
        topic = f'_lockstep_check_{id(self)}'
        got: list[Any] = []
        sub = node.create_subscription(Empty, topic, got.append, 10)
        pub = node.create_publisher(Empty, topic, 10)
        try:
            deadline = time.monotonic() + 10.0
            while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
                time.sleep(0.002)
            for _ in range(3):
                pub.publish(Empty())
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
                if taken is None:
                    raise LockstepError('expected the middleware to deliver a message to a '
                                        'subscription of the same process inside publish(), '
                                        'found it later: lockstep needs synchronous intra-'
                                        'process delivery (rmw_fastrtps_cpp or '
                                        'rmw_cyclonedds_cpp)')
        finally:
            node.destroy_publisher(pub)
            node.destroy_subscription(sub)
        self._delivery_checked = True

    def _instrument(self, pub: Any) -> None:
        if id(pub) in self._wrapped:
            return
        publish = pub.publish
        subs = self._subs_by_topic.setdefault(pub.topic_name, [])
        pending, stats = self._pending, self.stats

        def instrumented(msg: Any) -> None:
            publish(msg)
            stats.published += 1
            pending.extend(subs)

        pub.publish = instrumented
        self._wrapped.add(id(pub))

    # ------------------------------------------------------------------ running
    def tick(self) -> None:
        """Advance the clock one period, step the world, fire the due timers; return when
        every message published in the tick has been handled."""
        self._now_ns += self.period_ns
        self._set_clocks()
        self.stats.ticks += 1
        dt = self.period_ns * 1e-9
        for hook in self.hooks:
            self._call(hook, dt)
            self._deliver()
        for timer in self._timers:
            try:
                with timer.handle:
                    if not timer.handle.is_timer_ready():
                        continue
                    timer.handle.call_timer()
            except InvalidHandle:  # destroyed since the last seal
                continue
            self.stats.timers += 1
            self._call(timer.callback)
            self._deliver()
        self._sweep()

    def run_until(self, predicate: Callable[[], bool], max_s: float) -> bool:
        """Tick until ``predicate()`` holds (checked before each tick) or ``max_s`` simulated
        seconds have passed; returns whether it holds."""
        end = self._now_ns + round(max_s * 1e9)
        while not predicate():
            if self._now_ns >= end:
                return predicate()
            self.tick()
        return True

    def spin_for(self, duration_s: float) -> None:
        """Tick for ``duration_s`` simulated seconds."""
        self.run_until(lambda: False, duration_s)

    def _deliver(self) -> None:
        pending = self._pending
        stats = self.stats
        while pending:
            sub = pending.popleft()
            taken = self._take(sub)
            if taken is None:
                continue
            stats.messages += 1
            self._call_sub(sub, taken)

    def _sweep(self) -> None:
        """Handle what arrived outside the instrumented publishes, and service requests."""
        again = True
        while again:
            again = False
            for sub in self._subscriptions:
                while (taken := self._take(sub)) is not None:
                    self.stats.unscheduled += 1
                    self._call_sub(sub, taken)
                    self._deliver()
                    again = True
            for srv in self._services:
                try:
                    with srv.handle:
                        request, header = srv.handle.service_take_request(srv.srv_type.Request)
                except InvalidHandle:
                    continue
                if header is None:
                    continue
                self.stats.services += 1
                response = self._call(srv.callback, request, srv.srv_type.Response())
                if response is not None:
                    srv.send_response(response, header)
                self._deliver()
                again = True

    @staticmethod
    def _take(sub: Any) -> Any:
        try:
            with sub.handle:
                return sub.handle.take_message(sub.msg_type, sub.raw)
        except InvalidHandle:  # destroyed since the last seal: nothing to take
            return None

    def _call_sub(self, sub: Any, taken: Any) -> None:
        from rclpy.subscription import Subscription

        if sub._callback_type is Subscription.CallbackType.MessageOnly:
            self._call(sub.callback, taken[0])
        else:
            self._call(sub.callback, *taken)

    def _call(self, fn: Callable[..., Any], *args: Any) -> Any:
        try:
            result = fn(*args)
        except Exception:
            text = traceback.format_exc()
            self.errors.append(text)
            if self._on_error is not None:
                self._on_error(text)
            return None
        if inspect.iscoroutine(result):
            result.close()
            raise LockstepError(f'{fn!r}: coroutine callbacks are not supported in lockstep')
        return result

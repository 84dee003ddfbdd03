"""Lockstep: a closed, in-process ROS graph on one simulated clock, stepped deterministically.

The simulated rig (``invitro_session``) runs every node in one process. Stepped by this
executor instead of rclpy's, simulated time is the only time, and a run is a function of its
seed and configuration, whatever the host's speed or load:

* **One time source.** Every node's clock is attached to one :class:`rclpy.time_source.
  TimeSource` (no ``/clock`` subscription per node, no ``use_sim_time``): the executor sets
  the simulated time on all of them at once, so their timers, stamps and node-clock watchdogs
  read simulated seconds. Their ``now()`` returns the tick's one :class:`rclpy.time.Time`
  (the value the clock holds, without a call into rcl and a new object each time).
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
* **In-process transport** (``transport='inprocess'``, what the simulated session runs). A
  publish on a volatile topic whose only subscribers are the graph's is not handed to DDS: the
  message is serialized once (the CDR DDS would carry) and every subscription gets its own copy
  deserialized from it when it is taken, so values are rounded exactly as DDS rounds them (the
  float32 fields, such as a Joy's axes) and no subscriber shares an object with the publisher;
  a raw subscription (a recorder) gets the bytes DDS would give it (:mod:`cgail_rig.cdr`:
  rclpy's serializer leaves the padding undefined, a bag must be bit-identical). Both ways go
  through :func:`cgail_rig.cdr.encoder` and :func:`~cgail_rig.cdr.decoder` where they handle
  the type (struct calls generated per type: the same bytes and messages as rclpy's
  serializer, with DDS's zero padding, several times faster), else through rclpy; a publish
  nobody subscribes to is not serialized at all. Delivery order, the subscriptions' history
  depth (KEEP_LAST drops the oldest) and QoS compatibility are those of DDS. A latched
  (transient-local, KEEP_LAST) topic goes in-process too, its publisher keeping the last
  ``depth`` samples that DDS would hold for late joiners: when a subscriber joins (a new
  subscription of the graph at :meth:`~LockstepExecutor.seal`, or one outside the graph, seen at
  its next publish or sweep), the kept samples are handed to DDS (the graph's own subscriptions
  drop the copies they already had) and the topic goes through DDS from then on. These go
  through DDS as before: a volatile topic with a subscriber outside the graph, an inactive
  lifecycle publisher, a subscription that wants the message info. Results equal
  ``transport='dds'``.
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
import contextlib
from dataclasses import dataclass
import inspect
import time
import traceback
from typing import Any

from rclpy.clock import ClockType
from rclpy.exceptions import InvalidHandle
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.subscription import Subscription
from rclpy.time import Time
from rosgraph_msgs.msg import Clock

from cgail_rig import cdr

_MESSAGE_ONLY = Subscription.CallbackType.MessageOnly


#: ``transport``: every message through DDS, or in-process where the graph is closed (module
#: docstring).
TRANSPORTS = ('dds', 'inprocess')


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
        transport: ``'dds'`` (every message through the middleware) or ``'inprocess'``
            (module docstring); the results are the same, in-process is faster.
        sweep_every: sweep the subscriptions and services for what came from outside the
            graph every this many ticks (1: at the end of every tick); a graph that nothing
            outside talks to (the session) needs it rarely.

    Raises:
        ValueError: a non-positive period, a negative start time, an unknown transport or a
            sweep interval below 1.
    """

    def __init__(self, *, period_s: float, start_s: float = 0.0,
                 on_error: Callable[[str], None] | None = None, transport: str = 'dds',
                 sweep_every: int = 1) -> None:
        from rclpy.time_source import TimeSource

        if not period_s > 0.0:
            raise ValueError(f'period_s must be > 0, found {period_s!r}')
        if not start_s >= 0.0:
            raise ValueError(f'start_s must be >= 0, found {start_s!r}')
        if transport not in TRANSPORTS:
            raise ValueError(f'transport must be one of {TRANSPORTS}, found {transport!r}')
        if not (isinstance(sweep_every, int) and sweep_every >= 1):
            raise ValueError(f'sweep_every must be an integer >= 1, found {sweep_every!r}')
        self.transport = transport
        self.sweep_every = sweep_every
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
        # (subscription, None, None): take from DDS; (subscription, inbox, decode): take the
        # oldest CDR bytes of its in-process inbox, deserialized by ``decode`` (None: raw)
        self._pending: deque[tuple[Any, deque[bytes] | None, Any]] = deque()
        self._wrapped: set[int] = set()
        # in-process transport: per publisher (id), its route; per subscription (id), its inbox
        self._routes: dict[int, _Route] = {}
        self._inboxes: dict[int, deque[bytes]] = {}
        self._publish: dict[int, Callable[[Any], None]] = {}  # per publisher, rclpy's publish
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
        now = _TickTime(self._now_ns)
        source = self.time_source
        clocks = getattr(source, '_associated_clocks', None)
        if clocks is None or not hasattr(source, '_last_time_set'):
            source.clock_callback(Clock(clock=now.to_msg()))  # (an rclpy laid out otherwise)
        else:
            # TimeSource.clock_callback without the Clock message and a Time per clock (once a
            # tick, ~10 clocks): the override set from the one Time, kept for late attachers
            source._last_time_set = now
            handle = now._time_handle
            for clock in clocks:
                with clock.handle:
                    clock.handle.set_ros_time_override(handle)
        self._now_time = now

    def _clock_now(self) -> Any:
        """``now()`` of the nodes' clocks: the simulated time (an immutable rclpy Time)."""
        return self._now_time

    # ------------------------------------------------------------------ graph
    def add_node(self, node: Any) -> None:
        """Put ``node`` on the simulated clock and in the graph (its entities: :meth:`seal`)."""
        if node in self.nodes:
            return
        clock = node.get_clock()
        self.time_source.attach_clock(clock)
        clock.now = self._clock_now  # (module docstring: the tick's Time, the clock's value)
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
        if self.transport == 'inprocess':
            self._plan_routes(pubs)
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

    def _plan_routes(self, pubs: Iterable[Any]) -> None:
        """The in-process route of every publisher that may take one (module docstring):
        the compatible subscriptions of the graph, each with an inbox of its history depth."""
        from rclpy.qos import (
            DurabilityPolicy,
            HistoryPolicy,
            qos_check_compatible,
            QoSCompatibility,
        )
        for sub in self._subscriptions:
            if id(sub) not in self._inboxes:
                qos = sub.qos_profile
                depth = qos.depth if qos.history != HistoryPolicy.KEEP_ALL else None
                self._inboxes[id(sub)] = deque(maxlen=depth if depth else None)
        for key in list(self._routes):
            self._demote(key)  # subscriptions may have joined: DDS holds the latched history
        self._routes.clear()
        for pub in pubs:
            qos = pub.qos_profile
            latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
            if qos.durability != DurabilityPolicy.VOLATILE and not latched:
                continue
            if latched and (qos.history == HistoryPolicy.KEEP_ALL or qos.depth < 1):
                continue  # an unbounded history: DDS keeps it
            if qos.lifespan.nanoseconds > 0:
                continue  # samples that expire: the middleware's business
            # compatible (OK, or WARNING: a policy left to the system default) and matched:
            # seal waited for every one, and nothing else may be matched
            targets = [s for s in self._subs_by_topic.get(pub.topic_name, [])
                       if qos_check_compatible(pub.qos_profile, s.qos_profile)[0]
                       != QoSCompatibility.ERROR]
            if pub.get_subscription_count() != len(targets):
                continue  # a subscriber outside the graph (or not matched yet): DDS
            if any(s._callback_type is not _MESSAGE_ONLY for s in targets):
                continue  # the message info comes from DDS
            raw = any(s.raw for s in targets)
            if raw:
                try:  # a raw subscriber (a recorder) gets DDS's bytes: cdr.zero_padding
                    cdr.plan(pub.msg_type)
                except cdr.CdrError:
                    continue
            self._routes[id(pub)] = _Route(
                matched=len(targets), raw=raw,
                targets=[(s, self._inboxes[id(s)], None if s.raw else _decoder(s.msg_type))
                         for s in targets],
                pub=pub, history=deque(maxlen=qos.depth) if latched else None)

    def _demote(self, key: int) -> None:
        """Take publisher ``key`` off its in-process route; a latched one hands the samples
        it kept to DDS, for late joiners (module docstring)."""
        route = self._routes.pop(key, None)
        if route is None or not route.history:
            return
        samples = list(route.history)
        for data in samples:
            if not route.raw:  # (what was kept is rclpy's bytes: give DDS's)
                with contextlib.suppress(cdr.CdrError):
                    data = cdr.zero_padding(data, route.pub.msg_type)
            self._publish[key](data)
        for sub, inbox, sub_type in route.targets:
            # DDS delivered the samples to the graph's subscriptions too (inside publish), which
            # had them in-process: drop those copies, hand on anything older (from outside)
            taken: list[bytes] = []
            try:
                with sub.handle:
                    while (got := sub.handle.take_message(sub.msg_type, True)) is not None:
                        taken.append(got[0])
            except InvalidHandle:
                continue
            copies = 0
            while copies < min(len(taken), len(samples)) and \
                    _same_cdr(taken[-1 - copies], samples[-1 - copies], route.pub.msg_type):
                copies += 1
            for data in taken[:len(taken) - copies]:
                inbox.append(data)
                self._pending.append((sub, inbox, sub_type))

    def _instrument(self, pub: Any) -> None:
        if id(pub) in self._wrapped:
            return
        publish = pub.publish
        subs = self._subs_by_topic.setdefault(pub.topic_name, [])
        self._publish[id(pub)] = publish
        pending, stats, routes = self._pending, self.stats, self._routes
        serialize = _rclpy.rclpy_serialize
        msg_type = pub.msg_type
        key = id(pub)
        try:  # DDS's bytes in a few struct calls (cgail_rig.cdr.encoder)
            encode = cdr.encoder(msg_type)
        except cdr.CdrError:
            encode = None

        # (the publisher's count without rclpy's wrapper, once per publish: one thread here)
        matched_now = pub.handle.get_subscription_count

        def instrumented(msg: Any) -> None:
            route = routes.get(key)
            if route is not None and matched_now() != route.matched:
                if route.history is not None:
                    self._demote(key)  # a latched topic's late joiner: its history, then DDS
                route = None
            if route is None or not getattr(pub, '_enabled', True):
                publish(msg)  # through DDS (and lifecycle's inactive check, type check)
                stats.published += 1
                pending.extend((s, None, None) for s in subs)
                return
            raw = data = b''
            history = route.history
            if isinstance(msg, msg_type):
                # nobody listens: nothing to serialize (DDS would convert it and drop it),
                # unless a late joiner may want it (latched)
                encoded = None
                if encode is not None and (route.targets or history is not None):
                    try:  # (a value it does not convert as rclpy would: rclpy's below)
                        encoded = encode(msg)
                    except Exception:
                        encoded = None
                if encoded is not None:
                    data = raw = encoded  # (its padding is zero already)
                else:
                    data = raw = serialize(msg, msg_type) \
                        if route.targets or history is not None else b''
                if route.raw and encoded is None:
                    try:
                        raw = cdr.zero_padding(data, msg_type)
                    except cdr.CdrError:  # bytes the walk does not know: DDS from now on
                        routes.pop(key, None)
                        instrumented(msg)
                        return
            elif isinstance(msg, bytes):
                data = raw = msg
            else:
                raise TypeError(f'Expected {msg_type}, got {type(msg)}')
            stats.published += 1
            if history is not None:
                history.append(raw if route.raw else data)
            for sub, inbox, sub_type in route.targets:
                inbox.append(data if sub_type is not None else raw)
                pending.append((sub, inbox, sub_type))

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
        if self.stats.ticks % self.sweep_every == 0:
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
            sub, inbox, decode = pending.popleft()
            if inbox is None:
                taken = self._take(sub)
                if taken is None:
                    continue
            else:
                if not inbox:
                    continue  # dropped: more were published than the history holds
                payload = inbox.popleft()
                try:
                    with sub.handle:
                        pass
                except InvalidHandle:  # destroyed since the last seal
                    continue
                taken = (payload if decode is None else decode(payload), None)
            stats.messages += 1
            self._call_sub(sub, taken)

    def _sweep(self) -> None:
        """Hand a latched topic's history to DDS when a subscriber joined; handle what arrived
        outside the instrumented publishes, and service requests."""
        for key, route in list(self._routes.items()):
            if route.history is not None and route.pub.get_subscription_count() != route.matched:
                self._demote(key)
        self._deliver()
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
        if sub._callback_type is _MESSAGE_ONLY:
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
        if result is not None and inspect.iscoroutine(result):
            result.close()
            raise LockstepError(f'{fn!r}: coroutine callbacks are not supported in lockstep')
        return result


class _TickTime(Time):
    """The ROS time of one tick, as :meth:`LockstepExecutor._clock_now` hands it to every node:
    an rclpy ``Time`` whose ``nanoseconds`` (what ``now().nanoseconds``, ``to_msg()`` and the
    comparisons read, dozens of times a tick) is the int it was made from rather than a call
    into its rcl handle. Immutable like any ``Time``."""

    def __init__(self, nanoseconds: int) -> None:
        super().__init__(nanoseconds=nanoseconds, clock_type=ClockType.ROS_TIME)
        self._nanoseconds = int(nanoseconds)

    @property
    def nanoseconds(self) -> int:
        """:return: the total number of nanoseconds since the clock's epoch."""
        return self._nanoseconds


@dataclass
class _Route:
    """Where an in-process publish goes: ``matched`` is the publisher's match count when no
    subscriber outside the graph listens; ``raw``: a target takes the bytes; ``targets`` are
    (subscription, inbox, function that deserializes the bytes or None to hand them over);
    ``pub`` the publisher; ``history``: a latched topic's last samples (DDS's bytes if ``raw``,
    else rclpy's), None for a volatile one."""

    matched: int
    raw: bool
    targets: list[tuple[Any, deque[bytes], Any]]
    pub: Any = None
    history: deque[bytes] | None = None


def _decoder(msg_type: type) -> Callable[[bytes], Any]:
    """``decode(data) -> msg``: the message rclpy's deserializer gives for ``data``, by
    :func:`cgail_rig.cdr.decoder` (a few struct calls and no constructors, ~5x faster) where it
    handles the type and the bytes, else by rclpy."""
    deserialize = _rclpy.rclpy_deserialize
    try:
        fast = cdr.decoder(msg_type)
    except cdr.CdrError:
        return lambda data: deserialize(data, msg_type)

    def decode(data: bytes) -> Any:
        try:
            return fast(data)
        except Exception:  # (bytes it does not walk: rclpy's)
            return deserialize(data, msg_type)

    return decode


def _same_cdr(a: bytes, b: bytes, msg_type: type) -> bool:
    """Whether two serialized ``msg_type`` are the same message (their padding aside)."""
    if a == b:
        return True
    try:
        return cdr.zero_padding(a, msg_type) == cdr.zero_padding(b, msg_type)
    except cdr.CdrError:
        return False


"""A thin layer over one Zenoh session: publish typed messages, receive validated ones, track who is alive.

Every process (DMO, agent, recorder) opens one ``Bus`` for one run under one name. What arrives is decoded and
checked against its key before any handler sees it; what fails goes to ``on_reject`` with its reason and is
counted, and a failing handler is logged and counted, so nothing received can crash the receiver.

Handlers run on Zenoh's threads: keep them short (hand work to a queue) and never close the bus from one.
"""

from __future__ import annotations

import atexit
import collections
import json
import logging
import queue
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

import zenoh

from scenarios.names import NAME_PATTERN, is_name

from ..codec import MessageError, decode
from ..keys import Keys, check_route, parse_key
from ..schemas import Envelope, Message
from ..stamping import Sender
from .faults import FaultInjector

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")

Handler = Callable[[str, Message, int], None]             # (key, message, received_at ns)
PayloadHandler = Callable[[str, Message, int, bytes], None]  # ... and the payload's bytes as they arrived
RawHandler = Callable[[str, bytes, int], None]            # (key, payload, received_at ns)
RejectHook = Callable[[str, bytes, MessageError], None]   # (key, payload, error: str(error) is the reason)
Tap = Callable[[str, bytes, int], None]                   # (key, payload, ns): each payload sent or received
Entry = tuple[str, bytes, int]                            # (key, payload, ns): one reply to a query
Answer = Callable[[str, str], Iterable[Entry]]            # (key expression asked, parameters) -> replies


# What a process that listens (the DMO, a router) accepts at once: sessions, handshakes under way, and how long one
# may take. Sized for fleets of thousands joining together on a busy machine (docs/hosts.md).
MAX_SESSIONS = 10_000
ACCEPT_PENDING = 2_000
ACCEPT_TIMEOUT_S = 60.0

PRESENCE_GRACE_S = 1.0  # how long past its timeout a liveliness query may take to say it is done


@dataclass(frozen=True)
class BusConfig:
    """How to reach the other processes. The same three endpoint settings as the Zenoh examples (``mode``,
    ``connect``, ``listen``), an optional Zenoh config file under them, a ``lease_s`` and raw ``overrides``:
    (config key, JSON5 value) pairs given to ``zenoh.Config.insert_json5`` last (auth, TLS...).

    ``lease_s`` is the lease this process announces: the others declare it gone once it has been silent
    (frozen) that long. A killed or closed process is seen gone within milliseconds whatever the lease.

    ``connect_timeout_s`` is how long opening waits for a ``connect`` endpoint to answer, retrying, so an agent
    may be started before its DMO or router; past it, opening fails (a client's Zenoh default is to fail at once).
    It also bounds the session's handshake (Zenoh's default gives up after 10 s, which a router that hundreds of
    agents join at once on a busy machine can take). A process that listens takes up to ``MAX_SESSIONS``
    sessions and ``ACCEPT_PENDING`` handshakes at once, each given ``ACCEPT_TIMEOUT_S`` (Zenoh's defaults, 1,000,
    100 and 10 s, refused agents of a fleet of 1,000 joining three routers; docs/hosts.md).

    With explicit endpoints, multicast scouting is off and the scouting delay 0: the process connects where
    it is told at once and never meets a stranger's run. Without a config file, shared memory is off
    (docs/protocol.md, "Transport").
    """

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    lease_s: float | None = None
    connect_timeout_s: float | None = None
    config_file: str | None = None
    overrides: tuple[tuple[str, str], ...] = field(default_factory=tuple)

    def __post_init__(self):
        for name in ("connect", "listen", "overrides"):
            value = getattr(self, name)
            if isinstance(value, str):
                raise ValueError(f"{name} must be a list, not a string")
            object.__setattr__(self, name, tuple(tuple(v) if name == "overrides" else str(v) for v in value))
        if self.mode is not None and self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, not {self.mode!r}")
        if self.lease_s is not None and not 0.05 <= self.lease_s <= 3600:
            raise ValueError(f"lease_s must be between 0.05 and 3600 seconds, not {self.lease_s}")
        if self.connect_timeout_s is not None and not 0 <= self.connect_timeout_s <= 86400:
            raise ValueError(f"connect_timeout_s must be between 0 and 86400 seconds, not {self.connect_timeout_s}")

    def to_zenoh(self) -> zenoh.Config:
        config = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        settings: list[tuple[str, str]] = []
        if not self.config_file:  # messages are small; each peer's 16 MiB pool would only cost memory
            settings.append(("transport/shared_memory/enabled", "false"))
        if self.mode is not None:
            settings.append(("mode", json.dumps(self.mode)))
        if self.connect:
            settings.append(("connect/endpoints", json.dumps(list(self.connect))))
        if self.listen:
            settings.append(("listen/endpoints", json.dumps(list(self.listen))))
        if self.connect or self.listen:
            settings += [("scouting/multicast/enabled", "false"), ("scouting/delay", "0")]
        if self.lease_s is not None:
            # A killed peer is noticed when its link closes; a frozen one only when its lease expires.
            settings.append(("transport/link/tx/lease", str(round(self.lease_s * 1000))))
        if self.connect and self.connect_timeout_s is not None:
            timeout_ms = str(round(self.connect_timeout_s * 1000))
            settings += [("connect/timeout_ms", timeout_ms), ("transport/unicast/open_timeout", timeout_ms)]
        if self.listen:
            settings += [("transport/unicast/max_sessions", str(MAX_SESSIONS)),
                         ("transport/unicast/accept_pending", str(ACCEPT_PENDING)),
                         ("transport/unicast/accept_timeout", str(round(ACCEPT_TIMEOUT_S * 1000)))]
        for key, value in settings + list(self.overrides):
            try:
                config.insert_json5(key, value)
            except Exception as err:  # zenoh raises its own ZError
                raise ValueError(f"invalid zenoh setting {key}={value}: {err}") from None
        return config


class Subscription:
    """A declared Zenoh subscriber; closing it (or its bus) stops delivery."""

    def __init__(self, bus: Bus, subscriber):
        self._bus = bus
        self._subscriber = subscriber

    def close(self) -> None:
        subscriber, self._subscriber = self._subscriber, None
        if subscriber is not None:
            self._bus._forget(self)
            _quietly(subscriber.undeclare, "undeclare subscriber")

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Bus:
    """One process's Zenoh session for one run. Use as a context manager; everything declared on it is closed
    with it. ``name`` is this process's sender id ("dmo", "recorder" or an agent id) and its liveliness name.

    Every message it publishes carries ``run_token`` (the run's token: the DMO draws it, the others learn it from the
    DMO's clock and set it here) and ``incarnation`` (this process: its bus's creation time, ns). ``faults``
    (messages/transport/faults.py) drops, delays, duplicates or corrupts what it publishes; None: nothing."""

    def __init__(self, run_id: str, name: str, config: BusConfig | None = None, *,
                 on_reject: RejectHook | None = None, announce: bool = True, faults: FaultInjector | None = None):
        self.keys = Keys(run_id)
        if not is_name(name):
            raise ValueError(f"process name {name!r} must match {NAME_PATTERN}")
        self.name = name
        self.config = config or BusConfig()
        self.on_reject = on_reject
        self._announce = announce
        self._session: zenoh.Session | None = None
        self._token = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._subscriptions: list[Subscription] = []
        self._sender = Sender(self.keys, name, time.time_ns())  # what it stamps on each message
        self._send_lock = threading.RLock()  # also guards the publisher cache
        self._state_lock = threading.Lock()
        self._published = 0
        self._received = 0
        self._handler_errors = 0
        self._answering: set[threading.Thread] = set()  # answering a slow query (serve)
        self._rejected: collections.Counter[str] = collections.Counter()
        self.faults = faults
        # called with every payload this bus puts on the wire (after faults) and every valid one it receives (a
        # raw subscription's: every one): the DMO keeps its day's traffic this way, to answer late joiners
        # (dmo/operator/history.py); an invalid payload is told by the refusal it gets, not kept whole
        self.tap: Tap | None = None
        # asked gate(key, size) of every payload received, before anything else: False drops it unread (a sender
        # over its budget: messages/budget.py)
        self.gate: Callable[[str, int], bool] | None = None
        self._dropped = 0
        self._slow: queue.Queue | None = None  # the slow queries waiting for the one thread that answers them

    # --- lifetime ----------------------------------------------------------------------------------------

    def open(self) -> Bus:
        if self._session is not None:
            return self
        if self.config.connect:
            log.info("connecting to %s%s", ", ".join(self.config.connect), "" if self.config.connect_timeout_s is None
                     else f" (waiting up to {self.config.connect_timeout_s:g} s for an answer)")
        try:
            with _OPENING:
                self._session = zenoh.open(self.config.to_zenoh())
        except zenoh.ZError as err:
            if self.config.connect and "Unable to connect" in str(err):
                waited = "" if self.config.connect_timeout_s is None else f" within {self.config.connect_timeout_s:g} s"
                raise ConnectionError(f"could not connect to {', '.join(self.config.connect)}{waited}: nobody "
                                      "listens there, or it refused us (credentials, TLS certificate)") from None
            raise
        _OPEN.add(self)
        try:
            if self._announce:
                self._token = self._session.liveliness().declare_token(self.keys.alive(self.name))
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Undeclare everything and close the session; safe to call twice."""
        session, self._session = self._session, None
        if session is None:
            return
        _OPEN.discard(self)
        if self.faults is not None:
            self.faults.cancel()
        for subscription in list(self._subscriptions):
            subscription.close()
        with self._state_lock:
            answering, self._answering = self._answering, set()
            slow, self._slow = self._slow, None
        if slow is not None:  # the answering thread ends after the query it is answering, if any
            _drain(slow)
            slow.put(None)
        for thread in answering:  # a thread left in Zenoh's code at interpreter exit aborts the process
            thread.join(ANSWERING_STOP_S)
        with self._send_lock:
            publishers, self._publishers = list(self._publishers.values()), {}
        for publisher in publishers:
            _quietly(publisher.undeclare, "undeclare publisher")
        if self._token is not None:
            _quietly(self._token.undeclare, "undeclare liveliness token")
            self._token = None
        _quietly(session.close, "close zenoh session")

    def __enter__(self) -> Bus:
        return self.open()

    def faults_injected(self) -> dict[str, int]:
        """How many of each message fault this bus injected (empty without faults)."""
        return {} if self.faults is None else self.faults.summary()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def incarnation(self) -> int:
        """This process's (its bus's creation time, ns)."""
        return self._sender.incarnation

    @property
    def run_token(self) -> str:
        """The run's token, stamped on every message published."""
        return self._sender.run_token

    @run_token.setter
    def run_token(self, token: str) -> None:
        self._sender.run_token = token

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError(f"bus {self.name!r} is not open")
        return self._session

    # --- sending -----------------------------------------------------------------------------------------

    def publish(self, msg: Envelope, key: str | None = None, *,
                before_put: Callable[[str, bytes, Message], None] | None = None) -> Message:
        """Stamp ``run`` (the run's token), ``incarnation``, ``seq`` (this sender's next number) and ``sent_at`` (now,
        ns), and put the message on its key (``keys.for_message`` unless given; a given key must fit the message).
        ``before_put(key, payload, stamped)`` is called just before the put, so that what tracks the payload (an
        agent's ``Delivery``) knows it before any answer to it can arrive. Returns the stamped message; ``encode``
        of it is the payload sent."""
        with self._send_lock:
            key, payload, stamped = self._sender.stamp(msg, key, time.time_ns())
            if before_put is not None:
                before_put(key, payload, stamped)
            self._send(key, payload)
            self._published += 1
        return stamped

    def republish(self, key: str, payload: bytes) -> None:
        """Put a payload this bus published before again, as it was (same seq): through the faults like any
        publication, since a message sent again crosses the same network."""
        self._own(key)
        with self._send_lock:
            self._send(key, payload)

    def publish_raw(self, key: str, payload: bytes) -> None:
        """Put bytes as they are (replay, fault injection); no stamping, no checks beyond the run prefix."""
        self._own(key)
        self.session.put(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON,
                         congestion_control=zenoh.CongestionControl.BLOCK)
        self._tapped(key, payload, time.time_ns())

    def _send(self, key: str, payload: bytes) -> None:
        """Put a payload through this process's message faults, which stand for the network: the tap sees what
        the process sent, once, whether the network then loses, repeats or garbles it (a DMO's history must answer
        an agent's question with an award the network lost)."""
        if self.faults is None:
            self._put(key, payload)
        else:
            self.faults.send(key, payload, self._put)
        self._tapped(key, payload, time.time_ns())

    def _put(self, key: str, payload: bytes) -> None:
        self._publisher(key).put(payload)

    def _tapped(self, key: str, payload: bytes, at: int) -> None:
        if self.tap is not None:
            try:
                self.tap(key, payload, at)
            except Exception:
                with self._state_lock:
                    self._handler_errors += 1
                log.exception("%s: tap failed on %s", self.name, key)

    def wait_for_subscribers(self, key: str, timeout_s: float) -> bool:
        """Wait until someone subscribes to ``key`` (a concrete key), so a first message is not sent into the void."""
        return wait_matching(self._publisher(key), timeout_s)

    def _publisher(self, key: str) -> zenoh.Publisher:
        self._own(key)
        with self._send_lock:
            publisher = self._publishers.get(key)
            if publisher is None:
                publisher = self.session.declare_publisher(
                    key, encoding=zenoh.Encoding.APPLICATION_JSON,
                    # never drop under load: a lost meter report would be settled as missing
                    congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
                self._publishers[key] = publisher
            return publisher

    # --- receiving ---------------------------------------------------------------------------------------

    def subscribe(self, pattern: str, handler: Handler | PayloadHandler, *, payload: bool = False) -> Subscription:
        """Deliver each valid message on keys matching ``pattern`` as handler(key, message, received_at_ns), and with
        ``payload`` also the bytes as they arrived (handler(key, message, received_at_ns, payload)). Payloads that do
        not decode, or do not belong on their key, go to ``on_reject`` instead."""
        deliver = handler if payload else (lambda key, msg, at, _: handler(key, msg, at))

        def on_put(key: str, data: bytes, received_at: int) -> None:
            try:
                msg = decode(data, expected_kind=parse_key(key).kind)
                check_route(key, msg, self.keys.run_id)
            except MessageError as err:
                self._reject(key, data, err)
                return
            self._tapped(key, data, received_at)
            with self._state_lock:
                self._received += 1
            try:
                deliver(key, msg, received_at, data)
            except Exception:
                with self._state_lock:
                    self._handler_errors += 1
                log.exception("%s: handler for %s failed on %s #%d", self.name, pattern, msg.kind, msg.seq)

        return self._declare(pattern, on_put)

    def subscribe_raw(self, pattern: str, handler: RawHandler) -> Subscription:
        """Deliver every payload as it arrived, valid or not, as handler(key, payload, received_at_ns)."""

        def on_put(key: str, payload: bytes, received_at: int) -> None:
            self._tapped(key, payload, received_at)
            try:
                handler(key, payload, received_at)
            except Exception:
                with self._state_lock:
                    self._handler_errors += 1
                log.exception("%s: raw handler for %s failed", self.name, pattern)

        return self._declare(pattern, on_put)

    def _declare(self, pattern: str, on_put: RawHandler) -> Subscription:
        """Subscribe ``on_put(key, payload, received_at_ns)`` to every put on ``pattern`` that passes the gate."""
        self._own(pattern)

        def on_sample(sample: zenoh.Sample) -> None:
            received_at = time.time_ns()
            if sample.kind != zenoh.SampleKind.PUT:
                return
            key, payload = str(sample.key_expr), sample.payload
            if self.gate is not None and not self.gate(key, len(payload)):
                with self._state_lock:
                    self._dropped += 1
                return
            on_put(key, payload.to_bytes(), received_at)

        subscription = Subscription(self, self.session.declare_subscriber(pattern, on_sample))
        with self._state_lock:
            self._subscriptions.append(subscription)
        return subscription

    def _reject(self, key: str, payload: bytes, err: MessageError) -> None:
        with self._state_lock:
            self._rejected[err.code] += 1
        log.warning("%s: rejected %d bytes on %s: %s", self.name, len(payload), key, err.reason)
        if self.on_reject is not None:
            try:
                self.on_reject(key, payload, err)
            except Exception:
                with self._state_lock:
                    self._handler_errors += 1
                log.exception("%s: on_reject hook failed", self.name)

    def _forget(self, subscription: Subscription) -> None:
        with self._state_lock:
            if subscription in self._subscriptions:
                self._subscriptions.remove(subscription)

    def _own(self, key: str) -> None:
        if not str(key).startswith(self.keys.prefix + "/"):
            raise ValueError(f"key {key!r} is outside this run's prefix {self.keys.prefix}/")

    # --- queries ---------------------------------------------------------------------------------------

    def serve(self, pattern: str, answer: Answer, slow: Callable[[str, str], bool] | None = None) -> Subscription:
        """Answer queries on keys matching ``pattern``: ``answer(key_expr, parameters)`` gives the replies, each
        (key, payload, ns); the time travels as the reply's attachment, 8 bytes big-endian. A reply whose key
        does not intersect the query's is skipped (Zenoh refuses it). A query ``answer`` refuses with a ValueError
        (a bad parameter) gets an error reply saying why. A query that ``slow(key_expr, parameters)`` says is slow
        to answer is answered by one thread of its own, in turn: Zenoh hands a queryable its queries one at a time,
        and a day's traffic of a thousand agents (a few hundred thousand replies) held up every agent's query
        behind it. At most ``SLOW_WAITING`` slow queries wait for that thread; one more gets an error reply at once
        (busy), so that no asker can make the answerer hold, or start, more."""
        def on_query(query: zenoh.Query) -> None:
            if slow is not None and slow(str(query.key_expr), str(query.parameters)):
                try:
                    self._slow_queue(answering).put_nowait(query)
                except queue.Full:
                    query.reply_err(f"busy: {SLOW_WAITING} slow queries already wait for an answer; ask again later")
                    query.drop()
            else:
                answering(query)

        def answering(query: zenoh.Query) -> None:
            try:
                asked = str(query.key_expr)
                for key, payload, at in answer(asked, str(query.parameters)):
                    if self._session is None:  # closing: the asker gets what was sent (close() waits for this)
                        break
                    if zenoh.KeyExpr(asked).intersects(zenoh.KeyExpr(key)):
                        query.reply(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON,
                                    attachment=int(at).to_bytes(8, "big"))
            except ValueError as err:
                log.warning("%s: refused a query on %s: %s", self.name, query.selector, err)
                query.reply_err(str(err))
            except Exception:
                with self._state_lock:
                    self._handler_errors += 1
                log.exception("%s: answering a query on %s failed", self.name, pattern)
            finally:
                query.drop()

        self._own(pattern)
        subscription = Subscription(self, self.session.declare_queryable(pattern, on_query))
        with self._state_lock:
            self._subscriptions.append(subscription)
        return subscription

    def _slow_queue(self, answering: Callable[[zenoh.Query], None]) -> queue.Queue:
        """The queue of slow queries, and the one thread that answers them until the bus closes (started with the
        first)."""
        with self._state_lock:
            if self._slow is None:
                self._slow = queue.Queue(maxsize=SLOW_WAITING)
                thread = threading.Thread(target=self._answer_slow, args=(self._slow, answering), name="answering",
                                          daemon=True)
                self._answering.add(thread)
                thread.start()
            return self._slow

    def _answer_slow(self, waiting: queue.Queue, answering: Callable[[zenoh.Query], None]) -> None:
        while (query := waiting.get()) is not None:
            answering(query)

    def fetch(self, selector: str, timeout_s: float = 5.0) -> list[tuple[str, bytes, int | None]]:
        """Query ``selector`` (a key expression of this run, with ``?parameters`` if any) and return every reply
        as (key, payload, ns or None), in the order they came; none if nobody answers."""
        return list(self.replies(selector, timeout_s))

    def replies(self, selector: str, timeout_s: float = 5.0) -> Iterator[tuple[str, bytes, int | None]]:
        """``fetch``'s replies one at a time, as they come: a day's traffic need not be in memory at once."""
        self._own(selector.split("?", 1)[0])
        for reply in self.session.get(selector, timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE):
            sample = reply.ok
            if sample is None:
                log.info("%s: an error reply to %s: %s", self.name, selector, reply.err)
                continue
            at = sample.attachment.to_bytes() if sample.attachment is not None else b""
            yield str(sample.key_expr), sample.payload.to_bytes(), int.from_bytes(at, "big") if at else None

    # --- presence ----------------------------------------------------------------------------------------

    def watch_presence(self, on_join: Callable[[str], None], on_leave: Callable[[str], None], *,
                       history: bool = True) -> Subscription:
        """Call on_join(name) when another process of this run appears (with ``history``, also for those already
        there) and on_leave(name) when it vanishes: closed at once, killed within milliseconds, frozen after
        its lease."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                name = parse_key(str(sample.key_expr)).topic
            except MessageError:
                return
            if name == self.name:
                return
            try:
                (on_join if sample.kind == zenoh.SampleKind.PUT else on_leave)(name)
            except Exception:
                with self._state_lock:
                    self._handler_errors += 1
                log.exception("%s: presence callback failed for %s", self.name, name)

        subscriber = self.session.liveliness().declare_subscriber(self.keys.alive("*"), on_sample, history=history)
        subscription = Subscription(self, subscriber)
        with self._state_lock:
            self._subscriptions.append(subscription)
        return subscription

    def present(self, timeout_s: float = 1.0) -> set[str]:
        """Names of the processes of this run alive now (this one included if it announced itself). The replies go
        to a callback, not a channel: a router answers from its own tables on the asking thread, and more tokens
        than a channel holds (256) left that thread waiting on itself for good (a DMO with 400 agents)."""
        names, done = set(), threading.Event()

        def reply(r: zenoh.Reply) -> None:
            try:
                names.add(parse_key(str(r.ok.key_expr)).topic)
            except (AttributeError, MessageError):
                pass  # an error reply, or a token that is not ours

        self.session.liveliness().get(self.keys.alive("*"), zenoh.handlers.Callback(reply, done.set),
                                      timeout=timeout_s)
        done.wait(timeout_s + PRESENCE_GRACE_S)
        return set(names)

    # --- counters ----------------------------------------------------------------------------------------

    def stats(self) -> dict:
        """Counters since the bus opened: published, received (valid), dropped by the gate, rejected by code,
        handler_errors."""
        with self._state_lock:
            return {"published": self._published, "received": self._received, "dropped": self._dropped,
                    "rejected": dict(self._rejected), "rejected_total": sum(self._rejected.values()),
                    "handler_errors": self._handler_errors}


def _drain(waiting: queue.Queue) -> None:
    """Refuse the queries still waiting for an answer: the bus closes."""
    while True:
        try:
            query = waiting.get_nowait()
        except queue.Empty:
            return
        if query is not None:
            _quietly(lambda: (query.reply_err("closing"), query.drop()), "refuse a waiting query")


def wait_matching(publisher: zenoh.Publisher, timeout_s: float) -> bool:
    """Wait at most ``timeout_s`` until ``publisher`` has a subscriber; whether it has. The listener goes first, so
    a subscriber that comes between it and the look at the status is not missed. (A status is an object, truthy
    even when nothing matches: its ``matching`` says.)"""
    matched = threading.Event()
    with publisher.declare_matching_listener(lambda status: status.matching and matched.set()):
        return publisher.matching_status.matching or matched.wait(timeout_s)


def _quietly(action: Callable[[], object], what: str) -> None:
    try:
        action()
    except Exception:
        log.debug("could not %s", what, exc_info=True)


ANSWERING_STOP_S = 10.0  # how long closing waits for a slow query's answer to stop (it stops at its next reply)
SLOW_WAITING = 1  # slow queries (a day's traffic) that may wait while one is answered: a recorder asks one at a time

# A process opens its sessions one at a time. The agents forked ten to a process (dmosim run --hosting fork) would
# otherwise all shake hands at once: a thousand TLS handshakes at once on 2 cores left an agent unconnected after
# its 60 s while 849 others had registered (docs/benchmarks.md).
_OPENING = threading.Lock()

# A session with a callback subscriber owns a non-daemon thread, so a process that forgets to close it hangs
# at exit: Python joins that thread before running atexit hooks. threading's own exit hook runs before the
# join (concurrent.futures relies on it), so open buses are closed there.
_OPEN: weakref.WeakSet[Bus] = weakref.WeakSet()


def _close_open_buses() -> None:
    for bus in list(_OPEN):
        bus.close()


getattr(threading, "_register_atexit", atexit.register)(_close_open_buses)


__all__ = ["MODES", "Bus", "BusConfig", "Subscription"]

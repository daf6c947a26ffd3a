"""What every service process shares: session, liveliness, inboxes, stop signal, stats.

A service is ``main(argv)`` in ``quick_stream.services`` (the repo's ``services/``): it
parses the standard zenoh flags (:mod:`quick_stream.stream.transport`) plus its own, opens a
:class:`ServiceRuntime`, and loops: take messages from its inboxes, call the library stage,
publish.

* **Inbox**: a callback subscriber that appends each payload to a bounded deque.
  When full it drops the *oldest* and counts it (zenoh's ``RingChannel`` drops
  silently; we report drops in the stats). Lossless inboxes are the same with a
  bound no healthy stream reaches. Every inbox recovers what its own link dropped
  from the lossless publishers' caches (zenoh-ext sample-miss recovery), in order;
  what the cache no longer held is counted (``inbox<i>_lost``).
* **Publishers never wait for a subscriber**: all of them drop for a congested link
  (``CongestionControl.DROP``), so a slow foreign subscriber, peer or client, can only
  slow itself; the pipeline's own lossless keys are numbered, cached and recovered
  (docs/deployment.md, "Delivery guarantees per key").
* **Stop**: SIGTERM and SIGINT set a flag; the loop ends, then the runtime
  undeclares everything and closes the session in ``finally``
  (measured: without a handler SIGTERM kills the process before cleanup).
* **Liveliness**: a token on ``quick/@v1/<stream>/health/<service>``, so the
  launcher and other services see who is up (and who went away, in milliseconds).
* **Stats**: a ``stats`` message about once a second (``values`` the service fills, rates from
  :mod:`quick_stream.stream.meters`:
  counters, fps, ms per item, drops, errors).
* **Taking over**: publishers may keep a history cache; every service answers cursor
  queries (newest seq per stage received); a service restarted mid-stream asks how far its
  predecessor's output got and subscribes to its inputs with history (docs/architecture.md).
* **Containment**: :meth:`ServiceRuntime.contained` logs and counts an unexpected exception
  while handling one message, and the service goes on.
"""
from __future__ import annotations

import argparse
import atexit
import gc
import logging
import os
import signal
import threading
import time
from collections import deque
from typing import Any, Callable, Iterator

import zenoh
import zenoh.ext

from . import keys
from .arrivals import ArrivalLedger, Gap
from .wire import Decoded, Stats, WireError, decode, encode_stats
from .wire.codec import set_max_image_side

# Set by the supervisor (quick_stream/stream/launcher.py) for a service it restarted: how many times.
RESTARTED_ENV = "QUICK_STREAM_RESTARTED"

log = logging.getLogger(__name__)


class Inbox:
    """Bounded drop-oldest queue of (key, payload bytes, arrival ns) fed by a zenoh callback subscriber.

    It also keeps ``arrivals``: per (stream, stage) of the key the highest seq of the data
    messages that arrived since that stage's last ``end`` and the seqs skipped on the way
    (read from the envelope on arrival, so a busy service still answers cursor queries
    exactly; :class:`~quick_stream.stream.arrivals.ArrivalLedger`). ``on_gap`` hears each gap."""

    def __init__(self, capacity: int, cond: threading.Condition,
                 on_arrival: Callable[[str, bytes, int], None] | None = None,
                 on_gap: Callable[[Gap], None] | None = None) -> None:
        self.capacity = self.base_capacity = self.catch_up = capacity
        self.catch_up_until = 0.0  # monotonic time before which a drained queue keeps the catch-up bound
        self.on_arrival = on_arrival
        self.on_gap = on_gap
        self._q: deque[tuple[str, bytes, int]] = deque()  # (key, payload, arrival time ns)
        self._cond = cond
        self.received = 0
        self.dropped = 0
        self.skipped = 0
        self.lost = 0  # messages of a lossless publisher that never arrived and were no longer in its cache
        self.skip_through: int | None = None  # data messages with a seq <= this are not queued (taken over)
        self._newest: int | None = None  # taking over: the newest data seq queued so far
        self._newest_pub: int | None = None  # taking over: the latest publication time queued so far (frames)
        self.arrivals = ArrivalLedger()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key, data = str(sample.key_expr), sample.payload.to_bytes()
        item = (key, data, time.time_ns())
        # Checked before any bookkeeping reads it (a malformed message's seq must not move the
        # ledger, the cursor or the skips); queued all the same: its consumer logs why it is refused.
        env = self.arrivals.checked(key, data)
        if env is not None and (gap := self.arrivals.account(key, *env)) is not None and self.on_gap is not None:
            self.on_gap(gap)
        if self.on_arrival is not None:
            self.on_arrival(*item)
        if self.skip_through is not None:
            # A service taking over skips what its predecessor already handled; a history
            # replay of many of those must not push the ones it needs out of the queue.
            if env is not None and env[0] != "end":
                if env[1] <= self.skip_through and not (env[2] is not None and self._newest_pub is not None
                                                        and env[2] > self._newest_pub):
                    # (one published after everything queued is live, not a replay: a stream renumbered
                    # below the cursor, which the stage takes as a new numbering once a run confirms it)
                    self.skipped += 1
                    return
                if env[2] is not None:
                    self._newest_pub = max(env[2], self._newest_pub or env[2])
                if self._newest is not None and env[1] < self._newest:
                    # older than what already came: the history replay, delivered after live messages
                    # (and after the queue first drained); it is owed, so hold it as during catch-up
                    self.capacity = max(self.capacity, self.catch_up)
                self._newest = env[1] if self._newest is None else max(self._newest, env[1])
        with self._cond:
            if len(self._q) >= self.capacity:
                self._q.popleft()
                self.dropped += 1
            self._q.append(item)
            self.received += 1
            self._cond.notify_all()

    def _on_miss(self, miss: Any) -> None:
        self.lost += miss.nb
        log.warning("%d messages of publisher %s were lost (no longer in its cache)", miss.nb, miss.source)

    def pop(self) -> tuple[str, bytes, int] | None:
        with self._cond:
            if not self._q:
                return None
            item = self._q.popleft()
            if not self._q and self.capacity != self.base_capacity and time.monotonic() >= self.catch_up_until:
                self.capacity = self.base_capacity  # caught up: back to the live bound
            return item

    def __len__(self) -> int:
        return len(self._q)


LOSSLESS_STAGES = ("frame", "flow", "motion", "correction")  # the keys published with ``lossless=True``
RECOVERY_CACHE = 150  # messages every lossless publisher keeps for receivers to recover (5 s at 30 fps)
HEARTBEAT_S = 0.5  # a lossless publisher's heartbeat: a receiver notices a lost last message within it


class TimedPublisher:
    """A zenoh publisher whose ``put`` is timed: the longest put since the last stats (``put_ms_max``)
    and the puts that took longer than ``SLOW_PUT_MS`` (``slow_puts``, a running count) go into the
    service's stats as ``pub_<stage>_put_ms_max`` / ``pub_<stage>_slow_puts``. A put that waits is a
    congested link (docs/deployment.md, "Delivery guarantees per key")."""

    SLOW_PUT_MS = 100.0

    def __init__(self, pub: Any, stage: str) -> None:
        self.pub, self.stage = pub, stage
        self.put_ms_max = 0.0
        self.slow_puts = 0

    def put(self, payload: bytes, **kw: Any) -> None:
        t0 = time.perf_counter()
        self.pub.put(payload, **kw)
        ms = (time.perf_counter() - t0) * 1e3
        self.put_ms_max = max(self.put_ms_max, ms)
        self.slow_puts += ms > self.SLOW_PUT_MS

    def take(self) -> dict[str, Any]:
        out = {f"pub_{self.stage}_put_ms_max": round(self.put_ms_max, 1), f"pub_{self.stage}_slow_puts": self.slow_puts}
        self.put_ms_max = 0.0
        return out

    def undeclare(self) -> None:
        self.pub.undeclare()


class ServiceRuntime:
    """One service process's zenoh session and life cycle (use as a context manager)."""

    def __init__(self, service: str, stream: str, conf: zenoh.Config, stats_period_s: float = 1.0,
                 install_signals: bool = True) -> None:
        self.service = service
        self.stream = keys.check_stream(stream)
        self.stop = threading.Event()
        self._cond = threading.Condition()
        self._inboxes: list[Inbox] = []
        self._subs: list[Any] = []  # keep references: a dropped subscriber is undeclared
        self._pubs: list[Any] = []
        self._timed: list[TimedPublisher] = []
        self._stats_seq = 0
        self._stats_period = stats_period_s
        self._next_stats = time.monotonic() + stats_period_s
        if install_signals:
            signal.signal(signal.SIGTERM, self._on_signal)
            signal.signal(signal.SIGINT, self._on_signal)
        self.session = zenoh.open(conf)
        self._token = None  # declared by ready(), once the service's subscribers exist
        self._stats_pub = self._declare_publisher("stats")
        # Everything allocated so far (modules, OpenCV/zenoh objects) lives for the whole run:
        # keep it out of the collector's generations so collections stay short.
        gc.freeze()

    def _on_signal(self, signum: int, _frame: Any) -> None:
        log.info("%s/%s: signal %d, stopping", self.stream, self.service, signum)
        self.stop.set()
        with self._cond:
            self._cond.notify_all()

    # --- endpoints -------------------------------------------------------------------------------

    def publisher(self, stage: str, lossless: bool = False, stream: str | None = None,
                  cache: int = 0) -> TimedPublisher:
        """Publisher on ``quick/@v1/<stream>/<stage>``. Every publisher drops for a congested link
        instead of waiting for it (``CongestionControl.DROP``: at most zenoh's ``wait_before_drop``,
        1 ms, per link and message), so no subscriber, the pipeline's or a foreign viewer, can hold a
        publisher. ``lossless`` (flows, motions, corrections, frames, their end markers): an advanced
        publisher that numbers its messages, keeps at least ``RECOVERY_CACHE`` of them and sends a
        heartbeat, so a receiver whose own link dropped some fetches them back from the cache, in
        order (:meth:`inbox`); only what fell out of the cache is lost, and counted there. ``cache``
        > 0 also keeps the last ``cache`` messages for a restarted consumer's history query. Its puts
        are timed (:class:`TimedPublisher`, in the stats)."""
        pub = TimedPublisher(self._declare_publisher(stage, lossless, stream, cache), stage)
        self._timed.append(pub)
        return pub

    def _declare_publisher(self, stage: str, lossless: bool = False, stream: str | None = None,
                           cache: int = 0) -> zenoh.Publisher | zenoh.ext.AdvancedPublisher:
        kw = dict(congestion_control=zenoh.CongestionControl.DROP, reliability=zenoh.Reliability.RELIABLE)
        key = keys.key(stream or self.stream, stage)
        if lossless or cache > 0:
            # the cache's replies drop for a congested link too: a foreign subscriber that asks for the
            # history and stops reading must not hold the cache (zenoh replies under its lock, and each
            # put takes it); a healthy receiver's recovery asks again for what it still misses
            replies = zenoh.ext.RepliesConfig(congestion_control=zenoh.CongestionControl.DROP)
            size = max(cache, RECOVERY_CACHE) if lossless else cache
            detect = zenoh.ext.MissDetectionConfig(heartbeat=HEARTBEAT_S) if lossless else None
            pub = zenoh.ext.declare_advanced_publisher(
                self.session, key, cache=zenoh.ext.CacheConfig(size, replies_config=replies),
                sample_miss_detection=detect, publisher_detection=True, **kw)
        else:
            pub = self.session.declare_publisher(key, **kw)
        self._pubs.append(pub)
        return pub

    def inbox(self, key_expr: str, capacity: int, history: bool = False,
              on_arrival: Callable[[str, bytes, int], None] | None = None,
              on_gap: Callable[[Gap], None] | None = None, skip_through: int | None = None,
              catch_up: int = 0, publisher: str | None = None, publisher_wait_s: float = 5.0,
              catch_up_s: float = 5.0) -> Inbox:
        """Subscribe ``key_expr`` into a drop-oldest inbox of ``capacity`` messages. ``history``: first
        receive what the publishers' caches hold (a service restarted mid-stream takes over);
        ``skip_through``: data messages with a seq up to this one are counted (``skipped``) but not
        queued, so a history replay of what the predecessor handled leaves room for the rest;
        ``catch_up``: the capacity for ``catch_up_s`` and then until the queue first drains (the
        backlog a restarted service finds in the history is longer than the live bound, and a
        history replay arrives in pieces: the queue may drain between them; a restarted flow fell
        back to the live bound after the first frames of its history and dropped 17 of the rest). ``publisher``: with ``history``, the
        service whose cache holds it; the subscription waits (up to ``publisher_wait_s``) until that
        service's liveliness token is seen, so its history query reaches it (killed together with the
        router, a restarted flow subscribed before the capture was reachable again and never got the
        frames of its restart: 45 orphans).
        ``on_arrival(key, payload, arrival_ns)`` runs in zenoh's thread as each message arrives, before it is
        queued (keep it short; it must not raise); ``on_gap(gap)`` before it, when the message skips seqs
        of its stage (:mod:`quick_stream.stream.arrivals`)."""
        box = Inbox(capacity, self._cond, on_arrival, on_gap)
        box.skip_through = skip_through
        box.capacity = box.catch_up = max(capacity, catch_up)
        box.catch_up_until = time.monotonic() + catch_up_s if catch_up > capacity else 0.0
        if history and publisher is not None and self.wait_for([publisher], publisher_wait_s):
            log.warning("%s/%s: %s not seen after %.0f s; subscribing to %s with history all the same",
                        self.stream, self.service, publisher, publisher_wait_s, key_expr)
        # Recovery: messages of a lossless publisher (LOSSLESS_STAGES) that this session's link dropped
        # (congested: this process stopped reading for a while) are fetched back from the publisher's
        # cache and handed on in order; what the cache no longer holds is counted as ``lost``. Those
        # keys get an advanced subscriber each; the others (stabilized, stats) a plain one, as before:
        # an advanced subscriber also drops a message that is not numbered and whose timestamp is not
        # newer than the last one delivered from its session (zenoh-ext's timestamped path; with every
        # key on advanced subscribers, test_faults[router] missed 1-4 stabilized frames in 2 of 4 runs,
        # most likely reordered while the router restarted). ``history``: a publisher this session does
        # not know yet (its declaration arrives after ours) is queried once seen.
        head, _, last = key_expr.rpartition("/")
        lossless = [key_expr] if last in LOSSLESS_STAGES else [f"{head}/{st}" for st in LOSSLESS_STAGES] if last == "*" else []
        for k in lossless:
            sub = zenoh.ext.declare_advanced_subscriber(
                self.session, k, box._on_sample,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True) if history else None,
                recovery=zenoh.ext.RecoveryConfig(heartbeat=True))
            self._subs.append(sub.sample_miss_listener(box._on_miss))
            self._subs.append(sub)
        if key_expr not in lossless:
            def others(sample: zenoh.Sample) -> None:
                if str(sample.key_expr).rpartition("/")[2] not in LOSSLESS_STAGES:
                    box._on_sample(sample)
            self._subs.append(self.session.declare_subscriber(key_expr, others))
        self._inboxes.append(box)
        return box

    def subscribe(self, key_expr: str, callback: Callable[[zenoh.Sample], None]) -> None:
        """A plain callback subscriber (kept referenced until close); the callback must be quick."""
        self._subs.append(self.session.declare_subscriber(key_expr, callback))

    def watch_health(self, callback: Callable[[str, bool], None]) -> None:
        """``callback(service, up)`` for each service of this stream whose liveliness token is up now
        (at once) and whenever one appears or goes away (zenoh's thread; keep it quick)."""
        def on_token(sample: zenoh.Sample) -> None:
            try:
                _, service = keys.parse_health(str(sample.key_expr))
            except ValueError:
                return
            callback(service, sample.kind != zenoh.SampleKind.DELETE)

        key = f"{keys.PREFIX}/{self.stream}/health/*"
        self._subs.append(self.session.liveliness().declare_subscriber(key, on_token, history=True))

    def wait(self, timeout_s: float) -> None:
        """Sleep until any inbox has a message, a stop signal, or ``timeout_s``."""
        with self._cond:
            if self.stop.is_set() or any(len(b) for b in self._inboxes):
                return
            self._cond.wait(timeout_s)

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def ready(self) -> None:
        """Declare the liveliness token: call once the service's subscribers are declared, so
        whoever waits for it (capture's ``--wait-for``) cannot publish before they exist."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(keys.health_key(self.stream, self.service))

    # --- stream cursor ---------------------------------------------------------------------------------

    def serve_cursor(self, all_streams: bool = False) -> None:
        """Answer cursor queries (``quick/@v1/<stream>/cursor/<service>``) with, per stage this service
        receives, the newest seq of the stream under way (its inboxes' ``arrivals``). A service
        restarted mid-stream asks for its own output stage, so it takes over where its
        predecessor stopped (:meth:`stream_cursor`). ``all_streams``: for every stream it receives
        (a recorder of all streams), each answered about its own."""
        def on_query(query: zenoh.Query) -> None:
            stream = str(query.key_expr).split("/")[2]
            newest: dict[str, int] = {}
            for box in self._inboxes:
                for (s, stage), seq in box.arrivals.newest().items():
                    if s == stream:
                        newest[stage] = max(seq, newest.get(stage, -1))
            # dropped for a congested link, like every put: the asker asks again (stream_cursor, lagging)
            query.reply(keys.cursor_key(stream, self.service), encode_stats(Stats(self.service, newest), stream, 0),
                        congestion_control=zenoh.CongestionControl.DROP)

        key = keys.cursor_key("*" if all_streams else self.stream, self.service)
        self._subs.append(self.session.declare_queryable(key, on_query))

    def stream_cursor(self, stage: str, timeout_s: float = 3.0, settle_s: float = 1.0) -> int | None:
        """The newest seq of ``stage`` in this stream that any running service has received, or None
        (nothing yet: a new stream, or nobody who receives that stage is up).

        A new session sees the others' liveliness tokens before their queryables, and a busy
        service may answer late, so it asks again (up to ``timeout_s``) while other services of the
        stream are alive and either none has answered yet or the stream is under way (some stage
        has a seq) but nobody has answered for ``stage``. With every answer saying no stream is under
        way it answers None at once; with nobody else alive, once ``settle_s`` has passed (right after
        connecting, a session may see only some of the others' tokens, or none: a restarted flow
        once started afresh that way, and the frames of its restart went out uncorrected)."""
        if os.environ.get(RESTARTED_ENV):
            # restarted by the supervisor, so a stream was most likely under way: killed together with
            # the router, the others may take seconds to reconnect (a restarted flow once settled after
            # 1 s, alone, and started afresh: 77 frames went out uncorrected)
            timeout_s = settle_s = max(timeout_s, 10.0)
        t0 = time.monotonic()
        deadline = t0 + timeout_s
        self._wait_connected(min(timeout_s, 1.0))
        while True:
            answered, under_way, best = self._ask_cursor(stage)
            if best is not None or (answered and not under_way):
                return best
            alone = time.monotonic() - t0 > settle_s and not (self.alive() - {self.service})
            if time.monotonic() > deadline or self.stop.is_set() or alone:
                if under_way:
                    log.warning("%s/%s: the stream is under way but no service reports %s; starting afresh",
                                self.stream, self.service, stage)
                elif not answered and not alone:
                    log.warning("%s/%s: no service answered the cursor query in %.0f s; starting afresh",
                                self.stream, self.service, timeout_s)
                return None
            self.stop.wait(0.1)

    def _wait_connected(self, timeout_s: float) -> None:
        """Until the session has a router or a peer (``zenoh.open`` returns before it connects)."""
        deadline = time.monotonic() + timeout_s
        info = self.session.info
        while not (list(info.routers_zid()) or list(info.peers_zid())) and time.monotonic() < deadline:
            time.sleep(0.01)

    def _cursor_answers(self) -> Iterator[tuple[str, dict]]:
        """(service, {stage: newest seq}) of every service of the stream that answers a cursor query
        (:meth:`serve_cursor`) within 0.5 s; an answer that does not decode is skipped."""
        replies = self.session.get(keys.cursor_key(self.stream), target=zenoh.QueryTarget.ALL,
                                   consolidation=zenoh.ConsolidationMode.NONE, timeout=0.5)
        for reply in replies:
            try:
                values = decode(reply.ok.payload.to_bytes()).obj.values
                service = str(reply.ok.key_expr).rsplit("/", 1)[-1]
            except (WireError, AttributeError, zenoh.ZError):
                continue
            yield service, values

    def _ask_cursor(self, stage: str) -> tuple[bool, bool, int | None]:
        """(any service answered, any answer has a seq (a stream is under way), the newest ``stage`` seq)."""
        answered, under_way, best = False, False, None
        for service, values in self._cursor_answers():
            answered = True
            log.debug("cursor %s: %s answered %s", stage, service, values)
            under_way = under_way or bool(values)
            seq = values.get(stage)
            if isinstance(seq, int) and not isinstance(seq, bool) and (best is None or seq > best):
                best = seq
        return answered, under_way, best

    def lagging(self, stage: str, seq: int, timeout_s: float, required: frozenset[str] = frozenset()) -> set[str]:
        """Wait until every service that has received ``stage`` of this stream, and every service in
        ``required`` (received or not), reports ``seq`` or a newer one (its inbox's arrivals,
        :meth:`serve_cursor`), or ``timeout_s`` passes; returns the services still behind (empty:
        delivered). A publisher asks before it ends the stream and closes, so what it put last is not
        left in flight, and after its first message, so every consumer has its start (a receiver
        recovers a message its link dropped only after the first one it got from that publisher)."""
        deadline = time.monotonic() + timeout_s
        while True:
            behind: set[str] = set()
            answered: set[str] = set()
            for service, values in self._cursor_answers():
                answered.add(service)
                got = values.get(stage)
                if isinstance(got, int) and not isinstance(got, bool) and got < seq:
                    behind.add(service)
                elif got is None and service in required:
                    behind.add(service)
            # a busy service may not answer in time: one that is alive and silent is not known to be done
            behind |= (self.alive() | required) - answered - {self.service}
            if not behind or time.monotonic() > deadline or self.stop.is_set():
                return behind
            self.stop.wait(0.05)

    def until_ended(self, stage: str, timeout_s: float) -> set[str]:
        """After this publisher's ``end`` of ``stage``: wait until no running service of the stream
        reports ``stage`` in its cursor any more (a receiver's arrival ledger closes the stage on the
        ``end``), or ``timeout_s`` passes; returns the services still reporting it. The publisher's
        cache closes with its session, so a receiver whose link dropped the ``end`` for congestion
        can recover it only while the publisher waits here."""
        deadline = time.monotonic() + timeout_s
        while True:
            still = {service for service, values in self._cursor_answers() if stage in values}
            if not still or time.monotonic() > deadline or self.stop.is_set():
                return still
            self.stop.wait(0.05)

    # --- liveliness --------------------------------------------------------------------------------

    def alive(self, stream: str | None = None) -> set[str]:
        """Services of ``stream`` (default: ours) whose liveliness token is up right now."""
        out = set()
        key = f"{keys.PREFIX}/{keys.check_stream(stream or self.stream)}/health/*"
        for reply in self.session.liveliness().get(key, timeout=1.0):
            try:
                out.add(keys.parse_health(str(reply.ok.key_expr))[1])
            except (ValueError, AttributeError, zenoh.ZError):
                continue
        return out

    def wait_for(self, services: list[str], timeout_s: float) -> set[str]:
        """Block until all ``services`` are alive (or timeout / stop); returns those still missing."""
        deadline = time.monotonic() + timeout_s
        missing = set(services)
        while missing and not self.stop.is_set():
            missing = set(services) - self.alive()
            if not missing or time.monotonic() > deadline:
                break
            self.stop.wait(0.1)
        return missing

    # --- stats ---------------------------------------------------------------------------------------

    def stats_due(self) -> bool:
        return time.monotonic() >= self._next_stats

    def publish_stats(self, values: dict[str, Any]) -> None:
        """Publish a ``stats`` message now (inbox drops are added automatically)."""
        vals = dict(values)
        for p in self._timed:
            vals.update(p.take())
        for i, b in enumerate(self._inboxes):
            vals[f"inbox{i}_dropped"] = b.dropped
            vals[f"inbox{i}_invalid"] = b.arrivals.invalid  # failed the check on arrival (not accounted)
            vals[f"inbox{i}_queued"] = len(b)
            vals[f"inbox{i}_lost"] = b.lost
            if b.skip_through is not None:
                vals[f"inbox{i}_skipped"] = b.skipped
        self._stats_pub.put(encode_stats(Stats(self.service, vals), self.stream, self._stats_seq))
        self._stats_seq += 1
        if self._stats_seq % TRIM_EVERY == 0:
            trim_heap()
        self._next_stats = time.monotonic() + self._stats_period

    def maybe_stats(self, values: Callable[[], dict[str, Any]]) -> None:
        if self.stats_due():
            self.publish_stats(values())

    def receive(self, inbox: Inbox, expect: str, errors: dict[str, int],
                stats: Callable[[], dict[str, Any]]) -> Iterator[Decoded]:
        """Decoded ``expect`` and ``end`` messages from ``inbox`` until stopped, publishing stats when
        due; one that does not decode, or of another type, is logged and counted in
        ``errors["decode_errors"]`` and skipped (the stream goes on)."""
        while not self.stop.is_set():
            self.maybe_stats(stats)
            item = inbox.pop()
            if item is None:
                self.wait(0.2)
                continue
            msg = self.decode(item[0], item[1], (expect, "end"), errors)
            if msg is not None:
                yield msg

    def decode(self, key_expr: str, data: bytes, expect: tuple[str, ...], errors: dict[str, int]) -> Decoded | None:
        """The message decoded, if it is one of the ``expect`` types and of this service's stream;
        otherwise None, logged (naming the key, field and problem) and counted in ``errors["decode_errors"]``."""
        try:
            msg = decode(data)
            if msg.stream != self.stream:
                raise WireError(f"message of stream {msg.stream!r} on the key of stream {self.stream!r}",
                                stream=msg.stream, seq=msg.seq, field="stream", type=msg.type)
        except WireError as e:
            errors["decode_errors"] += 1
            log.error("%s message on %s rejected: %s", "/".join(expect), key_expr, e)
            return None
        if msg.type not in expect:
            errors["decode_errors"] += 1
            log.error("unexpected %s message on %s", msg.type, key_expr)
            return None
        return msg

    def contained(self, what: str, errors: dict[str, int]) -> "_Contained":
        """Context for processing one message: an unexpected exception (a bug or an input no check
        foresaw) is logged with its traceback and counted in ``errors["internal_errors"]``, and the
        service goes on with the next message: one bad frame never kills a stream."""
        return _Contained(f"{self.stream}/{self.service}: {what}", errors)

    # --- shutdown --------------------------------------------------------------------------------------

    def close(self) -> None:
        entities = [*self._subs, *([self._token] if self._token is not None else []), *self._pubs]
        for e in entities:
            try:
                e.undeclare()
            except zenoh.ZError:
                pass  # already gone with a dying session: nothing left to release
        self._subs.clear()
        self._pubs.clear()
        self._token = None
        self.session.close()

    def __enter__(self) -> "ServiceRuntime":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class _Contained:
    def __init__(self, what: str, errors: dict[str, int]) -> None:
        self.what, self.errors = what, errors

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: type | None, exc: BaseException | None, _tb: Any) -> bool:
        if kind is None or not issubclass(kind, Exception):
            return False
        self.errors["internal_errors"] = self.errors.get("internal_errors", 0) + 1
        log.error("%s failed (%s: %s); skipped, the stream goes on", self.what, kind.__name__, exc,
                  exc_info=(kind, exc, _tb))
        return True


MAX_SIDE_ENV = "QUICK_STREAM_MAX_FRAME_SIDE"  # the default of every service's --max-frame-side


def service_parser(service: str, description: str | None) -> argparse.ArgumentParser:
    """Argument parser with the standard zenoh flags, ``--stream`` and ``-v``."""
    from .argtypes import stream_id
    from .transport import add_zenoh_args

    p = argparse.ArgumentParser(prog=f"quick-stream-{service}", description=description,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--stream", type=stream_id, default="cam0",
                   help="stream (camera) id, 1-64 of [A-Za-z0-9_-]; one per camera (default cam0)")
    p.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    p.add_argument("--max-frame-side", type=int, default=int(os.environ.get(MAX_SIDE_ENV, 4096)), metavar="PX",
                   help=f"largest image width or height accepted, checked from the header before decoding "
                   f"(default 4096, or ${MAX_SIDE_ENV})")
    add_zenoh_args(p)
    return p


TRIM_EVERY = 10  # stats periods (about 10 s)


def _libc_trim() -> Callable[[int], int] | None:
    try:
        import ctypes

        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None  # not glibc: nothing to do


_MALLOC_TRIM = _libc_trim()


def trim_heap() -> None:
    """Hand freed heap pages back to the OS (glibc ``malloc_trim``). Frames and messages of many
    sizes, allocated in zenoh's threads and freed in the service's, leave free memory spread over
    several malloc arenas; without this the resident size of a long run creeps up by several
    percent (10-minute soak, docs/reliability.md). A few milliseconds, every ``TRIM_EVERY`` stats."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


def lower_priority(niceness: int) -> None:
    """Raise this process's nice value by ``niceness`` (background work such as recording yields
    the CPU to the live path on a busy machine; its queue absorbs the wait)."""
    if niceness > 0:
        os.nice(niceness)


def setup_logging(service: str, verbose: bool) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format=f"%(asctime)s {service} %(levelname)s: %(message)s")


def _ignore_term_while_exiting() -> None:
    """At interpreter exit, after the service's work and clean-up are done: ignore SIGTERM.
    CPython puts the default (fatal) handler back while it finalises, so a supervisor's SIGTERM
    arriving in those last moments (zenoh's objects are dropped there, slowly on a busy machine)
    turned a clean exit into -15; an ignored signal is left alone (tests/test_runtime.py)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def service_main(service: str, parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace, zenoh.Config], int],
                 argv: list[str] | None, check: Callable[[argparse.Namespace], Any] | None = None,
                 early: Callable[[argparse.Namespace], int | None] | None = None) -> int:
    """A service's ``main``: parse, log, one OpenCV thread, build the zenoh config (and ``check`` the
    service's own settings and that its output paths can be written), then ``run(args, conf)``; a bad
    flag or config exits 2 with its message, before any session is opened. A session zenoh refuses
    to open (e.g. a listen endpoint already in use) is logged with zenoh's reason, exit 2.
    ``early`` may answer without a session (e.g. ``--list-devices``) by returning an exit code."""
    import cv2

    from .argtypes import check_outputs
    from .transport import config_from_args, zenoh_message

    args = parser.parse_args(argv)
    setup_logging(service, args.verbose)
    atexit.unregister(_ignore_term_while_exiting)  # once, however often main() runs in one process
    atexit.register(_ignore_term_while_exiting)
    if early is not None and (code := early(args)) is not None:
        return code
    cv2.setNumThreads(1)
    try:
        if hasattr(args, "max_frame_side"):
            set_max_image_side(args.max_frame_side)
        conf = config_from_args(args)
        check_outputs(args)
        if check is not None:
            check(args)
    except ValueError as e:
        logging.getLogger(service).error("%s", e)
        return 2
    try:
        return run(args, conf)
    except zenoh.ZError as e:
        logging.getLogger(service).error("zenoh: %s (check -e/-l/-c/--cfg and the QUICK_STREAM_ZENOH_* variables)",
                                         zenoh_message(e))
        return 2

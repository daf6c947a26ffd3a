"""What every service process shares: session, liveliness, inboxes, the service loop, stop, stats.

A service is ``main(argv)`` in ``quick_stream.services`` (the repo's ``services/``): it parses the
standard zenoh flags (:mod:`quick_stream.stream.transport`) plus its own
(:func:`~quick_stream.stream.process.service_main`), opens a :class:`ServiceRuntime`, declares its
inboxes and publishers, and hands the runtime one handler per message type
(:meth:`~quick_stream.stream.loop.Loop.serve`: the loop that receives, decodes, checks, dispatches,
contains errors, publishes stats and stops is the runtime's; docs/architecture.md).

* **Inboxes and publishers** (:mod:`quick_stream.stream.inbox`): drop-oldest inboxes that recover
  what their link dropped from the lossless publishers' caches; publishers that never wait for a
  subscriber (docs/deployment.md, "Delivery guarantees per key").
* **Stop**: SIGTERM and SIGINT set a flag; the loop ends, then the runtime
  undeclares everything and closes the session in ``finally``
  (measured: without a handler SIGTERM kills the process before cleanup).
* **Liveliness**: a token on ``quick/@v1/<stream>/health/<service>``, so the
  launcher and other services see who is up (and who went away, in milliseconds).
* **Stats**: a ``stats`` message about once a second (``values`` the service fills, rates from
  :mod:`quick_stream.stream.meters`; the runtime adds its own counters, ``decode_errors`` and
  ``internal_errors``, and each inbox's and publisher's).
* **Taking over**: publishers may keep a history cache; every service answers cursor
  queries (newest seq per stage received); a service restarted mid-stream asks how far its
  predecessor's output got and subscribes to its inputs with history
  (:mod:`quick_stream.stream.cursor`).
* **Containment**: :meth:`ServiceRuntime.contained` logs and counts an unexpected exception
  while handling one message, and the service goes on.
"""
from __future__ import annotations

import gc
import logging
import signal
import threading
import time
from typing import Any, Callable

import zenoh
import zenoh.ext

from . import keys
from .arrivals import Gap
from .cursor import Cursors
from .inbox import HEARTBEAT_S, RECOVERY_CACHE, Inbox, TimedPublisher
from .topology import LOSSLESS_KEYS
from .loop import Input, Loop
from .heap import trim_heap
from .process import CLOSE_TIMED_OUT, SESSION_CLOSE_S, TRIM_EVERY, close_within, closed_late
from .replays import ReplayFilter
from .wire import Decoded, Stats, WireError, decode, encode_stats

__all__ = ["ServiceRuntime", "Input", "Inbox", "TimedPublisher"]

log = logging.getLogger(__name__)


class ServiceRuntime(Cursors, Loop):
    """One service process's zenoh session and life cycle (use as a context manager)."""


    def __init__(self, service: str, stream: str, conf: zenoh.Config, stats_period_s: float = 1.0,
                 install_signals: bool = True, settings: str = "") -> None:
        """``settings``: the digest of the stabilizer settings the service runs with (in every stats
        message as ``settings``: a recording shows what each service ran with)."""
        self.service = service
        self.settings = settings
        self.stream = keys.check_stream(stream)
        self.stop = threading.Event()
        self.signals = 0  # SIGTERM/SIGINT received (a second one ends the waits of a stream's end)
        self._cond = threading.Condition()
        self._inboxes: list[Inbox] = []
        self._subs: list[Any] = []  # keep references: a dropped subscriber is undeclared
        self._pubs: list[Any] = []
        self._timed: list[TimedPublisher] = []
        self._stats_seq = 0
        self.errors: dict[str, int] = {}  # the runtime's counters: decode_errors, internal_errors (in the stats)
        self.stats_source: Callable[[], dict[str, Any]] | None = None  # the service's values (serve() sets it)
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
        self.signals += 1
        self.stop.set()
        with self._cond:
            self._cond.notify_all()

    # --- endpoints -------------------------------------------------------------------------------

    def publisher(self, stage: str, lossless: bool | None = None, stream: str | None = None,
                  cache: int = 0) -> TimedPublisher:
        """Publisher on ``quick/@v1/<stream>/<stage>``. Every publisher drops for a congested link
        instead of waiting for it (``CongestionControl.DROP``: at most zenoh's ``wait_before_drop``,
        1 ms, per link and message), so no subscriber, the pipeline's or a foreign viewer, can hold a
        publisher. ``lossless`` (flows, motions, corrections, frames, their end markers): an advanced
        publisher that numbers its messages, keeps at least ``RECOVERY_CACHE`` of them and sends a
        heartbeat, so a receiver whose own link dropped some fetches them back from the cache, in
        order (:meth:`inbox`); only what fell out of the cache is lost, and counted there. ``cache``
        > 0 also keeps the last ``cache`` messages for a restarted consumer's history query. Its puts
        are timed (:class:`TimedPublisher`, in the stats). ``lossless`` None: as the pipeline's table
        says (stream/topology.py: every data key)."""
        if lossless is None:
            lossless = stage in LOSSLESS_KEYS
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
              catch_up_s: float = 5.0, replays: ReplayFilter | None = None, keep_depth_mb: float = 0.0) -> Inbox:
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
        of its stage (:mod:`quick_stream.stream.arrivals`). ``replays``: messages received before, byte
        for byte, are dropped on arrival (:mod:`quick_stream.stream.replays`; the recorder's).
        ``keep_depth_mb``: the frames' depth streams the check decompressed are kept, up to this many
        MB, for the loop's decode of the same frames (the flow service's: each depth decompressed once,
        :meth:`.arrivals.ArrivalLedger.depth_of`)."""
        box = Inbox(capacity, self._cond, on_arrival, on_gap, replays)
        box.arrivals.keep_depth_bytes = int(keep_depth_mb * 2**20)
        box.skip_through = skip_through
        box.capacity = box.catch_up = max(capacity, catch_up)
        box.catch_up_until = time.monotonic() + catch_up_s if catch_up > capacity else 0.0
        if history and publisher is not None and self.wait_for([publisher], publisher_wait_s):
            log.warning("%s/%s: %s not seen after %.0f s; subscribing to %s with history all the same",
                        self.stream, self.service, publisher, publisher_wait_s, key_expr)
        # Recovery: messages of a lossless publisher (LOSSLESS_KEYS) that this session's link dropped
        # (congested: this process stopped reading for a while) are fetched back from the publisher's
        # cache and handed on in order; what the cache no longer holds is counted as ``lost``. Those
        # keys (every data key: stream/topology.py) get an advanced subscriber each; the others (stats) a
        # plain one: an advanced subscriber drops a message that is not numbered and whose timestamp is not
        # newer than the last one delivered from its session (zenoh-ext's timestamped path), so an
        # unnumbered key reordered while the router restarts would lose messages there. ``history``: a
        # publisher this session does not know yet (its declaration arrives after ours) is queried once seen.
        head, _, last = key_expr.rpartition("/")
        lossless = [key_expr] if last in LOSSLESS_KEYS else [f"{head}/{st}" for st in LOSSLESS_KEYS] if last == "*" else []
        for k in lossless:
            sub = zenoh.ext.declare_advanced_subscriber(
                self.session, k, box._on_sample,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True) if history else None,
                recovery=zenoh.ext.RecoveryConfig(heartbeat=True))
            self._subs.append(sub.sample_miss_listener(box._on_miss))
            self._subs.append(sub)
        if key_expr not in lossless:
            def others(sample: zenoh.Sample) -> None:
                if str(sample.key_expr).rpartition("/")[2] not in LOSSLESS_KEYS:
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

    def wait(self, timeout_s: float, inboxes: list[Inbox] | None = None) -> None:
        """Sleep until any inbox (of ``inboxes``, default all) has a message, a stop signal, or ``timeout_s``."""
        with self._cond:
            if self.stop.is_set() or any(len(b) for b in (self._inboxes if inboxes is None else inboxes)):
                return
            self._cond.wait(timeout_s)

    def ready(self) -> None:
        """Declare the liveliness token: call once the service's subscribers are declared, so
        whoever waits for it (capture's ``--wait-for``) cannot publish before they exist."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(keys.health_key(self.stream, self.service))


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

    def publish_stats(self, values: dict[str, Any] | None = None) -> None:
        """Publish a ``stats`` message now: ``values`` (default: the service's, ``stats_source()``; ``state``
        ``running`` unless they say otherwise) plus the runtime's counters and each publisher's and
        inbox's (drops, invalid, queued, lost, skipped)."""
        if values is None:
            values = self.stats_source() if self.stats_source is not None else {}
        vals = {"state": "running", **self.errors, **values}
        if self.settings:
            vals["settings"] = self.settings
        for p in self._timed:
            vals.update(p.take())
        for i, b in enumerate(self._inboxes):
            vals[f"inbox{i}_dropped"] = b.dropped
            vals[f"inbox{i}_dropped_foreign"] = b.dropped_foreign  # of them, not from the stream's own publisher
            vals[f"inbox{i}_invalid"] = b.arrivals.invalid  # failed the check on arrival (not accounted, not queued)
            vals[f"inbox{i}_ignored_ends"] = b.arrivals.ignored_ends  # not from the stream's publisher: not queued
            vals[f"inbox{i}_queued"] = len(b)
            vals[f"inbox{i}_lost"] = b.lost
            if b.skip_through is not None:
                vals[f"inbox{i}_skipped"] = b.skipped
        self._stats_pub.put(encode_stats(Stats(self.service, vals), self.stream, self._stats_seq))
        self._stats_seq += 1
        if self._stats_seq % TRIM_EVERY == 0:
            trim_heap()
        self._next_stats = time.monotonic() + self._stats_period

    def maybe_stats(self, values: Callable[[], dict[str, Any]] | None = None) -> None:
        """:meth:`publish_stats` if a stats period has passed (``values``: default the service's)."""
        if self.stats_due():
            self.publish_stats(values() if values is not None else None)

    def decode(self, key_expr: str, data: bytes, expect: tuple[str, ...], color: str = "bgr",
               checked: Decoded | None = None, pixels: bool = True, depth_raw: bytes | None = None,
               streams: bool = True) -> Decoded | None:
        """The message decoded (a frame's JPEG colour as ``color`` asks, :func:`~quick_stream.stream.wire.decode`;
        ``pixels=False``: every field checked, images and depth left undecoded), if it is one of the
        ``expect`` types and of this service's stream; otherwise None, logged (naming the key, field
        and problem) and counted in ``decode_errors``. ``checked``: the decode the inbox's check made
        of these very bytes when it decoded them whole (:attr:`.arrivals.ArrivalLedger.last`), taken
        instead of decoding them again; ``depth_raw``: a frame's depth stream that check decompressed
        (:meth:`.arrivals.ArrivalLedger.depth_of`), not decompressed again; ``streams=False`` (with
        ``pixels=False``): the depth's compressed stream left unchecked too (an inbox's message: its
        check on arrival decompressed it)."""
        try:
            msg = checked if checked is not None else decode(data, color=color, pixels=pixels, depth_raw=depth_raw,
                                                             streams=streams)
            if msg.stream != self.stream:
                raise WireError(f"message of stream {msg.stream!r} on the key of stream {self.stream!r}",
                                stream=msg.stream, seq=msg.seq, field="stream", type=msg.type)
        except WireError as e:
            self.count("decode_errors")
            log.error("%s message on %s rejected: %s", "/".join(expect), key_expr, e)
            return None
        if msg.type not in expect:
            self.count("decode_errors")
            log.error("unexpected %s message on %s", msg.type, key_expr)
            return None
        return msg

    def count(self, counter: str, n: int = 1) -> None:
        """Add ``n`` to one of the runtime's counters (in every stats message)."""
        self.errors[counter] = self.errors.get(counter, 0) + n

    def contained(self, what: str | Callable[[], str]) -> "_Contained":
        """Context for processing one message: an unexpected exception (a bug or an input no check
        foresaw) is logged with its traceback and counted in ``internal_errors``, and the
        service goes on with the next message: one bad frame never kills a stream. ``what`` names
        the message (a callable: asked only when an exception is logged)."""
        return _Contained(f"{self.stream}/{self.service}", what, self.errors)

    # --- shutdown --------------------------------------------------------------------------------------

    def close(self) -> None:
        """Undeclare everything and close the session, waiting at most ``SESSION_CLOSE_S``: a close that
        hangs (the router went away with a SIGKILLed ``up``) is logged and left behind
        (:func:`~quick_stream.stream.process.closed_late`), so the service still finishes its outputs."""
        entities = [*self._subs, *([self._token] if self._token is not None else []), *self._pubs]

        def undeclare_all() -> None:
            for e in entities:
                try:
                    e.undeclare()
                except zenoh.ZError:
                    pass  # already gone with a dying session: nothing left to release

        problem = close_within([undeclare_all, self.session.close], SESSION_CLOSE_S)
        self._subs.clear()
        self._pubs.clear()
        self._token = None
        if problem is not None:
            log.warning("%s/%s: closing the zenoh session: %s", self.stream, self.service, problem)
            if problem.startswith(CLOSE_TIMED_OUT):
                closed_late(problem)

    def __enter__(self) -> "ServiceRuntime":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class _Contained:
    def __init__(self, where: str, what: str | Callable[[], str], errors: dict[str, int]) -> None:
        self.where, self.what, self.errors = where, what, errors

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: type | None, exc: BaseException | None, _tb: Any) -> bool:
        if kind is None or not issubclass(kind, Exception):
            return False
        self.errors["internal_errors"] = self.errors.get("internal_errors", 0) + 1
        try:
            what = self.what() if callable(self.what) else self.what
        except Exception:  # noqa: BLE001 - a message too broken to be named is still contained
            what = "a message"
        log.error("%s: %s failed (%s: %s); skipped, the stream goes on", self.where, what, kind.__name__, exc,
                  exc_info=(kind, exc, _tb))
        return True

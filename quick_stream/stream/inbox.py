"""A service's inboxes and publishers: drop-oldest queues fed by zenoh subscribers, timed puts.

* **Inbox**: a callback subscriber that appends each payload to a bounded deque.
  When full it drops the *oldest* and counts it (zenoh's ``RingChannel`` drops
  silently; we report drops in the stats). A message is checked before it takes a slot
  (:func:`~quick_stream.stream.wire.check`: every field, the depth's compressed stream, the JPEG's
  header): one that fails, or an ``end`` not from the stream's own publisher
  (:meth:`~quick_stream.stream.arrivals.ArrivalLedger.end_refused`), is counted (``inbox<i>_invalid``,
  ``inbox<i>_ignored_ends``), said once per kind, and never queued, so it cannot push out a real one.
  A full queue drops the oldest message *not from its stream's own publisher* first (a foreign
  flood of valid messages sheds its own; ``inbox<i>_dropped_foreign``), else the oldest. Lossless
  inboxes are the same with a bound no healthy stream reaches. Every inbox recovers what its own link dropped
  from the lossless publishers' caches (zenoh-ext sample-miss recovery), in order;
  what the cache no longer held is counted (``inbox<i>_lost``).
* **Publishers never wait for a subscriber**: all of them drop for a congested link
  (``CongestionControl.DROP``), so a slow foreign subscriber, peer or client, can only
  slow itself; the pipeline's own lossless keys are numbered, cached and recovered
  (docs/deployment.md, "Delivery guarantees per key"). :class:`TimedPublisher` times each put.

Both are made by :class:`~quick_stream.stream.runtime.ServiceRuntime` (``inbox``, ``publisher``).
"""
from __future__ import annotations

import logging
import re
import threading
import time
from collections import deque
from typing import Any, Callable

import zenoh

from .arrivals import ArrivalLedger, Gap
from .replays import ReplayFilter

log = logging.getLogger(__name__)


class Inbox:
    """Bounded drop-oldest queue of (key, payload bytes, arrival ns) fed by a zenoh callback subscriber.

    It also keeps ``arrivals``: per (stream, stage) of the key the highest seq of the data
    messages that arrived since that stage's last ``end`` and the seqs skipped on the way
    (read from the envelope on arrival, so a busy service still answers cursor queries
    exactly; :class:`~quick_stream.stream.arrivals.ArrivalLedger`). ``on_gap`` hears each gap.
    ``replays``: a message received before, byte for byte (a restarted publisher sending again what
    its predecessor had sent), is dropped there, before anything accounts for it
    (:class:`~quick_stream.stream.replays.ReplayFilter`, which counts it)."""

    def __init__(self, capacity: int, cond: threading.Condition,
                 on_arrival: Callable[[str, bytes, int], None] | None = None,
                 on_gap: Callable[[Gap], None] | None = None, replays: ReplayFilter | None = None) -> None:
        self.capacity = self.base_capacity = self.catch_up = capacity
        self.catch_up_until = 0.0  # monotonic time before which a drained queue keeps the catch-up bound
        self.on_arrival = on_arrival
        self.on_gap = on_gap
        self.replays = replays
        self._q: deque[tuple[str, bytes, int, bool]] = deque()  # (key, payload, arrival time ns, foreign)
        self._foreign = 0  # queued messages not from their stream's own publisher: dropped first when full
        self._cond = cond
        self.dropped = 0
        self.dropped_foreign = 0  # of them, messages not from their stream's own publisher
        self.skipped = 0
        self.lost = 0  # messages of a lossless publisher that never arrived and were no longer in its cache
        self.skip_through: int | None = None  # data messages with a seq <= this are not queued (taken over)
        self._newest: int | None = None  # taking over: the newest data seq queued so far
        self._newest_pub: int | None = None  # taking over: the latest publication time queued so far (frames)
        self.arrivals = ArrivalLedger()
        self.refusals = RefusalLog()
        # the flow service's shedding (stream/gate.py): asked with the checked envelope (None: not valid)
        # before a message takes a slot (False: not queued, the asker counts it), told of each dropped for room
        self.admit: Callable[[str, bytes, tuple[str, int, int | None] | None], bool] | None = None
        self.on_drop: Callable[[str, bytes], None] | None = None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key, data = str(sample.key_expr), sample.payload.to_bytes()
        item = (key, data, time.time_ns())
        # Checked before any bookkeeping reads it (a malformed message's seq must not move the
        # ledger, the cursor or the skips) and before it takes a slot: one that fails is not queued.
        env = self.arrivals.checked(key, data)
        if env is not None and self.replays is not None and self.replays.replayed(key, env[0], env[1], data):
            return  # had already: neither accounted (no false renumbering), handed on nor queued
        source = publisher_of(sample)
        refused = None
        if env is None:
            e = self.arrivals.last_wire_error
            refused = (_kind(e), f"{key}: message refused on arrival: {e}")
        elif env[0] == "end" and (why := self.arrivals.end_refused(key, source, env[3])) is not None:
            refused = ("end", f"{key}: end of stream at {env[3]} ignored: {why} (docs/wire-format.md, "
                       "\"Who may end a stream\")")
        elif (gap := self.arrivals.account(key, *env[:3], source)) is not None and self.on_gap is not None:
            self.on_gap(gap)
        if self.on_arrival is not None:
            self.on_arrival(*item)  # every message as it arrived (the recorder records them all)
        if refused is not None:
            self.refusals.add(*refused)
            return
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
        if self.admit is not None and not self.admit(key, data, env[:3]):
            return
        foreign = self.arrivals.foreign(key, source)
        gone_item = None  # a message the full queue dropped (this one or a queued one): told to on_drop
        with self._cond:
            if len(self._q) >= self.capacity:
                # full: the oldest message not from its stream's own publisher goes first (a foreign flood,
                # valid messages or not, sheds its own, never the stream's), then this one if it is such a
                # message, else the oldest
                self.dropped += 1
                if not self._foreign and foreign:
                    self.dropped_foreign += 1
                    gone_item = item
                else:
                    i = next(j for j, it in enumerate(self._q) if it[3]) if self._foreign else 0
                    gone_item = self._q[i]
                    gone = gone_item[3]
                    del self._q[i]
                    self._foreign -= gone
                    self.dropped_foreign += gone
            if gone_item is not item:
                self._q.append((*item, foreign))
                self._foreign += foreign
                self._cond.notify_all()
        if gone_item is not None and self.on_drop is not None:
            self.on_drop(gone_item[0], gone_item[1])

    def _on_miss(self, miss: Any) -> None:
        self.lost += miss.nb
        log.warning("%d messages of publisher %s were lost (no longer in its cache)", miss.nb, miss.source)

    def pop(self) -> tuple[str, bytes, int] | None:
        with self._cond:
            if not self._q:
                return None
            *item, foreign = self._q.popleft()
            self._foreign -= foreign
            if not self._q and self.capacity != self.base_capacity and time.monotonic() >= self.catch_up_until:
                self.capacity = self.base_capacity  # caught up: back to the live bound
            return tuple(item)  # type: ignore[return-value]

    def __len__(self) -> int:
        return len(self._q)


def publisher_of(sample: Any) -> str | None:
    """Who published ``sample``: the zenoh session id its source info gives (an advanced publisher's; the
    capture's frames and end marker share it), else its timestamp's (every session of ours stamps), both
    when they disagree (a source info copied from another's sample); None when it says nothing. What a
    sender asserts, not an authenticated identity: docs/wire-format.md, "Who may end a stream"."""
    info, stamp = getattr(sample, "source_info", None), getattr(sample, "timestamp", None)
    src = str(info.source_id.zid) if info is not None else None
    ts = str(stamp.get_id()) if stamp is not None else None
    return src if ts is None or src == ts else ts if src is None else f"{src} (stamped by {ts})"


def _kind(e: Exception | None) -> str:
    """What kind of refusal ``e`` is, for saying each kind once: its type, field and problem, numbers left out."""
    if e is None:
        return "?"
    problem = re.sub(r"\d+", "N", str(getattr(e, "problem", e)).split(":")[0])[:60]
    return f"{getattr(e, 'type', None)}/{getattr(e, 'field', None)}/{problem}"


class RefusalLog:
    """Messages an inbox refused: each kind said in full once (the first of it), the rest counted and
    summed up at most every ``every_s`` seconds (a flood of forged messages must not bury the log)."""

    MAX_KINDS = 256  # kinds remembered; beyond them every refusal is only counted

    def __init__(self, every_s: float = 10.0) -> None:
        self.every_s = every_s
        self.kinds: set[str] = set()
        self.unsaid = 0
        self._next = 0.0

    def add(self, kind: str, text: str) -> None:
        if kind not in self.kinds and len(self.kinds) < self.MAX_KINDS:
            self.kinds.add(kind)
            log.error("%s", text)
            return
        self.unsaid += 1
        now = time.monotonic()
        if now >= self._next:
            log.error("%d more messages refused on arrival, of kinds already said (the latest: %s)", self.unsaid, text)
            self.unsaid, self._next = 0, now + self.every_s


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

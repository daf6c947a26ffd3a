"""Taking over mid-stream: the cursor every service answers and asks (a part of
:class:`~quick_stream.stream.runtime.ServiceRuntime`).

Every service answers *cursor* queries (``quick/@v1/<stream>/cursor/<service>``) with the newest
seq per stage it has received in the stream under way; a service restarted mid-stream asks how far
its predecessor's output got (:meth:`Cursors.stream_cursor`) and subscribes to its inputs with
history. A publisher asks before it ends a stream (:meth:`Cursors.lagging`) and after
(:meth:`Cursors.until_ended`), so what it put last is not left in flight (docs/architecture.md).
"""
from __future__ import annotations

import logging
import os
import threading
import time
from typing import Any, Callable, Iterator

import zenoh

from . import keys
from .inbox import Inbox
from .wire import Stats, WireError, decode, encode_stats

# Set by the supervisor (quick_stream/stream/launcher.py) for a service it restarted: how many times.
RESTARTED_ENV = "QUICK_STREAM_RESTARTED"

log = logging.getLogger(__name__)


class Cursors:
    """The cursor queries of a service's runtime: a mixin of
    :class:`~quick_stream.stream.runtime.ServiceRuntime`, which provides the session, the stream,
    the service's name, its inboxes, the stop event and :meth:`alive`."""

    session: zenoh.Session
    stream: str
    service: str
    stop: threading.Event
    _inboxes: list[Inbox]
    _subs: list[Any]

    def alive(self, stream: str | None = None) -> set[str]:
        raise NotImplementedError

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

    def take_over(self, output: str, inputs: str, log: logging.Logger) -> int | None:
        """Where this service starts in a stream under way: the newest ``output`` seq any running
        service received (:meth:`stream_cursor`; None: a new stream, start from its first message),
        said in ``log`` with the ``inputs`` whose history the service reads from there."""
        after = self.stream_cursor(output)
        if after is not None:
            log.warning("stream %s under way (%s out up to frame %d): taking over from the %s' history",
                        self.stream, output, after, inputs)
        return after

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

    def lagging(self, stage: str, seq: int, timeout_s: float, required: frozenset[str] = frozenset(),
                interrupted: Callable[[], bool] | None = None) -> set[str]:
        """Wait until every service that has received ``stage`` of this stream, and every service in
        ``required`` (received or not), reports ``seq`` or a newer one (its inbox's arrivals,
        :meth:`serve_cursor`), or ``timeout_s`` passes; returns the services still behind (empty:
        delivered). A publisher asks before it ends the stream and closes, so what it put last is not
        left in flight, and after its first message, so every consumer has its start (a receiver
        recovers a message its link dropped only after the first one it got from that publisher).
        ``interrupted()``: True ends the wait early (default: the stop event; a publisher ending its
        stream because it was stopped still waits, until a second signal)."""
        deadline = time.monotonic() + timeout_s
        interrupted = interrupted or self.stop.is_set
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
            if not behind or time.monotonic() > deadline or interrupted():
                return behind
            time.sleep(0.05)

    def until_ended(self, stage: str, timeout_s: float, interrupted: Callable[[], bool] | None = None) -> set[str]:
        """After this publisher's ``end`` of ``stage``: wait until no running service of the stream
        reports ``stage`` in its cursor any more (a receiver's arrival ledger closes the stage on the
        ``end``), or ``timeout_s`` passes; returns the services still reporting it. The publisher's
        cache closes with its session, so a receiver whose link dropped the ``end`` for congestion
        can recover it only while the publisher waits here. ``interrupted``: as :meth:`lagging`'s."""
        deadline = time.monotonic() + timeout_s
        interrupted = interrupted or self.stop.is_set
        while True:
            still = {service for service, values in self._cursor_answers() if stage in values}
            if not still or time.monotonic() > deadline or interrupted():
                return still
            time.sleep(0.05)

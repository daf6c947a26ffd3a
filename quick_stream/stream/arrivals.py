"""Which seqs of each stage never arrived: a receiver's view of loss anywhere upstream.

Every stage numbers its messages with the frame's seq, so a receiver that sees seq 229
follow 208 knows 209-228 did not reach it: dropped by a stage that says so in its own
stats (render's ``dropped``, flow's ``refused_frames``), or lost without a word (a
transport that drops under congestion: zenoh's ``CongestionControl.DROP`` gives up on a
message after ``wait_before_drop``; a publisher killed mid-send). The recorder keeps this
account of everything it records, so no loss is silent (docs/reliability.md).

A seq that arrives late (after a higher one) fills its gap again. The missing seqs of a
stage are remembered up to ``window`` behind its newest; older ones are final.

A stage whose numbering restarts lower (a camera or capture restarted without the stream's
cursor) is followed once a run of seqs confirms it, as the stages confirm it
(:class:`~quick_stream.core.continuity.JumpGuard`: ``resync`` consecutive seqs at or behind the newest,
none of them filling a gap, each following the previous by 1..``step``; a frame published before
the newest one, a history replay, never counts): the stage's newest becomes the run's last seq,
the run's seqs are taken back from ``duplicates``, the gaps inside the run are counted, the old
numbering's missing seqs are final (``renumberings``; logged). So the cursor a restarted service
resumes from follows the new numbering, and the new numbering is not a flood of duplicates.

Only messages that pass :func:`quick_stream.stream.wire.check` are accounted (every field valid, the
envelope's stream and type those of the key it came on): one malformed message with a huge seq
must not move a stage's newest seq, which restarted services resume from (the stream cursor).

An ``end`` closes a stage's stream only when it comes from the stream's own publisher
(:meth:`ArrivalLedger.end_refused`, docs/wire-format.md "Who may end a stream"): the publisher whose
message last moved the stage's newest seq (``source``, the zenoh session that published it), with a
``last_seq`` not behind that newest seq; with nothing under way on the key, any ``end`` is harmless.
"""
from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass, field

from ..core.continuity import JumpGuard, published_after
from . import keys
from .wire import Decoded, WireError, check

log = logging.getLogger(__name__)

# Message types the check decodes whole (they carry no image or depth): its result is the message decoded.
WHOLE_WHEN_CHECKED = ("flow", "motion", "correction", "end", "stats")


@dataclass
class _Stage:
    newest: int = -1
    first: int = -1  # the first seq accounted (or seeded)
    missing: set[int] = field(default_factory=set)
    unreceived: int = 0  # seqs skipped and not (yet) filled: the stage's count
    jumps: JumpGuard = field(default_factory=JumpGuard)  # a far-future or lower seq moves nothing until confirmed
    newest_pub: int | None = None  # when the newest was published (frames carry it), None: unknown
    owner: str | None = None  # the publisher (zenoh session id) whose message last moved ``newest``
    owned: bool = True  # False: seeded (a predecessor's account), no message of the stream seen yet


@dataclass
class Gap:
    """Seqs ``first``..``last`` of ``stage`` in ``stream`` skipped by the message that just arrived."""

    stream: str
    stage: str
    first: int
    last: int

    @property
    def count(self) -> int:
        return self.last - self.first + 1


class ArrivalLedger:
    """Per (stream, stage): the newest seq received and the seqs skipped on the way."""

    def __init__(self, window: int = 4096) -> None:
        self.window = window
        self._stages: dict[tuple[str, str], _Stage] = {}
        self._ended: dict[str, int] = {}  # unreceived of stages whose stream ended, per stage
        self.late = 0  # arrived after a higher seq (filled a gap)
        self.duplicates = 0  # arrived again (a restarted publisher republishing, a replay)
        self.invalid = 0  # failed the check: not accounted
        self.jumps = 0  # far ahead of the stage's newest and not (yet) confirmed by a run: not accounted
        self.renumberings = 0  # a stage's numbering went back, confirmed by a run: followed
        self.ignored_ends = 0  # ends not from the stream's own publisher, or behind what it sent: not honoured
        self.last_error: str | None = None  # why the newest invalid one failed
        self.last_wire_error: Exception | None = None  # and its error
        # the newest message checked whole (WHOLE_WHEN_CHECKED) and its decode, for its consumer to reuse
        # (a flow's decode costs 0.4-0.7 ms): (payload, decoded), the payload the very bytes object checked
        self.last: tuple[bytes, Decoded] | None = None
        # checked frames' depth streams, decompressed by the check, for their decode (:meth:`depth_of`):
        # payload id -> (payload, raw), the oldest forgotten beyond ``keep_depth_bytes`` (0: none kept)
        self.keep_depth_bytes = 0
        self._depths: OrderedDict[int, tuple[bytes, bytes]] = OrderedDict()
        self._depth_bytes = 0
        self._depth_lock = threading.Lock()  # kept in zenoh's threads, taken in the service's

    def checked(self, key_expr: str, payload: bytes) -> tuple[str, int, int | None, int | None] | None:
        """(type, seq, publication time ns or None, an end's ``last_seq`` or None) of a message that
        passes :func:`~quick_stream.stream.wire.check` on its key (a frame's ``pub_ns``); None (counted
        in ``invalid``, the reason in ``last_error``, the error in ``last_wire_error``) for one that does not."""
        try:
            stream, stage = keys.parse(key_expr)
            d = check(payload, stream, stage)
        except (ValueError, WireError) as e:
            self.invalid += 1
            self.last_error = f"{key_expr}: {e}"
            self.last_wire_error = e
            return None
        if d.type in WHOLE_WHEN_CHECKED:
            self.last = (payload, d)
        elif d.depth_raw is not None and self.keep_depth_bytes > 0:
            self._keep_depth(payload, d.depth_raw)
        return d.type, d.seq, d.pub_ns, d.obj.seq if d.type == "end" else None

    def _keep_depth(self, payload: bytes, raw: bytes) -> None:
        with self._depth_lock:
            old = self._depths.pop(id(payload), None)
            self._depth_bytes += len(raw) - (len(old[1]) if old is not None else 0)
            self._depths[id(payload)] = (payload, raw)  # the payload held: its id is not reused meanwhile
            while self._depth_bytes > self.keep_depth_bytes and self._depths:
                self._depth_bytes -= len(self._depths.popitem(last=False)[1][1])

    def depth_of(self, payload: bytes) -> bytes | None:
        """The depth stream the check of this very bytes object decompressed (forgotten here), if still
        kept (``keep_depth_bytes``): its decode need not decompress it again (the flow service's,
        :meth:`~quick_stream.stream.loop.Loop.handle`)."""
        if not self._depths:
            return None
        with self._depth_lock:
            kept = self._depths.pop(id(payload), None)
            if kept is None:
                return None
            self._depth_bytes -= len(kept[1])
        return kept[1] if kept[0] is payload else None

    def add(self, key_expr: str, payload: bytes) -> Gap | None:
        """Check and account one message on ``quick/@v1/<stream>/<stage>``; the gap it reveals, if any."""
        env = self.checked(key_expr, payload)
        return None if env is None else self.account(key_expr, *env[:3])

    def account(self, key_expr: str, mtype: str, seq: int, pub_ns: int | None = None,
                source: str | None = None) -> Gap | None:
        """Account a checked message (:meth:`checked`; ``pub_ns``: when it was published, if known;
        ``source``: who published it, the zenoh session's id if known); the gap it reveals, if any.
        Stats and health (numbered on their own) are not counted; an ``end`` (one :meth:`end_refused`
        lets through) closes the stage's stream (a new one may start again from 0)."""
        if mtype in ("stats", "health"):
            return None
        where = tuple(key_expr.rsplit("/", 2)[-2:])
        st = self._stages.setdefault(where, _Stage())  # type: ignore[arg-type]
        if mtype == "end":  # its seq is the stream's last frame, not the stage's last (a flow is
            # numbered by its pair's first frame): it says nothing about the stage's own seqs
            ended = self._stages.pop(where)
            if ended.unreceived:
                self._ended[where[1]] = self._ended.get(where[1], 0) + ended.unreceived
            return None
        if st.newest < 0:  # the first message of this stage we see: nothing before it is ours to miss
            st.newest = st.first = seq
            st.newest_pub, st.owner = pub_ns, source
            return None
        if seq > st.newest and not st.jumps.admit(st.newest, seq):
            self.jumps += 1  # one far-future seq (a glitch, a stray publisher) is not the stage's newest
            return None
        if seq > st.newest:
            gap = None
            if seq > st.newest + 1:
                gap = Gap(where[0], where[1], st.newest + 1, seq - 1)
                st.missing.update(range(max(st.newest + 1, seq - self.window), seq))
                st.unreceived += gap.count
            st.newest = seq
            st.newest_pub, st.owner, st.owned = pub_ns, source, True
            if len(st.missing) > self.window:
                st.missing = {s for s in st.missing if s > seq - self.window}
            return gap
        if seq in st.missing:
            st.missing.discard(seq)
            st.unreceived -= 1
            self.late += 1
            return None
        self.duplicates += 1
        if st.jumps.renumbered(seq, published_after(pub_ns, st.newest_pub)):
            self._renumber(where, st, pub_ns)
            st.owner, st.owned = source, True
        return None

    def foreign(self, key_expr: str, source: str | None) -> bool:
        """Whether a message on ``key_expr`` from ``source`` is not from the stream's own publisher (the one
        whose message last moved the stage's newest seq; False with nothing under way)."""
        st = self._stages.get(tuple(key_expr.rsplit("/", 2)[-2:]))  # type: ignore[arg-type]
        return st is not None and st.owned and source != st.owner

    def end_refused(self, key_expr: str, source: str | None, last_seq: int) -> str | None:
        """Why an ``end`` on ``key_expr`` from ``source`` (the zenoh session that published it) ending at
        ``last_seq`` is not honoured (counted in ``ignored_ends``), or None when it is: with a stream under
        way on the key it must come from the stream's own publisher, the one whose message last moved the
        stage's newest seq, and not end behind that seq; with nothing under way there is nothing to cut."""
        st = self._stages.get(tuple(key_expr.rsplit("/", 2)[-2:]))  # type: ignore[arg-type]
        if st is None or not st.owned:
            return None
        if source != st.owner:
            why = (f"from {source or 'a publisher that does not say who it is'}, not from the stream's publisher "
                   f"{st.owner or '(one that does not say who it is)'}")
        elif last_seq < st.newest:
            why = f"ends at {last_seq}, behind the newest message received ({st.newest})"
        else:
            return None
        self.ignored_ends += 1
        return why

    def _renumber(self, where: tuple[str, str], st: _Stage, pub_ns: int | None) -> None:
        """Follow a stage's confirmed new numbering: its run (:attr:`JumpGuard.run`) was counted as
        duplicates; it is the new numbering's start, with what is missing inside it."""
        run = st.jumps.run
        self.renumberings += 1
        self.duplicates -= len(run)
        log.warning("%s/%s: the numbering restarts at seq %d (after %d; confirmed by %d in a row): followed",
                    where[0], where[1], run[0], st.newest, len(run))
        st.missing = set()  # the old numbering's: final
        for a, b in zip(run, run[1:]):
            st.missing.update(range(a + 1, b))
        st.unreceived += len(st.missing)
        st.newest, st.first, st.newest_pub = run[-1], run[0], pub_ns

    def seed(self, stream: str, stage: str, newest: int) -> Gap | None:
        """Start a stage's account at ``newest`` as if it had been received (a restarted recorder
        continuing its predecessor's account): the next message reveals what came in between. If
        messages of the stage already arrived, the hole before the first of them is returned."""
        where = (stream, stage)
        st = self._stages.get(where)
        if st is None:
            self._stages[where] = _Stage(newest=int(newest), first=int(newest), owned=False)
            return None
        if st.first <= newest + 1:
            return None
        gap = Gap(stream, stage, newest + 1, st.first - 1)
        st.unreceived += gap.count
        st.first = int(newest)
        return gap

    def newest(self) -> dict[tuple[str, str], int]:
        """Per (stream, stage): the highest seq received since that stage's last ``end``."""
        return {where: st.newest for where, st in list(self._stages.items())}

    def unreceived(self) -> dict[str, int]:
        """Seqs never received, summed over streams, per stage (stages without any omitted)."""
        out = dict(self._ended)
        for (_, stage), st in list(self._stages.items()):  # zenoh's thread may be adding
            if st.unreceived:
                out[stage] = out.get(stage, 0) + st.unreceived
        return out

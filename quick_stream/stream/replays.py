"""Messages a receiver already has, arriving again: told apart from new ones by their bytes.

A restarted publisher may publish again what its predecessor had published: a restarted motion
service resumes after the newest *correction* (its resume cursor, docs/reliability.md), so the
motions its predecessor had published beyond that one (20-odd, a planning window) go out again,
byte for byte the same. To an arrival ledger they are seqs behind the newest, and 15 in a row
looked like a stage whose numbering restarted (a false "renumbering"); a recorder stored each
twice.

:class:`ReplayFilter` says which messages are *replays*: same key (stream and stage), same seq
and the same bytes as one received before. Those are counted (``replays``) and dropped before
anything accounts for them. Same key and seq with *different* bytes is a conflict: both are real
publications (a stage whose numbering restarted, a restarted publisher that computed something
else, a second publisher), so both are kept, counted (``conflicts``) and logged
(docs/recording.md, "Replays and conflicts").

Bounded: per key the ``window`` most recently received seqs, each with at most ``per_seq`` digests
(BLAKE2b, 16 bytes), and at most ``keys`` keys (the least recently used is forgotten). A replay
older than the window is not recognised (it is then what it was before: a duplicate to the
ledger, stored again). ``stats`` and ``health`` (numbered on their own, not data) pass unchecked;
an ``end`` starts its key afresh (a new stream may number from 0 again, and its messages may be the
same bytes as the last stream's: a deterministic source), and the same ``end`` again before any
other message on its key is a replay too.
"""
from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections import OrderedDict

log = logging.getLogger(__name__)

UNCHECKED = ("stats", "health")
WINDOW = 512  # seqs remembered per key: 17 s at 30 frames/s, beyond any restart's republishing
KEYS = 128  # keys remembered (5 data stages per stream: 25 streams); ~0.1 MB each when full
PER_SEQ = 4  # digests remembered per seq (conflicts beyond that forget the oldest)


def digest(payload: bytes) -> bytes:
    """The 16-byte BLAKE2b digest that identifies a message's bytes."""
    return hashlib.blake2b(payload, digest_size=16).digest()


class ReplayFilter:
    """Which arriving messages are byte-for-byte replays of ones received before (module doc).

    Thread-safe: zenoh may deliver the messages of different publishers from different threads."""

    def __init__(self, window: int = WINDOW, keys: int = KEYS, per_seq: int = PER_SEQ) -> None:
        if window < 1 or keys < 1 or per_seq < 1:
            raise ValueError(f"window, keys and per_seq must be >= 1, got {window}, {keys}, {per_seq}")
        self.window, self.keys, self.per_seq = window, keys, per_seq
        self._seen: OrderedDict[str, OrderedDict[int, tuple[bytes, ...]]] = OrderedDict()  # key -> seq -> digests
        self._ended: dict[str, bytes] = {}  # key -> the digest of its last end, until a message follows
        self._lock = threading.Lock()
        self.replays = 0  # dropped: same key, seq and bytes as a message received before
        self.conflicts = 0  # kept: same key and seq as one received before, other bytes
        self._logged: dict[tuple[str, bool], float] = {}  # (key, conflict) -> when last logged

    def replayed(self, key_expr: str, mtype: str, seq: int, payload: bytes) -> bool:
        """Whether this message (checked: its envelope's ``mtype`` and ``seq``) was received before,
        byte for byte; if not, it is remembered. A conflict (same seq, other bytes) is False, logged."""
        if mtype in UNCHECKED:
            return False
        d = digest(payload)
        with self._lock:
            if mtype == "end":
                if d != self._ended.get(key_expr):
                    # the stream ends: what follows on this key may be a new stream numbered from 0 again
                    self._seen.pop(key_expr, None)
                    self._ended.pop(key_expr, None)
                    self._ended[key_expr] = d
                    while len(self._ended) > self.keys:
                        self._ended.pop(next(iter(self._ended)))
                    return False
                self.replays += 1
                n, conflict = self.replays, False
            else:
                n, conflict = self._data(key_expr, seq, d)
                if n == 0:
                    return False
        self._say(key_expr, seq, mtype, n, conflict)
        return not conflict

    def _data(self, key_expr: str, seq: int, d: bytes) -> tuple[int, bool]:
        """(0, False) for a message new to its key, else the count so far and whether it conflicts."""
        seen = self._seen.get(key_expr)
        if seen is None:
            seen = self._seen[key_expr] = OrderedDict()
            while len(self._seen) > self.keys:
                self._seen.popitem(last=False)
        self._seen.move_to_end(key_expr)
        before = seen.get(seq)
        if before is None:
            seen[seq] = (d,)
            if len(seen) > self.window:
                seen.popitem(last=False)
            self._ended.pop(key_expr, None)  # a message after the end: its replay is no longer the last
            return 0, False
        if d in before:
            self.replays += 1
            return self.replays, False
        seen[seq] = (*before, d)[-self.per_seq:]
        self.conflicts += 1
        return self.conflicts, True

    def _say(self, key_expr: str, seq: int, mtype: str, n: int, conflict: bool) -> None:
        """Log a replay or a conflict: the first of a key, then at most one line per key and second."""
        now = time.monotonic()
        if now - self._logged.get((key_expr, conflict), -1e9) < 1.0:
            return
        if len(self._logged) > 2 * self.keys:
            self._logged.clear()  # bounded like the rest (a flood of stream names)
        self._logged[(key_expr, conflict)] = now
        where = "/".join(key_expr.rsplit("/", 2)[-2:])
        if conflict:
            log.warning("%s: %s seq %d arrived again with different bytes (%d such so far): a stage whose "
                        "numbering restarted, a restarted publisher that made something else, or a second "
                        "publisher; both are kept", where, mtype, seq, n)
        else:
            log.info("%s: %s seq %d arrived again, byte for byte (%d such so far: a restarted publisher "
                     "sending again what its predecessor had sent, or a repeat); kept once", where, mtype, seq, n)


__all__ = ["ReplayFilter", "digest"]

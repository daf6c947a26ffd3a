"""What a recorder has on disk, for its successor: the side file ``<output>.recorded.json``.

A killed recorder's successor continues its account (docs/reliability.md, "Faults"): per stream
and stage, the newest seq its predecessor had *on disk*; everything after that one up to the
first message the successor receives is a hole it logs and counts. So the side file must never
claim a message that a kill could still take: a message is counted once a flush wrote it out
(the MCAP writer keeps the open chunk in memory), never when it arrived. Claiming what had arrived
lost messages silently: with the side file written after a flush from the arrival ledger, a
message that arrived after the flush (or whose image record the flush took and whose wire record
it did not) was in no file and outside the hole its successor logged (in 5 of 10 SIGKILLed
recorders, docs/reliability.md).

:class:`OnDisk` keeps that account for the recorder: :meth:`OnDisk.wrote` as each wire message
is written (all its records), :meth:`OnDisk.flushed_now` once a flush (or a finished file) put
everything written so far on disk; :func:`save_recorded` right after that flush, and once at the
start (a recorder killed before its first flush passes its predecessor's account on, and its
successor knows it was killed). A kill between the flush and the side file leaves the previous
side file: the hole its successor logs is then larger than what was lost (it names messages that
are in the file), never smaller. A stage the side file does not name had nothing on disk: its
seqs before the successor's first one of it are the hole.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

Where = tuple[str, str]  # (stream, stage)


class OnDisk:
    """Per (stream, stage): the newest seq on disk (module doc). Not thread-safe: the recorder's lock."""

    def __init__(self, flushed: dict[Where, int] | None = None) -> None:
        """``flushed``: a killed predecessor's account (its side file), carried on until this
        recorder's own flushes move it (killed before its first flush, its successor still knows it)."""
        self.flushed: dict[Where, int] = dict(flushed or {})  # what the side file says
        self._written: dict[Where, int | None] = {}  # since the last flush; None: the stage's stream ended

    def wrote(self, where: Where, mtype: str, seq: int, newest: int | None) -> None:
        """Every record of a wire message of ``where`` is written (not yet flushed). ``newest``: the
        stage's newest seq by the receiver's arrival ledger, which decides what counts: the message
        moves the account only if it is that newest (not a late one, a refused far-future seq, a
        message that failed the check, a stats message); an ``end`` closes the stage's account."""
        if mtype == "end":
            self._written[where] = None
        elif newest is not None and seq == newest:
            self._written[where] = seq

    def flushed_now(self) -> None:
        """Everything written so far is on disk (a flush, or a finished file)."""
        for where, seq in self._written.items():
            if seq is None:
                self.flushed.pop(where, None)
            else:
                self.flushed[where] = seq
        self._written.clear()


def recorded_path(output: str | os.PathLike) -> Path:
    """The side file where a recorder keeps, per stream and stage, the newest seq it has on disk."""
    return Path(f"{output}.recorded.json")


def save_recorded(output: str | os.PathLike, newest: dict[Where, int]) -> None:
    """Write the side file atomically (a kill leaves the previous one, never half of one)."""
    p = recorded_path(output)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps({"time": time.time(), "newest": [[s, g, n] for (s, g), n in newest.items()]}))
    tmp.replace(p)


def load_recorded(output: str | os.PathLike, max_age_s: float = 60.0) -> dict[Where, int] | None:
    """What a killed predecessor had on disk, if it wrote the side file within ``max_age_s`` (an
    older one belongs to another run; a running recorder rewrites it at every flush); None when there
    is no such predecessor. A damaged file counts as none."""
    p = recorded_path(output)
    try:
        doc = json.loads(p.read_text())
        if time.time() - float(doc["time"]) > max_age_s:
            return None
        return {(str(s), str(g)): int(n) for s, g, n in doc["newest"]}
    except (OSError, ValueError, KeyError, TypeError):
        return None


__all__ = ["OnDisk", "load_recorded", "recorded_path", "save_recorded"]

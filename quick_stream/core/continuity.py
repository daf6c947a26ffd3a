"""Stream continuity: which frames scene flow takes, and between which of them it may bridge.

A live camera or a recording delivers holes and discontinuities: frames with no valid
depth, repeated or late sequence numbers, missing frames, timestamps that jump or go
back (a restarted camera or capture), a resolution or calibration change. The flow
stage asks :class:`ContinuityCheck` about every frame against the previous good one:

* **refused** (``FrameRefused``, a ValueError naming the frame and the problem): the
  frame fails :meth:`RGBDFrame.validate` (no valid depth pixel, bad intrinsics), or its
  seq is not after the previous frame's (duplicate, out of order; but see *renumbering*).
  The chain goes on from the previous good frame.
* **break**: flow is not computed across a seq gap of more than ``max_missing`` frames
  spanning more than ``max_bridge_s`` of capture time (a fast camera whose frames were shed
  upstream is bridged by time: 4 missing frames at 30 fps, more at 120 fps), a capture-time gap
  over ``max_gap_s`` or not forward, or a change of image size;
  the flow stage emits an empty flow naming the reason, so the motion is invalid, the
  path restarts at that frame and the frames are flagged (docs/architecture.md, "Holes and bad
  frames in a stream").
* **jumps**: a seq more than ``max_jump`` frames ahead of the previous good frame is refused
  unless ``confirm`` such frames in a row, each following the last, confirm a new numbering
  (then it is a break): one message with a far-future seq (a glitch, a stray publisher) must
  not make every later frame look out of order and halt the stream (:class:`JumpGuard`). The motion
  stage's flows and the render stage's corrections far ahead are held the same way until such a run
  confirms them, then taken whole (:class:`AheadHold`).
* **renumbering**: a seq at or behind the previous good frame's is refused, unless ``resync``
  such frames in a row, each following the last, confirm that the numbering went back (a camera
  or capture restarted without the stream's cursor): then it is a break, counted in
  ``renumberings``. Without this every later frame of a stream numbered from 0 again would be
  refused as out of order and the stream would halt for good (:class:`JumpGuard`).
* **notes**: repaired depth (non-finite values set invalid) and changed intrinsics
  (flow lifts each frame with its own, so it still bridges) are reported, not fatal.

Every case is counted in :attr:`ContinuityCheck.counts` (the flow service's stats).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from .frame import FrameError, RGBDFrame

COUNTERS = ("invalid_frames", "repaired_frames", "duplicate_frames", "out_of_order_frames", "missing_frames",
            "seq_gaps", "seq_jumps", "renumberings", "timestamp_jumps", "size_changes", "intrinsics_changes",
            "breaks")

# Names a confirmed renumbering in the break a stage reports (the flow's ``problem``, so the motion's
# reason and the restart correction's ``reason``): how the render stage tells, from the correction
# stream alone, where the new numbering's corrections begin (:func:`restarts_numbering`).
RENUMBERED = "the stream's numbering restarts"
# Ends every break's reason: the flow does not bridge it, so no motion across it may be guessed either
# (the motion stage's constant-velocity bridge leaves it to the path's restart, docs/method.md 2.4).
BREAK = "no scene flow across it, the path restarts"


class FrameRefused(ValueError):
    """The flow stage will not use this frame; the message names the frame and why."""


@dataclass
class ContinuityParams:
    """Limits beyond which scene flow does not bridge two frames."""

    max_missing: int = 4  # frames missing between two frames that flow still bridges
    max_bridge_s: float = 0.17  # ... or more, if they span at most this much capture time (5 frames at 30 fps)
    max_gap_s: float = 0.5  # capture time between two frames that flow still bridges
    max_jump: int = 300  # a seq further ahead than this (10 s at 30 fps) needs confirming (JumpGuard)
    confirm: int = 5  # consecutive frames of a new numbering that confirm a jump
    resync: int = 15  # consecutive frames behind the previous good one that confirm a renumbering (0.5 s at 30 fps)

    def validate(self) -> None:
        if self.max_missing < 0:
            raise ValueError(f"max_missing must be >= 0, got {self.max_missing}")
        if self.max_jump <= self.max_missing or self.confirm < 2:
            raise ValueError(f"max_jump must be > max_missing and confirm >= 2, got {self.max_jump}, {self.confirm}")
        if self.resync < 2:
            raise ValueError(f"resync must be >= 2, got {self.resync}")
        if not (math.isfinite(self.max_gap_s) and self.max_gap_s > 0):
            raise ValueError(f"max_gap_s must be a finite number > 0, got {self.max_gap_s}")
        if not (math.isfinite(self.max_bridge_s) and 0 <= self.max_bridge_s <= self.max_gap_s):
            raise ValueError(f"max_bridge_s must be in [0, max_gap_s], got {self.max_bridge_s}")


@dataclass
class Verdict:
    """What the check says of one frame: ``brk`` (why flow must not bridge to it, or "") and ``notes``."""

    brk: str = ""
    notes: list[str] = field(default_factory=list)


def published_after(pub_ns: int | None, newest_pub_ns: int | None) -> bool:
    """Whether a message may be newer than the newest one accepted, by the wall-clock time its
    publisher stamped (a frame's ``pub_ns``): False only when both stamps are known and ``pub_ns``
    is not later. Such a message is a replay (a publisher's history cache answering a restarted
    service, delivered after live ones), never the start of a new numbering."""
    return pub_ns is None or newest_pub_ns is None or pub_ns > newest_pub_ns


def restarts_numbering(reason: str) -> bool:
    """Whether a break's ``reason`` (a flow's ``problem``, a correction's ``reason``) is a confirmed
    renumbering (:data:`RENUMBERED`)."""
    return RENUMBERED in reason


def breaks_stream(problem: str) -> bool:
    """Whether a flow's ``problem`` is a discontinuity the flow does not bridge (:data:`BREAK`)."""
    return BREAK in problem


def starts_numbering(c) -> bool:
    """Whether correction ``c`` is the restart correction of a renumbering's break: marked a restart
    (``motion`` "restart", docs/method.md 4.4; before that, an invalid correction) with the reason naming
    the renumbering."""
    return (c.motion == "restart" or not c.valid) and restarts_numbering(c.reason)


class JumpGuard:
    """Decides when a seq far ahead of, or at or behind, the newest accepted one starts a new numbering.

    Both rules look for a *run*: consecutive refused seqs (no accepted one between them), each
    following the previous one of the run by 1..``step``, as a camera or capture that really
    renumbered delivers them. A single stray seq never forms one, and neither does a second
    publisher whose messages alternate with the accepted stream's (each accepted message ends
    the run).

    ``admit(newest, seq)`` (forward): True for a seq at most ``max_jump`` ahead of ``newest`` (or
    behind it: see :meth:`renumbered`), and for the ``confirm``-th far-ahead seq of a run; False for
    the others, so one message with a far-future seq is refused instead of becoming the newest and
    making every later one look out of order. An admitted ordinary seq ends both runs.

    ``renumbered(seq, fresh)`` (backward, for a seq at or behind the newest that the caller would refuse
    as a duplicate or out of order): True for the ``resync``-th seq of a run, which confirms that the
    numbering went back. ``fresh=False`` says the message was published before the newest accepted
    one (:func:`published_after`): a history replay, which neither joins nor ends a run.

    A confirming seq leaves its run in place until an ordinary seq is admitted, so if the caller
    still refuses the confirming message for another reason (no valid depth) the next one of the
    run confirms again instead of starting over.
    """

    def __init__(self, max_jump: int = 300, confirm: int = 5, step: int = 5, resync: int = 15) -> None:
        self.max_jump, self.confirm, self.step, self.resync = max_jump, confirm, step, resync
        self._run: list[int] = []  # far-ahead seqs in a row
        self._back: list[int] = []  # seqs behind the newest in a row
        self.refused = 0

    @property
    def run(self) -> list[int]:
        """The current backward run, oldest first (after :meth:`renumbered` said True: the seqs of the
        new numbering that confirmed it, the confirming one last)."""
        return list(self._back)

    @property
    def ahead(self) -> list[int]:
        """The current far-ahead run, oldest first (after :meth:`admit` said True for a far-ahead seq:
        the seqs that confirmed the new numbering, the confirming one last; empty after an ordinary seq)."""
        return list(self._run)

    def _extend(self, run: list[int], seq: int) -> list[int]:
        """``run`` with ``seq`` appended if it follows the run's last seq by 1..step, else a new run of ``seq``."""
        if run and 0 < seq - run[-1] <= self.step:
            run.append(seq)
            return run
        return [seq]

    def admit(self, newest: int | None, seq: int) -> bool:
        """Whether ``seq`` (after ``newest``, None: nothing accepted yet) may be accepted: not far ahead,
        or the ``confirm``-th of a far-ahead run."""
        if newest is None or seq - newest <= self.max_jump:
            self._run.clear()
            self._back.clear()
            return True
        self._run = self._extend(self._run, seq)
        if len(self._run) >= self.confirm:
            self._back.clear()
            return True
        self.refused += 1
        return False

    def renumbered(self, seq: int, fresh: bool = True) -> bool:
        """Whether ``seq``, at or behind the newest accepted seq, is the ``resync``-th of a backward run
        (the numbering went back: accept it, as a break); False: refuse it, as before."""
        if not fresh:
            return False
        self._back = self._extend(self._back, seq)
        return len(self._back) >= self.resync


T = TypeVar("T")


class AheadHold(Generic[T]):
    """A stage's intake of messages numbered by frame (flows, corrections) under :meth:`JumpGuard.admit`:
    one whose seq is more than ``max_jump`` ahead of the newest the stage took is *held*, not taken,
    until ``confirm`` in a row confirm a new numbering; then the run's held messages are taken, in
    order, with the confirming one (a real jump loses nothing). An ordinary seq admitted first drops
    what was held (counted in ``dropped``): one forged or garbled message with a far-future seq
    never becomes the newest, so it cannot make every later message look stale and halt the stream.
    Messages at or behind the newest are the caller's to judge (stale, or a renumbering) and are
    not offered: they neither end nor join a run."""

    def __init__(self, guard: JumpGuard | None = None) -> None:
        self.guard = guard or JumpGuard()
        self._held: list[T] = []
        self.dropped = 0  # held, then dropped: no run confirmed them

    def drop(self) -> int:
        """End of stream: what is held will not be confirmed; dropped (counted), how many."""
        n = len(self._held)
        self.dropped += n
        self._held = []
        return n

    def offer(self, newest: int | None, seq: int, item: T) -> list[T]:
        """The messages to take now, in order, given ``item`` numbered ``seq`` (ahead of ``newest``, the
        newest the stage took): ``[item]`` for an ordinary seq, nothing while a far-ahead run is being
        confirmed (``item`` held), the run's held messages and ``item`` when it confirms the run."""
        if self.guard.admit(newest, seq):
            if self.guard.ahead:  # the confirming one of a far-ahead run: the run's held ones first
                out, self._held = [*self._held, item], []
                return out
            self.dropped += len(self._held)
            self._held = []
            return [item]
        if len(self.guard.ahead) == 1:  # a new run: what the last one held is not continued by it
            self.dropped += len(self._held)
            self._held = []
        self._held.append(item)
        return []


class ContinuityCheck:
    """Checks each frame against the previous good one and counts what it finds (one per stream)."""

    def __init__(self, params: ContinuityParams | None = None) -> None:
        self.params = params or ContinuityParams()
        self.params.validate()
        self.counts = dict.fromkeys(COUNTERS, 0)
        self.jumps = JumpGuard(self.params.max_jump, self.params.confirm, self.params.max_missing + 1,
                               self.params.resync)

    def inspect(self, prev: RGBDFrame | None, frame: RGBDFrame, fresh: bool = True, shed: int = 0) -> Verdict:
        """Verdict on ``frame`` following ``prev`` (None: the first frame); raises :class:`FrameRefused`.
        ``fresh=False``: the frame was published before ``prev`` (:func:`published_after`), so it
        cannot start a new numbering. ``shed``: how many of the frames between them the caller shed
        (:mod:`~quick_stream.core.admission`): bridged by the same rules, counted as shed, not missing."""
        c = self.counts
        renumbered = False
        if prev is not None and frame.seq <= prev.seq:
            if not self.jumps.renumbered(frame.seq, fresh):
                kind = "duplicate_frames" if frame.seq == prev.seq else "out_of_order_frames"
                c[kind] += 1
                raise FrameRefused(f"{frame.label} is not after frame {prev.seq} "
                                   f"({'duplicate' if frame.seq == prev.seq else 'out of order'})")
            renumbered = True
        elif not self.jumps.admit(None if prev is None else prev.seq, frame.seq):
            c["seq_jumps"] += 1
            raise FrameRefused(f"{frame.label} is {frame.seq - prev.seq} frames ahead of frame {prev.seq} "
                               f"(more than {self.params.max_jump}): refused unless {self.params.confirm} "
                               "frames in a row continue the new numbering")
        n_notes = len(frame.notes)
        try:
            frame.validate()
        except FrameError as e:
            c["invalid_frames"] += 1
            raise FrameRefused(str(e)) from None
        v = Verdict(notes=[f"{frame.label}: {n}" for n in frame.notes[n_notes:]])
        c["repaired_frames"] += bool(v.notes)
        if prev is None:
            return v
        reasons = []
        missing = frame.seq - prev.seq - 1
        dt = (frame.timestamp_ns - prev.timestamp_ns) / 1e9
        if renumbered:
            c["renumberings"] += 1
            reasons.append(f"{RENUMBERED}: frame {frame.seq} follows frame {prev.seq}, confirmed by "
                           f"{self.params.resync} frames in a row")
        elif missing:
            c["seq_gaps"] += missing > shed
            c["missing_frames"] += missing - shed
            bridged = 0 < dt <= self.params.max_bridge_s and missing < self.params.max_jump  # not a renumbering
            if missing > self.params.max_missing and not bridged:
                reasons.append(f"{missing} frames missing between frame {prev.seq} and {frame.seq}")
        if dt <= 0 or dt > self.params.max_gap_s:
            c["timestamp_jumps"] += 1
            reasons.append(f"capture time jumps by {dt:+.3f} s from frame {prev.seq} to {frame.seq}")
        if frame.color.shape != prev.color.shape:
            c["size_changes"] += 1
            reasons.append(f"image size changes from {prev.color.shape[1]}x{prev.color.shape[0]} to "
                           f"{frame.color.shape[1]}x{frame.color.shape[0]} at frame {frame.seq}")
        k0, k1 = prev.intrinsics, frame.intrinsics
        if (k0.fx, k0.fy, k0.cx, k0.cy) != (k1.fx, k1.fy, k1.cx, k1.cy):
            c["intrinsics_changes"] += 1
            v.notes.append(f"{frame.label}: intrinsics change from fx={k0.fx:.2f} fy={k0.fy:.2f} cx={k0.cx:.2f} "
                           f"cy={k0.cy:.2f} to fx={k1.fx:.2f} fy={k1.fy:.2f} cx={k1.cx:.2f} cy={k1.cy:.2f}")
        if reasons:
            c["breaks"] += 1
            v.brk = "; ".join(reasons) + f": {BREAK}"
        return v

"""Frames waiting for their corrections, kept apart per numbering of the stream.

The render stage (:mod:`quick_stream.core.render_stage`) takes frames as they arrive and renders
them when their release comes. :class:`FrameHold` is the waiting room: it admits a frame
or refuses it (out of order, a duplicate, a jump no run of frames confirms), confirms a stream
renumbered lower (:class:`~quick_stream.core.continuity.JumpGuard`, as the flow stage does) and keeps
that numbering's frames apart from the old one's, bounds what it holds (frames and bytes: the
oldest is dropped), lets go of frames the flow stage shed, and says which numbering a correction
release belongs to and whether it can be rendered yet. It renders nothing.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from typing import Any, Callable, Iterable

from .continuity import JumpGuard, published_after, starts_numbering
from .frame import RGBDFrame
from .path.planner import Correction

FrameLoader = Callable[[], RGBDFrame]


class FrameHold:
    """Frames (decoded, or as loaders decoded only when rendered) held per numbering until their
    corrections reach them (:mod:`module docstring <quick_stream.core.frame_hold>`).

    At most ``max_frames`` wait, and at most ``max_bytes`` of them; beyond that the oldest is dropped
    and counted (``dropped``); a frame that cannot be loaded is reported in ``bad``; a frame the flow
    stage shed is let go undecoded (``shed``, :meth:`let_go`). ``prepare``: made for each decoded
    frame on arrival and handed back with it by :meth:`load` (the render stage's warp input), with
    the milliseconds it took. ``numbering`` counts the renumberings taken (``renumberings`` too)."""

    def __init__(self, max_frames: int = 240, max_bytes: int | None = None,
                 prepare: Callable[[RGBDFrame], Any] | None = None) -> None:
        self.max_frames, self.max_bytes, self.prepare = max_frames, max_bytes, prepare
        self._sizes: dict[tuple[int, int], int] = {}  # (numbering, seq) -> bytes, of the frames held
        self.held_bytes = 0
        self.shed = 0  # frames let go because the flow stage shed them
        self._shed_ahead: OrderedDict[int, None] = OrderedDict()  # named as shed before they arrived
        # held frames per numbering (0, then one more per renumbering), only those the corrections may still reach
        self._held: dict[int, OrderedDict[int, RGBDFrame | FrameLoader]] = {0: OrderedDict()}
        self._prepared: dict[tuple[int, int], tuple[Any, float]] = {}  # (numbering, seq) -> (prepare's, ms)
        self.numbering = 0  # the numbering frames are taken in
        self.reached = 0  # the numbering the corrections have reached
        self._newest_in: dict[int, int] = {}  # per numbering held, the newest frame taken in it
        self._newest_pub: int | None = None  # when the newest frame taken was published (None: unknown)
        self.renumberings = 0
        self.dropped = 0
        self.bad: list[dict] = []
        self.jumps = JumpGuard()  # the flow stage's defaults: what it refuses gets no correction

    @property
    def buffered(self) -> int:
        return sum(len(h) for h in self._held.values())

    @property
    def newest(self) -> int | None:
        """The newest frame taken (in the numbering frames are taken in), None before the first."""
        return self._newest_in.get(self.numbering)

    def fresh(self, pub_ns: int | None) -> bool:
        """Whether a frame published at ``pub_ns`` may be newer than the newest frame taken
        (:func:`~quick_stream.core.continuity.published_after`): False for a history replay."""
        return published_after(pub_ns, self._newest_pub)

    def add(self, seq: int, frame: RGBDFrame | FrameLoader, pub_ns: int | None = None,
            size: int | None = None) -> bool:
        """Hold a frame (or its loader, ``size`` bytes held) until its correction arrives; False
        when it is let go instead (the flow stage shed it: :meth:`let_go`). Refused (ValueError): one not
        after the newest taken (unless a run of them confirms that the numbering went back: then
        it is the first frame of a new numbering), and one far ahead of the newest taken that no
        run of frames confirms (:class:`~quick_stream.core.continuity.JumpGuard`, as the flow stage
        does). ``pub_ns``: when the frame was published, so a replay never starts a numbering."""
        newest = self.newest
        if seq in self._shed_ahead and (newest is None or seq > newest):
            del self._shed_ahead[seq]
            self.shed += 1
            return False
        if newest is not None and seq <= newest:
            if not self.jumps.renumbered(seq, self.fresh(pub_ns)):
                raise ValueError(f"frame {seq} is not after frame {newest}, the newest taken (out of order or "
                                 "duplicate)")
            self.numbering += 1
            self.renumberings += 1
            self._shed_ahead.clear()  # named in the old numbering
            self._held[self.numbering] = OrderedDict()
        elif not self.jumps.admit(newest, seq):
            raise ValueError(f"frame {seq} is {seq - newest} frames ahead of frame {newest} "
                             f"(more than {self.jumps.max_jump}): refused unless frames in a row continue from it")
        self._newest_in[self.numbering] = seq
        self._newest_pub = pub_ns
        self._held[self.numbering][seq] = frame
        if size is None:
            size = frame.color.nbytes + frame.depth.nbytes if isinstance(frame, RGBDFrame) else 0
        self._sizes[(self.numbering, seq)] = size
        self.held_bytes += size
        if isinstance(frame, RGBDFrame) and self.prepare is not None:
            t0 = time.perf_counter()
            made = self.prepare(frame)
            self._prepared[(self.numbering, seq)] = (made, (time.perf_counter() - t0) * 1e3)
        while self.buffered > self.max_frames or (self.max_bytes is not None and self.held_bytes > self.max_bytes
                                                  and self.buffered > 1):
            n = min(k for k, h in self._held.items() if h)
            self._take(n, next(iter(self._held[n])))
            self.dropped += 1
        return True

    def _take(self, n: int, seq: int, keep_prepared: bool = False) -> RGBDFrame | FrameLoader | None:
        """A held frame (or its loader) of numbering ``n`` out of the hold (None: not held)."""
        f = self._held.get(n, {}).pop(seq, None)
        self.held_bytes -= self._sizes.pop((n, seq), 0)
        if not keep_prepared:
            self._prepared.pop((n, seq), None)
        return f

    def let_go(self, seqs: Iterable[int], numbering: int | None = None) -> None:
        """Frames of ``numbering`` (default: the newest) the flow stage shed (a correction's or the end's
        ``shed``): each let go undecoded, counted in ``shed``; one not here yet is let go when it comes."""
        n = self.numbering if numbering is None else numbering
        for seq in seqs:
            if self._take(n, seq) is not None:
                self.shed += 1
            elif n == self.numbering and (self.newest is None or seq > self.newest):
                self._shed_ahead[seq] = None
                while len(self._shed_ahead) > 4096:
                    self._shed_ahead.popitem(last=False)

    def load(self, numbering: int, seq: int) -> tuple[RGBDFrame | None, Any, float]:
        """A held frame out of the hold, decoded (None: not held, or it cannot be decoded, reported in
        ``bad``), with what ``prepare`` made for it on arrival and the ms that took (None, 0: nothing)."""
        f = self._take(numbering, seq, keep_prepared=True)
        made, ms = self._prepared.pop((numbering, seq), (None, 0.0))
        if f is None or isinstance(f, RGBDFrame):
            return f, made, ms
        try:
            return f(), made, ms
        except Exception as e:  # noqa: BLE001 - a frame that cannot be decoded is reported, not fatal
            self.bad.append({"seq": seq, "error": f"{type(e).__name__}: {e}"})
            return None, None, 0.0

    def numbering_of(self, release: list[Correction]) -> int:
        """The numbering a release belongs to. The release that restarts the path in a new
        numbering (the restart correction of a renumbering's break,
        :func:`~quick_stream.core.continuity.starts_numbering`) belongs to the next numbering frames
        were taken in (if the frames have not shown one, this hold never saw the old numbering: the
        current one); any other release to the numbering the corrections reached, unless only a later
        numbering holds any of its frames (the restart release was lost or rendered before its frames came)."""
        later = sorted(n for n in self._held if n > self.reached)
        if starts_numbering(release[0]):
            return later[0] if later else self.reached
        seqs = {c.seq for c in release}
        for n in [self.reached, *later]:
            if not seqs.isdisjoint(self._held.get(n, {})):
                return n
        return self.reached

    def can_render(self, release: list[Correction]) -> bool:
        """Whether a release can be rendered now, before the frames it waits for could come:
        all its frames are held, or a newer frame of its numbering (or a later numbering) has been
        taken, so a missing one will never come. A release that restarts the path in a new numbering
        waits for its frames while the frames have not shown the renumbering yet."""
        if not release:
            return True
        n = self.numbering_of(release)
        held = self._held.get(n, {})
        seqs = [c.seq for c in release]
        if all(s in held for s in seqs):
            return True
        if starts_numbering(release[0]) and n == self.reached:
            return False
        newest = self._newest_in.get(n)
        return n < self.numbering or (newest is not None and newest > max(seqs))

    def reach(self, n: int) -> list[tuple[int, int]]:
        """The corrections reached numbering ``n``: the (numbering, seq) of every frame still held in an
        older numbering (no correction will reach them), which the hold keeps until they are loaded."""
        stale = [(old, seq) for old in sorted(k for k in self._held if k < n) for seq in self._held[old]]
        for old in [k for k in self._held if k < n]:
            self._newest_in.pop(old, None)
        self.reached = n
        return stale

    def waiting(self, n: int) -> list[int]:
        """The frames of numbering ``n`` held, oldest first."""
        return list(self._held.get(n, {}))

    def everything(self) -> list[tuple[int, int]]:
        """(numbering, seq) of every frame held, numbering by numbering, oldest first."""
        return [(n, seq) for n in sorted(self._held) for seq in self._held[n]]

    def forget_empty(self) -> None:
        """Drop the numberings older than the one the corrections reached once nothing of them is held."""
        for old in [k for k in self._held if k < self.reached and not self._held[k]]:
            del self._held[old]

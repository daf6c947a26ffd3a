"""Releases: the corrections of each planner call, from the motion stage to the render stage, and the render policy.

    MotionStage releases -> ReleaseNumbering -> (correction, (release, index, size)) -> wire ->
        ReleaseGroups -> RenderDriver -> Rendered (stabilized frame + latency stamps)

A *release* is what one planner call released (:mod:`quick_stream.core.stages`); the renderer frames
each as a whole, so the corrections travel tagged with their release. :class:`ReleaseNumbering`
tags them (the motion service publishes the tags), :class:`ReleaseGroups` regroups what arrives one
message at a time, and :class:`RenderDriver` is the render side over a service's life: which
frames are taken, when a release renders (all its frames here, a newer one arrived, or
``frame_wait`` passed), the latency stamps of each frame (docs/wire-format.md), the end of a
stream (frames the corrections' end overtook get ``frame_wait``; then every release left and
every frame still held are rendered) and the counters carried from one stream to the next.

The render service, :class:`~quick_stream.core.stabilizer.Stabilizer` and ``quick-stream rerun``
run these same objects (docs/architecture.md), so a re-run checks the service's own policy.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from .continuity import AheadHold, starts_numbering
from .frame import RGBDFrame
from .logs import log_or_quiet
from .path.planner import Correction
from .release_tags import Tag
from .render import FramingParams, WarpParams
from .render_stage import FrameLoader, RenderStage, StabilizedFrame


class ReleaseGroups:
    """Corrections grouped by planner release; yields complete releases in order.

    The motion service sends a release's corrections back to back, so a release still
    incomplete when another one starts arriving lost its sender mid-way (a killed motion
    service): it is handed over with what arrived (``abandoned``). A restarted motion
    service numbers releases from 0 again; a correction that does not fit the open release
    of that number (other size, or an index already there) starts a new one.

    ``ready`` holds (release, corrections, completed at, numbering, closed by), in seq order within a numbering:
    the restart correction of a renumbering's break (:func:`~quick_stream.core.continuity.starts_numbering`,
    going back) starts the next numbering, whose releases follow every release of the old one.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock  # when a release completed (how long it has waited for its frames)
        # per open release: its size, the corrections in, its numbering and the frame that closed it
        self._open: dict[int, tuple[int, dict[int, Correction], int, int | None]] = {}
        self.ready: list[tuple[int, list[Correction], float, int, int | None]] = []
        self.abandoned = 0
        self.numbering = 0  # renumberings the corrections announced
        self._newest: int | None = None  # the newest correction seq of the current numbering

    @property
    def newest(self) -> int | None:
        """The newest correction seq of the current numbering (None: none yet)."""
        return self._newest

    def _hand_over(self, rel: int) -> None:
        _, got, numbering, closed_by = self._open.pop(rel)
        self.ready.append((rel, [got[i] for i in sorted(got)], self.clock(), numbering, closed_by))
        self.ready.sort(key=lambda r: (r[3], r[1][0].seq))

    def _numbering(self, c: Correction) -> int:
        """The numbering ``c`` belongs to (a restart correction going back starts the next one)."""
        if starts_numbering(c) and self._newest is not None and c.seq <= self._newest:
            self.numbering += 1
            self._newest = None
        self._newest = c.seq if self._newest is None else max(self._newest, c.seq)
        return self.numbering

    def add(self, c: Correction, tag: Tag | tuple[int, int, int] | None) -> None:
        numbering = self._numbering(c)
        if tag is None:  # a sender without release tags: each correction is its own release
            self.ready.append((-1, [c], self.clock(), numbering, None))
            return
        rel, idx, size, closed_by = Tag(*tag)
        for other in [r for r in self._open if r != rel]:
            self.abandoned += 1
            self._hand_over(other)
        if rel in self._open and (self._open[rel][0] != size or idx in self._open[rel][1]
                                  or self._open[rel][2] != numbering):
            self.abandoned += 1
            self._hand_over(rel)
        got = self._open[rel][1] if rel in self._open else {}
        got[idx] = c
        self._open[rel] = (size, got, numbering, closed_by)
        if len(got) == size:
            self._hand_over(rel)

    def flush_incomplete(self) -> int:
        """End of stream: hand over partial releases (what arrived of them); returns how many."""
        n = len(self._open)
        for rel in sorted(self._open):
            self._hand_over(rel)
        return n


@dataclass
class Release:
    """One release due for rendering: its id and its corrections."""

    id: int
    corrections: list[Correction]
    closed_by: int | None = None  # the frame whose arrival closed it (None: not known)

    @property
    def label(self) -> str:
        return f"release {self.id} (frames {self.corrections[0].seq}..{self.corrections[-1].seq})"


@dataclass
class Rendered:
    """A stabilized frame with its latency stamps (docs/wire-format.md): when the capture published
    it (``src_pub_ns``) and the frame whose arrival closed its release (``ready_pub_ns``)."""

    frame: StabilizedFrame
    src_pub_ns: int | None
    ready_pub_ns: int | None


CARRIED = ("dropped", "missing", "orphans", "bad_frames", "filled", "fill_raised", "bordered", "renumberings",
           "shed_upstream")


class RenderDriver:
    """The render stage over a service's life (module docstring): frames and tagged corrections in,
    due releases rendered with their latency stamps out, one stream after another.

    ``frame_wait``: seconds a release whose frames are not all here waits for them (unless a newer
    frame shows they will not come); ``max_frames``, ``max_bytes``: what the stage holds at most
    (:class:`~quick_stream.core.render_stage.RenderStage`); frames the flow stage shed, named by the
    corrections and the end marker (``shed``), are let go (``shed_upstream``); ``resume_after``: a restarted render takes over after the
    last frame its predecessor rendered (frames and corrections up to it are skipped, counted in
    ``taken_over``, until a renumbering or the end of the stream); ``log``: where refusals,
    renumberings and frames that cannot be rendered are reported (None: silent); ``clock``: seconds,
    monotonic (how long a release has waited)."""

    def __init__(self, warp: WarpParams | None = None, framing: FramingParams | None = None, *,
                 max_frames: int = 150, frame_wait: float = 1.0, resume_after: int | None = None,
                 keep_inputs: bool = False, log: logging.Logger | None = None,
                 clock: Callable[[], float] = time.monotonic, max_bytes: int | None = None) -> None:
        self._make = lambda: RenderStage(warp, framing, max_frames=max_frames, keep_inputs=keep_inputs,
                                         max_bytes=max_bytes)
        self.stage = self._make()
        self.releases = ReleaseGroups(clock)  # one for the service's life: a restarted motion renumbers from 0
        self.ahead: AheadHold[tuple[Correction, Tag | None]] = AheadHold()  # far-ahead corrections
        self.max_frames, self.frame_wait, self.resume_after = max_frames, frame_wait, resume_after
        self.log, self.clock = log_or_quiet(log), clock
        self._pub_ns: dict[tuple[int, int], int] = {}  # (numbering, seq) -> when the capture published the frame
        self.refused = self.taken_over = self.flagged = self.ended = 0
        self._done = dict.fromkeys(CARRIED, 0)  # counts of the streams already ended
        self.ending = False  # the corrections' end came: the stream ends once its frames are in
        self.end_marker: Any = None  # what came with it (forwarded by the service)
        self._deadline: float | None = None

    def add_correction(self, c: Correction, tag: Tag | None) -> None:
        """One correction as it arrives, with its release tag (None: a sender without tags). One more
        than ``max_jump`` frames beyond both the newest correction and the newest frame taken is held
        until a run confirms it, as the flow and motion stages do
        (:class:`~quick_stream.core.continuity.AheadHold`; dropped unconfirmed:
        ``jump_corrections``): rendered as a release, one from the far future made orphans of every frame held.
        The frames a correction names as shed by the flow stage are let go when its release renders."""
        if self.resume_after is not None and c.seq <= self.resume_after:
            return
        newest = max((s for s in (self.releases.newest, self.stage.hold.newest) if s is not None), default=None)
        dropped = self.ahead.dropped
        if self.releases.newest is None or c.seq <= self.releases.newest:
            taken = [(c, tag)]  # (not ahead of the corrections: neither joins nor ends a run)
        else:
            taken = self.ahead.offer(newest, c.seq, (c, tag))
        if self.ahead.dropped > dropped:
            self.log.log(logging.ERROR, "%d corrections held far ahead dropped: no run confirmed a new numbering",
                      self.ahead.dropped - dropped)
        if not taken:
            self.log.log(logging.WARNING, "correction %d is %d frames beyond frame %d (more than %d): held until %d in "
                      "a row continue from it", c.seq, c.seq - newest, newest, self.ahead.guard.max_jump,
                      self.ahead.guard.confirm)
        for c, tag in taken:
            self.releases.add(c, tag)

    def add_frame(self, seq: int, frame: RGBDFrame | FrameLoader, pub_ns: int | None = None,
                  size: int | None = None) -> bool:
        """Hold a frame (or its loader, ``size`` bytes) for its release; False when it is not taken:
        rendered before a restart (``taken_over``), refused by the stage (``refused_frames``, reported)
        or shed by the flow stage (``shed_upstream``)."""
        st = self.stage.hold
        if self.resume_after is not None and seq <= self.resume_after and (st.newest is None or not st.fresh(pub_ns)):
            # rendered before the restart (the frames' history); once frames are taken, one published
            # after them is live: a stream renumbered below the cursor, for the stage to confirm
            self.taken_over += 1
            return False
        renumberings = st.renumberings
        try:
            if not self.stage.add_frame(seq, frame, pub_ns, size):
                return False
        except ValueError as e:
            self.refused += 1
            self.log.log(logging.ERROR, "frame %d: %s", seq, e)
            return False
        if st.renumberings > renumberings:
            self.log.log(logging.WARNING, "frame %d: the stream's numbering restarts (confirmed by %d frames in a row); "
                      "%d frames of the old numbering held for their corrections", seq, st.jumps.resync,
                      st.buffered - 1)
            self.resume_after = None  # the predecessor's cursor says nothing of the new numbering
        self._pub_ns[(st.numbering, seq)] = pub_ns or 0
        while len(self._pub_ns) > self.max_frames + 64:
            self._pub_ns.pop(next(iter(self._pub_ns)))
        return True

    def due(self, force: bool = False) -> Iterator[Release]:
        """The releases to render now, in order, each popped as it is yielded (render it with
        :meth:`render` before asking for the next): all its frames are here, a newer frame has
        arrived (a missing one will not come), ``frame_wait`` has passed, or ``force``."""
        while force and self.releases.ready or self.has_due:
            rel, corrections, _, _, closed_by = self.releases.ready.pop(0)
            yield Release(rel, corrections, closed_by)

    @property
    def has_due(self) -> bool:
        """Whether a release is due now (:meth:`due`; a service that renders one a pass, so that the
        frames arriving meanwhile are taken between releases, does not sleep while one is)."""
        if not self.releases.ready:
            return False
        _, corrections, t_done, _, _ = self.releases.ready[0]
        return self.stage.hold.can_render(corrections) or self.clock() - t_done > self.frame_wait

    def render(self, release: Release) -> Iterator[Rendered]:
        """Render a release and the orphans it reveals, each frame stamped as it is rendered: ready when
        the frame that closed the release was published (the release's newest when that is not
        known, or not after it, or not here)."""
        st, last = self.stage, max(c.seq for c in release.corrections)
        n = st.hold.numbering_of(release.corrections)
        closed = release.closed_by if release.closed_by is not None and release.closed_by > last else last
        ready = (n, closed) if (n, closed) in self._pub_ns else (n, last)
        bad = st.hold.bad
        nbad = len(bad)
        try:
            for sf in st.iter_release(release.corrections):
                yield self._stamped(sf, ready)
        finally:
            for b in bad[nbad:]:
                self.log.log(logging.ERROR, "frame %d cannot be rendered: %s", b["seq"], b["error"])

    def _stamped(self, sf: StabilizedFrame, ready: tuple[int, int] | None) -> Rendered:
        src = self._pub_ns.pop((sf.numbering, sf.seq), None)
        self.flagged += bool(sf.flags)
        return Rendered(sf, src, self._pub_ns.get(ready, src) if ready is not None else src)

    @property
    def takes_corrections(self) -> bool:
        """Whether a service reads corrections now: every pending one first (cheap, and what releases
        frames), then the frames that had arrived by then (under overload frames come faster than
        they decode: one correction per pass of an endless frame drain starved the corrections), but
        none while a stream ends (they are the next stream's)."""
        return not self.ending

    @property
    def idle_s(self) -> float:
        """How long a service with nothing to read sleeps before asking again: shorter while a stream
        ends (the frames its end overtook are awaited)."""
        return 0.02 if self.ending else 0.05

    def end(self, marker: Any = None) -> None:
        """The corrections' end: no more corrections of this stream; what arrived of a release is
        a release (``abandoned``), and the frames the end overtook get ``frame_wait`` (:meth:`end_due`)."""
        self.ending, self.end_marker, self._deadline = True, marker, None
        if self.ahead.drop():
            self.log.log(logging.ERROR, "end of stream with corrections held far ahead: dropped, no run confirmed them")
        self.stage.hold.let_go(getattr(marker, "shed", ()))  # shed after the last flow: never corrected
        n = self.releases.flush_incomplete()
        if n:
            self.log.log(logging.WARNING, "end of stream with %d incomplete releases", n)

    def end_due(self, stopping: bool = False) -> bool:
        """After :meth:`end`: whether the stream ends now (:meth:`finish`): every release rendered,
        ``frame_wait`` passed since the first ask (a frame a congested link dropped comes back later,
        from its publisher's cache), or ``stopping``."""
        if not self.ending:
            return False
        if self._deadline is None:
            self._deadline = self.clock() + self.frame_wait
        return stopping or not self.releases.ready or self.clock() > self._deadline

    def finish(self) -> Iterator[tuple[str, Iterator[Rendered]]]:
        """End of stream: every release left, as it is, then every frame still held, uncorrected and
        flagged; (label, frames) per group, each rendered as its frames are asked for (in order).
        :meth:`restart` then starts the next stream."""
        for rel in self.due(force=True):
            yield rel.label, self.render(rel)
        yield "end of stream", self._flushed()

    def _flushed(self) -> Iterator[Rendered]:
        for sf in self.stage.flush():
            yield self._stamped(sf, None)

    def restart(self) -> None:
        """After :meth:`finish`: the next stream starts afresh; the counters go on."""
        for k, v in self._per_stream().items():
            self._done[k] += v
        self.ended += 1
        self.stage = self._make()
        self.ending, self.end_marker, self._deadline, self.resume_after = False, None, None, None

    def _per_stream(self) -> dict[str, int]:
        st, hold, filler = self.stage, self.stage.hold, self.stage.filler
        return {"dropped": hold.dropped, "missing": st.missing, "orphans": st.orphans, "bad_frames": len(hold.bad),
                "filled": filler.filled, "fill_raised": filler.fill_raised, "bordered": filler.bordered,
                "renumberings": hold.renumberings, "shed_upstream": hold.shed}

    def stats(self) -> dict[str, int]:
        """The counters of docs/reliability.md (the stream under way plus those ended)."""
        return {"refused_frames": self.refused, "taken_over": self.taken_over, "buffered": self.stage.hold.buffered,
                "held_mb": round(self.stage.hold.held_bytes / 2**20, 1),
                **{k: self._done[k] + v for k, v in self._per_stream().items()}, "flagged": self.flagged,
                "pending_releases": len(self.releases.ready), "ended": self.ended,
                "abandoned_releases": self.releases.abandoned, "jump_corrections": self.ahead.dropped}

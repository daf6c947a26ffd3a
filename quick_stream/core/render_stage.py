"""The render stage, shared by the in-process stabilizer and the ``render`` service.

    frames + correction batches -> RenderStage -> StabilizedFrame

:class:`RenderStage` holds frames until their correction batch arrives (a batch is what one
planner call released, :mod:`quick_stream.core.stages`), then warps, frames and renders the batch as a
whole (one zoom track, :func:`~quick_stream.core.render.segment_zooms`), filling uncovered borders from
its neighbours. A frame that no correction will ever reach (an *orphan*, skipped upstream) is
rendered with no correction, flagged, instead of being held forever; a stream renumbered lower
keeps the old numbering's frames apart from the new one's. The policy around it (corrections
regrouped into the planner's releases, when a release renders, latency stamps, the end of a stream)
is :mod:`quick_stream.core.release`.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator

import numpy as np

from .continuity import JumpGuard, published_after, starts_numbering
from .frame import RGBDFrame
from .path.planner import Correction
from .render import FramingParams, MeshWarp, WarpParams, ZoomSmoother, render, segment_zooms, solve_warp
from .render.fill import FillSource, covered_zoom, fill_border, ordered_sources, raise_for
from .render.mapping import map_samples, render_covered, rezoom_samples
from .render.warp import WarpInput, prepare_warp
from .timing import StageTimer

FrameLoader = Callable[[], RGBDFrame]


@dataclass
class StabilizedFrame:
    seq: int
    timestamp_ns: int
    image: np.ndarray  # BGR uint8, same size as the input
    correction: Correction
    zoom: float
    mesh: MeshWarp
    input_image: np.ndarray | None = None  # kept only when the caller asks (metrics)
    numbering: int = 0  # which of the stream's numberings the render stage took the frame in (see RenderStage)

    @property
    def flags(self) -> list[str]:
        out = []
        if not self.correction.valid:
            out.append(self.correction.reason)
        if not self.mesh.ok:
            out.append(f"warp: {self.mesh.reason}")
        return out


@dataclass
class _Plan:
    """A frame about to be rendered: its correction, frame, warp (None until solved, from the warp
    input made on arrival, ``prepared``; ``prep_ms``: the ms that took plus the frame's share of
    loading, counted with the solve as its warp time) and zoom, the numbering it was taken in, its
    share of the batch's framing time (ms) and, when the border fill's estimate made them, the map
    samples at that zoom (the render reuses them)."""

    c: Correction
    f: RGBDFrame
    mesh: MeshWarp | None
    zoom: float
    numbering: int
    framing_ms: float
    samples: np.ndarray | None = None
    prepared: WarpInput | None = None
    prep_ms: float = 0.0


ORPHAN = "no correction: frame skipped upstream"
STALE = "no correction: the stream's numbering restarted before this frame's correction came"


def orphan_correction(seq: int, reason: str = ORPHAN) -> Correction:
    """What a frame no correction reached is rendered with: none, flagged."""
    return Correction(seq, np.eye(4), -1, False, False, reason)


class RenderStage:
    """Holds frames until their correction batch arrives, then warps, frames and renders them.

    Frames may be given decoded or as a loader (decoded only when rendered, so a
    service buffers compressed bytes). At most ``max_frames`` wait, and at most ``max_bytes`` of
    them; beyond that the oldest is dropped and counted (``dropped``); a correction whose frame is
    gone is counted in ``missing``; a frame that cannot be loaded is reported in ``bad``; a frame the
    flow stage shed is let go undecoded, not rendered as an orphan (``shed``, :meth:`let_go`).

    A stream whose numbering goes back (confirmed as the flow stage confirms it,
    :class:`~quick_stream.core.continuity.JumpGuard`) is held apart from the frames of the old
    numbering still waiting (``numbering`` counts the renumberings taken, ``renumberings``
    too): the old numbering's corrections still come first, each batch renders against the
    frames of its own numbering, and once the corrections reach the new numbering (the
    restart correction the renumbering's break made, :func:`~quick_stream.core.continuity.starts_numbering`)
    what is left of the old one is rendered uncorrected and flagged (``orphans``) before it.
    """

    def __init__(self, warp: WarpParams | None = None, framing: FramingParams | None = None,
                 max_frames: int = 240, keep_inputs: bool = False, max_bytes: int | None = None) -> None:
        self.warp = warp or WarpParams()
        self.framing = framing or FramingParams()
        self.framing.validate()
        self.zoom = ZoomSmoother(self.framing)
        self.max_frames, self.max_bytes = max_frames, max_bytes
        self.keep_inputs = keep_inputs
        self._sizes: dict[tuple[int, int], int] = {}  # (numbering, seq) -> bytes, of the frames held
        self.held_bytes = 0
        self.shed = 0  # frames let go because the flow stage shed them
        self._shed_ahead: OrderedDict[int, None] = OrderedDict()  # named as shed before they arrived
        self.timer = StageTimer()
        # held frames per numbering (0, then one more per renumbering), only those the corrections may still reach
        self._held: dict[int, OrderedDict[int, RGBDFrame | FrameLoader]] = {0: OrderedDict()}
        # warp inputs of decoded frames, made on arrival, and the ms that took
        self._prepared: dict[tuple[int, int], tuple[WarpInput, float]] = {}
        self.numbering = 0  # the numbering frames are taken in
        self._corr = 0  # the numbering the corrections have reached
        self._newest_in: dict[int, int] = {}  # per numbering held, the newest frame taken in it
        self._newest_pub: int | None = None  # when the newest frame taken was published (None: unknown)
        self.renumberings = 0
        self.dropped = 0
        self.missing = 0
        self.orphans = 0
        self.bad: list[dict] = []
        self._past: list[FillSource] = []  # the last fill_frames rendered frames the border fill can read
        self.filled = 0  # frames whose border was filled from neighbours
        self.fill_raised = 0  # frames zoomed in beyond their plan because fill left a border
        self.bordered = 0  # frames rendered with output pixels no source reached (a black border): 0 expected
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

    def add_frame(self, seq: int, frame: RGBDFrame | FrameLoader, pub_ns: int | None = None,
                  size: int | None = None) -> bool:
        """Buffer a frame (or its loader, ``size`` bytes held) until its correction arrives; False
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
        if isinstance(frame, RGBDFrame):
            t0 = time.perf_counter()
            wi = prepare_warp(frame, self.warp)
            self._prepared[(self.numbering, seq)] = (wi, (time.perf_counter() - t0) * 1e3)
        while self.buffered > self.max_frames or (self.max_bytes is not None and self.held_bytes > self.max_bytes
                                                  and self.buffered > 1):
            n = min(k for k, h in self._held.items() if h)
            self._take(n, next(iter(self._held[n])))
            self.dropped += 1
        return True

    def _take(self, n: int, seq: int, keep_prepared: bool = False) -> RGBDFrame | FrameLoader | None:
        """A held frame (or its loader) of numbering ``n`` out of the buffer (None: not held)."""
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

    def _load(self, numbering: int, seq: int) -> RGBDFrame | None:
        f = self._take(numbering, seq, keep_prepared=True)
        if f is None or isinstance(f, RGBDFrame):
            return f
        try:
            return f()
        except Exception as e:  # noqa: BLE001 - a frame that cannot be decoded is reported, not fatal
            self.bad.append({"seq": seq, "error": f"{type(e).__name__}: {e}"})
            return None

    @staticmethod
    def _restarts(batch: list[Correction]) -> bool:
        """Whether a batch begins a new numbering: the restart correction of a renumbering's break."""
        return starts_numbering(batch[0])

    def numbering_of(self, batch: list[Correction]) -> int:
        """The numbering a correction batch belongs to. The batch that restarts the path in a new
        numbering belongs to the next numbering frames were taken in (if the frames have not shown
        one, this stage never saw the old numbering: the current one); any other batch to the
        numbering the corrections reached, unless only a later numbering holds any of its frames
        (the restart batch was lost or rendered before its frames came)."""
        later = sorted(n for n in self._held if n > self._corr)
        if self._restarts(batch):
            return later[0] if later else self._corr
        seqs = {c.seq for c in batch}
        for n in [self._corr, *later]:
            if not seqs.isdisjoint(self._held.get(n, {})):
                return n
        return self._corr

    def can_render(self, batch: list[Correction]) -> bool:
        """Whether a correction batch can be rendered now, before the frames it waits for could come:
        all its frames are held, or a newer frame of its numbering (or a later numbering) has been
        taken, so a missing one will never come. A batch that restarts the path in a new numbering
        waits for its frames while the frames have not shown the renumbering yet."""
        if not batch:
            return True
        n = self.numbering_of(batch)
        held = self._held.get(n, {})
        seqs = [c.seq for c in batch]
        if all(s in held for s in seqs):
            return True
        if self._restarts(batch) and n == self._corr:
            return False
        newest = self._newest_in.get(n)
        return n < self.numbering or (newest is not None and newest > max(seqs))

    def render_batch(self, corrections: list[Correction]) -> list[StabilizedFrame]:
        """Render one correction batch and the orphans it reveals, in seq order (see :meth:`iter_batch`)."""
        return list(self.iter_batch(corrections))

    def iter_batch(self, corrections: list[Correction]) -> Iterator[StabilizedFrame]:
        """Render one correction batch and the orphans it reveals, yielding frames in seq order.

        Each frame is rendered only when the caller asks for it, so a service can publish the
        first frame while the rest of the batch waits. What it waits for is what its zoom needs:
        with the border fill and zooms planned with the path (``auto``), its own warp and border
        estimate and those of the ``fill_lookahead`` frames after it (docs/method.md (14a));
        otherwise every warp of the batch and its zoom track. Orphans are held frames older than the
        batch's newest that the batch does not cover (skipped upstream: no correction
        will ever come); each is framed on its own, uncorrected and flagged, unless a correction of
        the batch names it as shed by the flow stage (then it is let go: :meth:`let_go`)."""
        if not corrections:
            return
        n = self.numbering_of(corrections)
        stale: list[_Plan] = []
        for old in sorted(k for k in self._held if k < n):  # the corrections moved on: none will reach these
            for seq in list(self._held[old]):
                self.orphans += 1
                stale += self._plan([orphan_correction(seq, STALE)], old)
            del self._held[old]
            self._newest_in.pop(old, None)
        self._corr = n
        self.let_go([s for c in corrections for s in c.shed], n)  # shed by flow: not orphans
        held = self._held.get(n, {})
        last = max(c.seq for c in corrections)
        covered = {c.seq for c in corrections}
        plans: list[_Plan] = []
        for seq in [s for s in held if s < last and s not in covered]:
            self.orphans += 1
            plans += self._plan([orphan_correction(seq)], n)
        plans += self._plan(corrections, n)
        if len(plans) > len(corrections):
            plans.sort(key=lambda p: p.c.seq)
        for p in stale:  # the old numbering's last frames first, as they are
            yield self._timed(p, lambda p=p: (render(p.f.color, p.mesh, p.zoom), p.zoom))
        ahead = [FillSource(p.c.seq, p.c.chain, p.c.camera, p.f.color, p.f.intrinsics.K) for p in plans
                 if p.c.camera is not None] if self.framing.fill_frames else []
        if ahead and self.framing.mode == "auto":
            # each frame as soon as its zoom is known: its own and the look-ahead's estimates made
            zooms = self.zoom.cover_frames([p.zoom for p in plans], lambda j: self._need(plans[j], ahead))
            for p, z in zip(plans, zooms):
                if z != p.zoom:  # zoomed in further: the samples read from those at the plan's zoom
                    p.samples = rezoom_samples(p.samples, p.mesh.width, p.mesh.height, p.zoom, z)
                    p.zoom = z
                yield self._timed(p, lambda p=p: self._render(p, ahead))
            return
        for p in plans:
            yield self._timed(p, lambda p=p: self._render(p, ahead))

    def _timed(self, p: _Plan, draw: Callable[[], tuple[np.ndarray, float]]) -> StabilizedFrame:
        """The stabilized frame ``draw`` renders for plan ``p`` (its warp solved first), its render time
        and its framing share recorded (one sample per frame)."""
        mesh = self._solve(p)
        t0 = time.perf_counter()
        image, z = draw()
        sf = StabilizedFrame(p.c.seq, p.f.timestamp_ns, image, p.c, z, mesh,
                             p.f.color if self.keep_inputs else None, p.numbering)
        self.timer.add("render", (time.perf_counter() - t0) * 1e3)
        self.timer.add("framing", p.framing_ms)
        return sf

    def _solve(self, p: _Plan) -> MeshWarp:
        """Plan ``p``'s warp, solved now if it was not (its time, with its preparation's, one "warp" sample)."""
        if p.mesh is None:
            t0 = time.perf_counter()
            p.mesh = solve_warp(p.f, p.c.point_transform, self.warp, p.prepared)
            p.prepared = None
            self.timer.add("warp", (time.perf_counter() - t0) * 1e3 + p.prep_ms)
        return p.mesh

    def _sources(self, c: Correction, ahead: list[FillSource]) -> list[FillSource]:
        if c.camera is None:
            return []
        return ordered_sources(c.seq, c.chain, self._past + ahead, self.framing.fill_frames)

    def _need(self, p: _Plan, ahead: list[FillSource]) -> float:
        """The zoom plan ``p`` needs so that the border fill covers what its mesh leaves at the planned zoom
        (docs/method.md 5.4), estimated before rendering, on every 4th pixel; the plan keeps the map
        samples at its zoom for its render (:func:`~quick_stream.core.render.mapping.rezoom_samples`
        reads them where the zoom rises). Its time is the plan's framing share."""
        mesh = self._solve(p)
        t0 = time.perf_counter()
        p.samples = map_samples(mesh, p.zoom)
        need = covered_zoom(mesh, p.f.depth, p.f.intrinsics.K, p.zoom,
                            None if p.c.camera is None else p.c.camera @ p.c.matrix,
                            self._sources(p.c, ahead), samples=p.samples)
        p.framing_ms += (time.perf_counter() - t0) * 1e3
        return need

    def _render(self, p: _Plan, ahead: list[FillSource]) -> tuple[np.ndarray, float]:
        """One frame at its zoom, its border filled from its neighbours (the batch's frames ``ahead``
        and the last frames rendered before it) when the correction carries a camera pose;
        what fill leaves uncovered is zoomed away (docs/method.md 5.4). Returns (image, zoom)."""
        c, f, mesh, zoom = p.c, p.f, self._solve(p), p.zoom
        reach = self.framing.fill_frames
        if not reach:
            return render(f.color, mesh, zoom), zoom
        sources = self._sources(c, ahead)
        virtual = c.camera @ c.matrix if c.camera is not None else None
        samples, filled = map_samples(mesh, zoom) if p.samples is None else p.samples, False
        for _ in range(3):
            image, uncovered, depth = render_covered(f.color, f.depth, mesh, zoom, samples=samples)
            if depth is None:
                break
            if sources:
                uncovered = fill_border(image, uncovered, depth, f.intrinsics.K, zoom, virtual, sources)
                filled = True
            if not uncovered.any() or self.framing.mode != "auto" or zoom >= self.framing.fill_zoom_max:
                break
            raised = min(raise_for(uncovered, zoom) * (1.0 + 1e-6), self.framing.fill_zoom_max)
            samples = rezoom_samples(samples, mesh.width, mesh.height, zoom, raised)
            zoom = raised
        self.filled += filled
        self.fill_raised += zoom > p.zoom
        self.bordered += depth is not None and bool(uncovered.any())
        if c.camera is not None:
            self._past = (self._past + [FillSource(c.seq, c.chain, c.camera, f.color, f.intrinsics.K)])[-reach:]
        return image, zoom

    def flush(self) -> list[StabilizedFrame]:
        """End of stream: render every frame still waiting as an orphan (no correction will come),
        numbering by numbering."""
        out: list[StabilizedFrame] = []
        for n in sorted(self._held):
            for seq in list(self._held[n]):
                self.orphans += 1
                for p in self._plan([orphan_correction(seq, STALE if n < self.numbering else ORPHAN)], n):
                    out.append(self._timed(p, lambda p=p: (render(p.f.color, p.mesh, p.zoom), p.zoom)))
        return out

    def _plan(self, corrections: list[Correction], numbering: int) -> list[_Plan]:
        """Load the frames (of ``numbering``) and the batch's zoom track; the warps are solved when a
        frame needs its own (:meth:`_solve`), unless the zoom track needs them all first."""
        t0 = time.perf_counter()
        items = []
        for c in corrections:
            f = self._load(numbering, c.seq)
            if f is None:
                self.missing += 1
                continue
            prepared, ms = self._prepared.pop((numbering, c.seq), (None, 0.0))
            items.append(_Plan(c, f, None, 1.0, numbering, 0.0, prepared=prepared, prep_ms=ms))
        if not items:
            return []
        t1 = time.perf_counter()
        for p in items:  # loading is the warp's share (decoding, where frames were held compressed)
            p.prep_ms += (t1 - t0) * 1e3 / len(items)
        planned = [p.c.zoom for p in items]
        if self.framing.fill_frames and self.framing.mode == "auto" and None not in planned:
            # the plan counted on the border fill (docs/method.md 5.4): rendering zooms further only
            # where fill leaves a border, not where the frame's own mesh does
            zooms = np.clip(np.asarray(planned, dtype=np.float64), 1.0, None)
            self.zoom.last = float(zooms[-1])
        else:
            meshes = [self._solve(p) for p in items]
            t1 = time.perf_counter()  # the warps' time is theirs
            zooms = segment_zooms(meshes, self.framing, self.zoom, planned)
        share = (time.perf_counter() - t1) * 1e3 / len(items)
        for p, z in zip(items, zooms):
            p.zoom, p.framing_ms = float(z), share
        return items

"""The render stage, shared by the in-process stabilizer and the ``render`` service.

    frames + releases -> RenderStage -> StabilizedFrame

:class:`RenderStage` renders a release (what one planner call released,
:mod:`quick_stream.core.stages`) as a whole: it takes the release's frames out of its
:class:`~quick_stream.core.frame_hold.FrameHold` (``hold``: frames wait there, per numbering of the
stream, until their corrections come), plans the release's zooms (one zoom track,
:func:`~quick_stream.core.render.segment_zooms`, or the path's planned zooms), solves each warp when
first needed and renders each frame with its border filled from its neighbours
(:class:`~quick_stream.core.render.filler.BorderFiller`, ``filler``). A frame that no correction will
ever reach (an *orphan*, skipped upstream, or left in a numbering the corrections moved past) is
rendered with no correction, flagged, instead of being held forever. The policy around it
(corrections regrouped into the planner's releases, when a release renders, latency stamps, the
end of a stream) is :mod:`quick_stream.core.release`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from .frame import RGBDFrame
from .frame_hold import FrameHold, FrameLoader
from .path.planner import Correction
from .render import FramingParams, MeshWarp, WarpParams, ZoomSmoother, render, segment_zooms, solve_warp
from .render.filler import BorderFiller, source_of
from .render.mapping import map_samples, rezoom_samples
from .render.warp import WarpInput, prepare_warp
from .timing import StageTimer

__all__ = ["RenderStage", "StabilizedFrame", "FrameLoader", "ORPHAN", "STALE", "orphan_correction"]


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
    share of the release's framing time (ms) and, when the border fill's estimate made them, the map
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
    """Renders releases against the frames its ``hold`` keeps (module docstring).

    ``max_frames``, ``max_bytes``: what the hold keeps at most
    (:class:`~quick_stream.core.frame_hold.FrameHold`); a correction whose frame is gone is counted in
    ``missing``, a frame rendered without a correction in ``orphans``; the border fill's counts are
    the ``filler``'s."""

    def __init__(self, warp: WarpParams | None = None, framing: FramingParams | None = None,
                 max_frames: int = 240, keep_inputs: bool = False, max_bytes: int | None = None) -> None:
        self.warp = warp or WarpParams()
        self.framing = framing or FramingParams()
        self.framing.validate()
        self.zoom = ZoomSmoother(self.framing)
        self.keep_inputs = keep_inputs
        self.hold = FrameHold(max_frames, max_bytes, prepare=lambda f: prepare_warp(f, self.warp))
        self.filler = BorderFiller(self.framing)
        self.timer = StageTimer()
        self.missing = 0
        self.orphans = 0

    def add_frame(self, seq: int, frame: RGBDFrame | FrameLoader, pub_ns: int | None = None,
                  size: int | None = None) -> bool:
        """Hold a frame (or its loader) until its release comes (:meth:`FrameHold.add
        <quick_stream.core.frame_hold.FrameHold.add>`: False when let go, ValueError when refused)."""
        return self.hold.add(seq, frame, pub_ns, size)

    def iter_release(self, corrections: list[Correction]) -> Iterator[StabilizedFrame]:
        """Render one release and the orphans it reveals, yielding frames in seq order.

        Each frame is rendered only when the caller asks for it, so a service can publish the
        first frame while the rest of the release waits. What it waits for is what its zoom needs:
        with the border fill and zooms planned with the path (``auto``), its own warp and border
        estimate and those of the ``fill_lookahead`` frames after it (docs/method.md (14a));
        otherwise every warp of the release and its zoom track. Orphans are held frames older than the
        release's newest that the release does not cover (skipped upstream: no correction
        will ever come); each is framed on its own, uncorrected and flagged, unless a correction of
        the release names it as shed by the flow stage (then it is let go:
        :meth:`FrameHold.let_go <quick_stream.core.frame_hold.FrameHold.let_go>`)."""
        if not corrections:
            return
        hold = self.hold
        n = hold.numbering_of(corrections)
        stale: list[_Plan] = []
        for old, seq in hold.reach(n):  # the corrections moved on: none will reach these
            self.orphans += 1
            stale += self._plan([orphan_correction(seq, STALE)], old)
        hold.forget_empty()
        hold.let_go([s for c in corrections for s in c.shed], n)  # shed by flow: not orphans
        last = max(c.seq for c in corrections)
        covered = {c.seq for c in corrections}
        plans: list[_Plan] = []
        for seq in [s for s in hold.waiting(n) if s < last and s not in covered]:
            self.orphans += 1
            plans += self._plan([orphan_correction(seq)], n)
        plans += self._plan(corrections, n)
        if len(plans) > len(corrections):
            plans.sort(key=lambda p: p.c.seq)
        for p in stale:  # the old numbering's last frames first, as they are
            yield self._timed(p, lambda p=p: (render(p.f.color, p.mesh, p.zoom), p.zoom))
        ahead = [source_of(p.c, p.f) for p in plans if p.c.camera is not None] if self.framing.fill_frames else []
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

    def _need(self, p: _Plan, ahead: list) -> float:
        """The zoom plan ``p`` needs so that the border fill covers what its mesh leaves at the planned
        zoom (:meth:`BorderFiller.need <quick_stream.core.render.filler.BorderFiller.need>`), on every
        4th pixel; the plan keeps the map samples at its zoom for its render
        (:func:`~quick_stream.core.render.mapping.rezoom_samples` reads them where the zoom rises).
        Its time is the plan's framing share."""
        mesh = self._solve(p)
        t0 = time.perf_counter()
        p.samples = map_samples(mesh, p.zoom)
        need = self.filler.need(p.c, p.f, mesh, p.zoom, p.samples, ahead)
        p.framing_ms += (time.perf_counter() - t0) * 1e3
        return need

    def _render(self, p: _Plan, ahead: list) -> tuple[np.ndarray, float]:
        """One frame at its zoom, its border filled (:meth:`BorderFiller.render
        <quick_stream.core.render.filler.BorderFiller.render>`). Returns (image, zoom)."""
        return self.filler.render(p.c, p.f, self._solve(p), p.zoom, p.samples, ahead)

    def flush(self) -> list[StabilizedFrame]:
        """End of stream: render every frame still waiting as an orphan (no correction will come),
        numbering by numbering."""
        out: list[StabilizedFrame] = []
        for n, seq in self.hold.everything():
            self.orphans += 1
            for p in self._plan([orphan_correction(seq, STALE if n < self.hold.numbering else ORPHAN)], n):
                out.append(self._timed(p, lambda p=p: (render(p.f.color, p.mesh, p.zoom), p.zoom)))
        return out

    def _plan(self, corrections: list[Correction], numbering: int) -> list[_Plan]:
        """Load the frames (of ``numbering``) and the release's zoom track; the warps are solved when a
        frame needs its own (:meth:`_solve`), unless the zoom track needs them all first."""
        t0 = time.perf_counter()
        items = []
        for c in corrections:
            f, prepared, ms = self.hold.load(numbering, c.seq)
            if f is None:
                self.missing += 1
                continue
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

"""The pipeline's three stateful stages, shared by the in-process stabilizer and the services.

    frames -> FlowStage -> SceneFlowResult -> MotionStage -> MotionEstimate + correction batches
    frames + correction batches -> RenderStage -> StabilizedFrame

:class:`~quick_stream.stabilizer.Stabilizer` chains them in one process; the
``flow``, ``motion`` and ``render`` services each drive one of them from Zenoh
messages (docs/architecture.md). Because the services add only transport, a
stream run through the services gives bit-for-bit the offline result
(tests/test_services_e2e.py).

A *correction batch* is what one planner call released (the first frame's
correction; a closed segment; a segment closed early by an invalid motion plus
the restart frame). The renderer frames each batch as a whole (one zoom track,
:func:`~quick_stream.render.segment_zooms`), so the batches travel as batches.

Streams with holes: :class:`MotionStage` turns a gap between consecutive flows
(the flow stage skipped frames or was restarted) into an invalid motion, so the
path restarts there and the frames are flagged; :class:`RenderStage` renders a
frame that no correction will ever reach (an *orphan*, skipped upstream) with
no correction, flagged, instead of holding it forever.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from .continuity import ContinuityCheck, ContinuityParams, JumpGuard
from .frame import RGBDFrame
from .motion import MotionEstimate, MotionEstimator, MotionParams, invalid_motion
from .motion_pipeline import StageTimer
from .path.budget import FrameModel
from .path.planner import Correction, PathPlanner, PlannerParams
from .render import FramingParams, MeshWarp, WarpParams, ZoomSmoother, render, segment_zooms, solve_warp
from .render.fill import FillSource, covered_zoom, fill_border, ordered_sources, raise_for
from .render.mapping import render_covered
from .render.warp import WarpInput, prepare_warp
from .sceneflow import SceneFlow, SceneFlowParams, SceneFlowResult

FrameLoader = Callable[[], RGBDFrame]


class FlowStage:
    """Scene flow between each good frame and the previous one (one instance per stream).

    Each frame first passes :class:`~quick_stream.continuity.ContinuityCheck` (counted in
    ``check.counts``); ``notes`` holds what it reported of the last frame pushed.
    """

    def __init__(self, params: SceneFlowParams | None = None, continuity: ContinuityParams | None = None) -> None:
        self.flow = SceneFlow(params)
        self.check = ContinuityCheck(continuity)
        self.notes: list[str] = []
        self._prev: RGBDFrame | None = None

    def push(self, frame: RGBDFrame) -> SceneFlowResult | None:
        """Add the next frame; returns the flow from the previous good frame to it (None for the first).

        A frame the check refuses (no valid depth, duplicate, out of order) raises
        :class:`~quick_stream.continuity.FrameRefused` (a ValueError) and is not used. Across a
        discontinuity (too many missing frames, a timestamp jump, a size change) the flow is
        empty and its ``problem`` names the discontinuity, so the path restarts there.
        """
        prev = self._prev
        verdict = self.check.inspect(prev, frame)
        self.notes = verdict.notes
        self._prev = frame
        if prev is None:
            return None
        if verdict.brk:
            return SceneFlowResult.empty(prev, frame, verdict.brk)
        return self.flow.compute(prev, frame)

    def restart(self) -> None:
        """End of stream: the next frame starts a new chain (the counters go on)."""
        self._prev = None


class MotionStage:
    """Motion estimation plus path planning: flows in, motions and correction batches out."""

    def __init__(self, motion: MotionParams | None = None, planner: PlannerParams | None = None,
                 warp: WarpParams | None = None) -> None:
        """``warp``: the render stage's warp parameters (the path's crop budget fits the same mesh)."""
        self.estimator = MotionEstimator(motion)
        self.planner = PathPlanner(planner, warp)
        if self.planner.params.group != self.estimator.params.group:
            raise ValueError(f"motion group {self.estimator.params.group!r} and path group "
                             f"{self.planner.params.group!r} differ")
        self._last: int | None = None  # seq of the newest frame the path has reached
        self.gaps = 0
        self.timer = StageTimer()

    @property
    def started(self) -> bool:
        return self._last is not None

    def start(self, seq: int) -> list[Correction]:
        """First frame of the stream: its correction batch (identity, a keyframe)."""
        self._last = seq
        return self.planner.start(seq)

    def push(self, flow: SceneFlowResult) -> tuple[list[MotionEstimate], list[list[Correction]]]:
        """Add one flow; returns the motions made and the correction batches released, in order.

        Starts the path at ``flow.seq`` if not started. A flow that does not begin
        at the newest frame reached (frames skipped upstream) first gets an invalid
        motion across the gap. A flow that ends at or before that frame is refused
        with ValueError (stale or duplicate).
        """
        batches: list[list[Correction]] = []
        motions: list[MotionEstimate] = []
        if self._last is None:
            batches.append(self.start(flow.seq))
        if flow.seq_next <= self._last:
            raise ValueError(f"flow {flow.seq}->{flow.seq_next} ends at or before frame {self._last} "
                             "(stale or duplicate)")
        p = self.estimator.params
        if flow.seq != self._last:
            self.gaps += 1
            gap = invalid_motion(self._last, flow.seq, p.group, p.estimator,
                                 f"no scene flow from frame {self._last} to {flow.seq} (frames skipped upstream)")
            motions.append(gap)
            batches.append(self.planner.push(gap))
        t0 = time.perf_counter()
        m = self.estimator.estimate(flow)
        t1 = time.perf_counter()
        motions.append(m)
        batches.append(self.planner.push(m, self.frame_model(flow)))
        self.timer.add("motion", (t1 - t0) * 1e3)
        self.timer.add("path", (time.perf_counter() - t1) * 1e3)
        self._last = flow.seq_next
        return motions, [b for b in batches if b]

    def frame_model(self, flow: SceneFlowResult) -> FrameModel | None:
        """The 3D points of the flow's second frame (x + v at the pixels the flow reached), for the crop budget."""
        b = self.planner.params.budget
        if not (self.planner.params.mode == "smooth" and b.enabled) or flow.problem or len(flow) == 0:
            return None
        K = flow.intrinsics_next
        return FrameModel.from_points(K.width, K.height, K, flow.pixels_next, flow.points + flow.displacements,
                                      b.model_points)

    def finish(self) -> list[list[Correction]]:
        """End of stream: the last segment's batch (if any)."""
        b = self.planner.finish() if self.started else []
        return [b] if b else []


@dataclass
class StabilizedFrame:
    seq: int
    timestamp_ns: int
    image: np.ndarray  # BGR uint8, same size as the input
    correction: Correction
    zoom: float
    mesh: MeshWarp
    input_image: np.ndarray | None = None  # kept only when the caller asks (metrics)

    @property
    def flags(self) -> list[str]:
        out = []
        if not self.correction.valid:
            out.append(self.correction.reason)
        if not self.mesh.ok:
            out.append(f"warp: {self.mesh.reason}")
        return out


def orphan_correction(seq: int) -> Correction:
    """What a frame no correction reached is rendered with: none, flagged."""
    return Correction(seq, np.eye(4), -1, False, False, "no correction: frame skipped upstream")


class RenderStage:
    """Holds frames until their correction batch arrives, then warps, frames and renders them.

    Frames may be given decoded or as a loader (decoded only when rendered, so a
    service buffers compressed bytes). At most ``max_frames`` wait; beyond that the
    oldest is dropped and counted (``dropped``); a correction whose frame is gone is
    counted in ``missing``; a frame that cannot be loaded is reported in ``bad``.
    """

    def __init__(self, warp: WarpParams | None = None, framing: FramingParams | None = None,
                 max_frames: int = 240, keep_inputs: bool = False) -> None:
        self.warp = warp or WarpParams()
        self.framing = framing or FramingParams()
        self.framing.validate()
        self.zoom = ZoomSmoother(self.framing)
        self.max_frames = max_frames
        self.keep_inputs = keep_inputs
        self.timer = StageTimer()
        self._frames: OrderedDict[int, RGBDFrame | FrameLoader] = OrderedDict()
        self._prepared: dict[int, WarpInput] = {}  # warp inputs of decoded frames, made on arrival
        self.dropped = 0
        self.missing = 0
        self.orphans = 0
        self.bad: list[dict] = []
        self._past: list[FillSource] = []  # the last fill_frames rendered frames the border fill can read
        self.filled = 0  # frames whose border was filled from neighbours
        self.fill_raised = 0  # frames zoomed in beyond their plan because fill left a border
        self.jumps = JumpGuard()  # the flow stage's defaults: what it refuses gets no correction
        self._newest: int | None = None  # the newest frame taken

    @property
    def buffered(self) -> int:
        return len(self._frames)

    def add_frame(self, seq: int, frame: RGBDFrame | FrameLoader) -> None:
        """Buffer a frame (or its loader) until its correction arrives. Refused (ValueError): one not
        after the newest buffered, and one far ahead of the newest taken that no run of frames
        confirms (:class:`~quick_stream.continuity.JumpGuard`, as the flow stage does)."""
        if self._frames and seq <= next(reversed(self._frames)):
            raise ValueError(f"frame {seq} is not after the newest buffered frame (out of order or duplicate)")
        if not self.jumps.admit(self._newest, seq):
            raise ValueError(f"frame {seq} is {seq - self._newest} frames ahead of frame {self._newest} "
                             f"(more than {self.jumps.max_jump}): refused unless frames in a row continue from it")
        self._newest = seq
        self._frames[seq] = frame
        if isinstance(frame, RGBDFrame):
            self._prepared[seq] = prepare_warp(frame, self.warp)
        while len(self._frames) > self.max_frames:
            old, _ = self._frames.popitem(last=False)
            self._prepared.pop(old, None)
            self.dropped += 1

    def _load(self, seq: int) -> RGBDFrame | None:
        f = self._frames.pop(seq, None)
        if f is None or isinstance(f, RGBDFrame):
            return f
        try:
            return f()
        except Exception as e:  # noqa: BLE001 - a frame that cannot be decoded is reported, not fatal
            self.bad.append({"seq": seq, "error": f"{type(e).__name__}: {e}"})
            return None

    def render_batch(self, corrections: list[Correction]) -> list[StabilizedFrame]:
        """Render one correction batch and the orphans it reveals, in seq order (see :meth:`iter_batch`)."""
        return list(self.iter_batch(corrections))

    def iter_batch(self, corrections: list[Correction]) -> Iterator[StabilizedFrame]:
        """Render one correction batch and the orphans it reveals, yielding frames in seq order.

        Warps and the batch's zoom track are solved first (cheap); each frame is then
        rendered only when the caller asks for it, so a service can publish the first
        frame while the rest of the batch waits. Orphans are held frames older than the
        batch's newest that the batch does not cover (skipped upstream: no correction
        will ever come); each is framed on its own, uncorrected and flagged."""
        if not corrections:
            return
        last = max(c.seq for c in corrections)
        covered = {c.seq for c in corrections}
        plans: list[tuple[Correction, RGBDFrame, MeshWarp, float]] = []
        for seq in [s for s in self._frames if s < last and s not in covered]:
            self.orphans += 1
            plans += self._plan([orphan_correction(seq)])
        plans += self._plan(corrections)
        if len(plans) > len(corrections):
            plans.sort(key=lambda x: x[0].seq)
        ahead = [FillSource(c.seq, c.chain, c.camera, f.color, f.intrinsics.K) for c, f, _, _ in plans
                 if c.camera is not None] if self.framing.fill_frames else []
        if ahead and self.framing.mode == "auto":
            plans = self._cover(plans, ahead)
        for c, f, mesh, z in plans:
            t0 = time.perf_counter()
            image, z = self._render(c, f, mesh, z, ahead)
            sf = StabilizedFrame(c.seq, f.timestamp_ns, image, c, z, mesh, f.color if self.keep_inputs else None)
            self.timer.add("render", (time.perf_counter() - t0) * 1e3)
            yield sf

    def _sources(self, c: Correction, ahead: list[FillSource]) -> list[FillSource]:
        if c.camera is None:
            return []
        return ordered_sources(c.seq, c.chain, self._past + ahead, self.framing.fill_frames)

    def _cover(self, plans: list, ahead: list[FillSource]) -> list:
        """Zooms raised, smoothly, where the border fill will not cover what the mesh leaves at the
        planned zoom (docs/method.md 5.4): estimated before rendering, on every 4th pixel."""
        t0 = time.perf_counter()
        need = [covered_zoom(mesh, f.depth, f.intrinsics.K, z, None if c.camera is None else c.camera @ c.matrix,
                             self._sources(c, ahead)) for c, f, mesh, z in plans]
        zooms = self.zoom.cover([z for *_, z in plans], need)
        self.timer.add("framing", (time.perf_counter() - t0) * 1e3 / max(len(plans), 1))
        return [(c, f, mesh, float(z)) for (c, f, mesh, _), z in zip(plans, zooms)]

    def _render(self, c: Correction, f: RGBDFrame, mesh: MeshWarp, zoom: float,
                ahead: list[FillSource]) -> tuple[np.ndarray, float]:
        """One frame at ``zoom``, its border filled from its neighbours (the batch's frames ``ahead``
        and the last frames rendered before it) when the correction carries a camera pose;
        what fill leaves uncovered is zoomed away (docs/method.md 5.4). Returns (image, zoom)."""
        reach = self.framing.fill_frames
        if not reach:
            return render(f.color, mesh, zoom), zoom
        sources = self._sources(c, ahead)
        virtual = c.camera @ c.matrix if c.camera is not None else None
        planned, filled = zoom, False
        for _ in range(3):
            image, uncovered, depth = render_covered(f.color, f.depth, mesh, zoom)
            if depth is None:
                break
            if sources:
                uncovered = fill_border(image, uncovered, depth, f.intrinsics.K, zoom, virtual, sources)
                filled = True
            if not uncovered.any() or self.framing.mode != "auto" or zoom >= self.framing.fill_zoom_max:
                break
            zoom = min(raise_for(uncovered, zoom) * (1.0 + 1e-6), self.framing.fill_zoom_max)
        self.filled += filled
        self.fill_raised += zoom > planned
        if c.camera is not None:
            self._past = (self._past + [FillSource(c.seq, c.chain, c.camera, f.color, f.intrinsics.K)])[-reach:]
        return image, zoom

    def has_frames(self, seqs: list[int]) -> bool:
        return all(s in self._frames for s in seqs)

    def flush(self) -> list[StabilizedFrame]:
        """End of stream: render every frame still waiting as an orphan (no correction will come)."""
        out: list[StabilizedFrame] = []
        for seq in list(self._frames):
            self.orphans += 1
            for c, f, mesh, z in self._plan([orphan_correction(seq)]):
                out.append(StabilizedFrame(c.seq, f.timestamp_ns, render(f.color, mesh, z), c, z, mesh,
                                           f.color if self.keep_inputs else None))
        return out

    def _plan(self, corrections: list[Correction]) -> list[tuple[Correction, RGBDFrame, MeshWarp, float]]:
        """Load the frames, solve their warps and the batch's zoom track."""
        t0 = time.perf_counter()
        items = []
        for c in corrections:
            f = self._load(c.seq)
            if f is None:
                self.missing += 1
                continue
            items.append((c, f, solve_warp(f, c.point_transform, self.warp, self._prepared.pop(c.seq, None))))
        if not items:
            return []
        t1 = time.perf_counter()
        planned = [c.zoom for c, _, _ in items]
        if self.framing.fill_frames and self.framing.mode == "auto" and None not in planned:
            # the plan counted on the border fill (docs/method.md 5.4): rendering zooms further only
            # where fill leaves a border, not where the frame's own mesh does
            zooms = np.clip(np.asarray(planned, dtype=np.float64), 1.0, None)
            self.zoom.last = float(zooms[-1])
        else:
            zooms = segment_zooms([m for _, _, m in items], self.framing, self.zoom, planned)
        t2 = time.perf_counter()
        n = len(items)
        for _ in range(n):  # per-frame samples (the batch's average)
            self.timer.add("warp", (t1 - t0) * 1e3 / n)
            self.timer.add("framing", (t2 - t1) * 1e3 / n)
        return [(c, f, mesh, float(z)) for (c, f, mesh), z in zip(items, zooms)]


class ReleaseGroups:
    """Corrections grouped by planner release; yields complete releases in order.

    The motion service sends a release's corrections back to back, so a release still
    incomplete when another one starts arriving lost its sender mid-way (a killed motion
    service): it is handed over with what arrived (``abandoned``). A restarted motion
    service numbers releases from 0 again; a correction that does not fit the open release
    of that number (other size, or an index already there) starts a new one.
    """

    def __init__(self) -> None:
        self._open: dict[int, tuple[int, dict[int, Correction]]] = {}
        self.ready: list[tuple[int, list[Correction], float]] = []  # (release, batch, completed at)
        self.unbatched = 0
        self.abandoned = 0

    def _hand_over(self, rel: int) -> None:
        _, got = self._open.pop(rel)
        self.ready.append((rel, [got[i] for i in sorted(got)], time.monotonic()))
        self.ready.sort(key=lambda r: r[1][0].seq)

    def add(self, c: Correction, batch: tuple[int, int, int] | None) -> None:
        if batch is None:  # a sender without release tags: each correction is its own batch
            self.unbatched += 1
            self.ready.append((-1, [c], time.monotonic()))
            return
        rel, idx, size = batch
        for other in [r for r in self._open if r != rel]:
            self.abandoned += 1
            self._hand_over(other)
        if rel in self._open and (self._open[rel][0] != size or idx in self._open[rel][1]):
            self.abandoned += 1
            self._hand_over(rel)
        _, got = self._open.setdefault(rel, (size, {}))
        got[idx] = c
        if len(got) == size:
            self._hand_over(rel)

    def flush_incomplete(self) -> int:
        """End of stream: hand over partial releases (what arrived of them); returns how many."""
        n = len(self._open)
        for rel in sorted(self._open):
            self._hand_over(rel)
        return n

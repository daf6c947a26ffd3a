"""The pipeline's three stateful stages, shared by the in-process stabilizer and the services.

    frames -> FlowStage -> SceneFlowResult -> MotionStage -> MotionEstimate + releases   (FlowStage: flow_stage.py)
    frames + releases -> RenderStage -> StabilizedFrame   (quick_stream/core/render_stage.py)

:class:`~quick_stream.core.stabilizer.Stabilizer` chains them in one process; the
``flow``, ``motion`` and ``render`` services each drive one of them from Zenoh
messages (docs/architecture.md). Because the services add only transport, a
stream run through the services gives bit-for-bit the offline result
(tests/integration/test_services_e2e.py).

A *release* is what one planner call released (the first frame's
correction; a closed segment; a segment closed early by an invalid motion plus
the restart frame). The renderer frames each release as a whole (one zoom track,
:func:`~quick_stream.core.render.segment_zooms`), so the releases travel as releases: tagged as
releases (:mod:`quick_stream.core.release`).

:class:`~quick_stream.core.flow_stage.FlowDriver` and :class:`MotionDriver` are the flow and motion stages over a service's life
(what each refuses, counted and reported; taking over after a restarted service's predecessor; one
stream after another, the counters going on); the services, the in-process
:class:`~quick_stream.core.stabilizer.Stabilizer` and ``quick-stream rerun`` run them
(docs/architecture.md), the render side is :class:`~quick_stream.core.release.RenderDriver`.

Streams with holes: :class:`MotionStage` turns a gap between consecutive flows
(the flow stage skipped frames or was restarted) into an invalid motion, so the
path restarts there and the frames are flagged; :class:`RenderStage` renders a
frame that no correction will ever reach (an *orphan*, skipped upstream) with
no correction, flagged, instead of holding it forever. A stream renumbered lower
(confirmed by a run of frames, :class:`~quick_stream.core.continuity.JumpGuard`) is a break:
the flow goes back, :class:`MotionStage` restarts the path there, and
:class:`RenderStage` keeps the old numbering's frames apart from the new one's.
"""
from __future__ import annotations

import logging
import time
from typing import Collection

from .continuity import AheadHold, breaks_stream, restarts_numbering
from .logs import log_or_quiet
from .motion import KINDS, MotionEstimate, MotionEstimator, MotionParams, invalid_motion
from .motion.chain import MotionBridge, split_over
from .params import check_groups
from .path.frame_model import FrameModel
from .path.planner import Correction, PathPlanner, PlannerParams
from .release_tags import ReleaseNumbering, Tag
from .render.warp import WarpParams
from .sceneflow import SceneFlowResult
from .timing import StageTimer


class MotionStage:
    """Motion estimation plus path planning: flows in, motions and releases out."""

    def __init__(self, motion: MotionParams | None = None, planner: PlannerParams | None = None,
                 warp: WarpParams | None = None, keep_segments: int | None = None) -> None:
        """``warp``: the render stage's warp parameters (the path's crop budget fits the same mesh);
        ``keep_segments``: the segment accounts the planner keeps (:class:`~.path.planner.PathPlanner`)."""
        self.estimator = MotionEstimator(motion)
        self.bridge = MotionBridge(self.estimator.params.bridge_frames)
        self.planner = PathPlanner(planner, warp, keep_segments)
        check_groups(self.estimator.params, self.planner.params)
        self._last: int | None = None  # seq of the newest frame the path has reached
        self.gaps = 0
        self.renumberings = 0  # breaks to a new numbering taken (the path restarted at a lower seq)
        self._break: tuple[int, int] | None = None  # (seq, seq_next) of the last of them
        self.ahead: AheadHold[SceneFlowResult] = AheadHold()  # far-ahead flows (the flow stage's defaults)
        self.timer = StageTimer()

    @property
    def started(self) -> bool:
        return self._last is not None

    @property
    def reached(self) -> int | None:
        """The newest frame the path has reached (None: not started)."""
        return self._last

    def start(self, seq: int) -> list[Correction]:
        """First frame of the stream: its release (identity, a keyframe)."""
        self._last = seq
        return self.planner.start(seq)

    def push(self, flow: SceneFlowResult) -> tuple[list[MotionEstimate], list[list[Correction]]]:
        """Add one flow; returns the motions made and the releases, in order.

        Starts the path at ``flow.seq`` if not started. A flow that does not begin
        at the newest frame reached (frames skipped upstream) first gets an invalid
        motion across the gap. A flow that ends at or before that frame, begins before it or goes
        back is refused with ValueError (stale, duplicate or overlapping), unless it is the flow
        stage's break to a new numbering (:meth:`renumbers`): the path then restarts at its
        ``seq_next``, and the corrections of the old numbering and of the new one go out in separate
        releases. A flow reaching more than ``max_jump`` frames beyond the newest frame reached is
        held (nothing returned) until ``confirm`` flows in a row confirm the new numbering, as the
        flow stage confirms frames (:class:`~quick_stream.core.continuity.AheadHold`): then they are
        all taken, in order; an ordinary flow first drops them (``jump_flows``), so one far-future
        flow (forged or garbled) never halts the stream.
        """
        reach = max(flow.seq, flow.seq_next)
        if not self.started or reach <= self._last:
            return self._take(flow)  # the first flow, a stale one (refused) or the break to a lower numbering
        self._refuse(flow)  # one the path could never take is refused as it comes, never held
        taken = self.ahead.offer(self._last, reach, flow)
        if len(taken) <= 1:
            return self._take(flow) if taken else ([], [])
        motions: list[MotionEstimate] = []
        released: list[list[Correction]] = []
        for f in taken:  # a confirmed run: the held flows, then this one
            try:
                m, b = self._take(f)
            except ValueError:  # (the run's flows follow each other: only a copy among them)
                self.ahead.dropped += 1
                continue
            motions += m
            released += b
        return motions, released

    def _refuse(self, flow: SceneFlowResult) -> bool:
        """Raises ValueError for a flow the path cannot take after the newest frame reached (stale,
        duplicate, overlapping, going back); returns whether it is the break to a new numbering."""
        renumbered = self.renumbers(flow)
        if renumbered or self._last is None:
            return renumbered
        if flow.seq_next <= self._last:
            raise ValueError(f"flow {flow.seq}->{flow.seq_next} ends at or before frame {self._last} "
                             "(stale or duplicate)")
        if flow.seq < self._last:
            raise ValueError(f"flow {flow.seq}->{flow.seq_next} begins before frame {self._last}, the newest the "
                             "path reached (stale or duplicate: overlapping)")
        if flow.seq_next <= flow.seq:
            raise ValueError(f"flow {flow.seq}->{flow.seq_next} goes back but is not the flow stage's break to "
                             "a new numbering")
        return False

    def _take(self, flow: SceneFlowResult) -> tuple[list[MotionEstimate], list[list[Correction]]]:
        """:meth:`push` without the far-ahead hold."""
        released: list[list[Correction]] = []
        motions: list[MotionEstimate] = []
        renumbered = self._refuse(flow)
        if self._last is None:
            released.append(self.start(flow.seq))
        if renumbered:
            self.renumberings += 1
            self._break = (flow.seq, flow.seq_next)
            self.bridge.reset()
        p = self.estimator.params
        if flow.seq != self._last:
            self.gaps += 1
            gap = invalid_motion(self._last, flow.seq, p.group, p.estimator,
                                 f"no scene flow from frame {self._last} to {flow.seq} (frames skipped upstream)")
            gap = self.bridge.take(gap, flow.seq - self._last)
            motions.append(gap)
            released.append(self.planner.push(gap))
        t0 = time.perf_counter()
        parts = known_motions(flow, self.estimator, self.bridge)
        t1 = time.perf_counter()
        motions += parts
        for part in parts:  # the crop budget's model of the flow's second frame goes with the last part
            model = self.frame_model(flow) if part.seq_next == flow.seq_next else None
            released += split_numberings(self.planner.push(part, model))
        self.timer.add("motion", (t1 - t0) * 1e3)
        self.timer.add("path", (time.perf_counter() - t1) * 1e3)
        self._last = flow.seq_next
        return motions, [b for b in released if b]

    def renumbers(self, flow: SceneFlowResult) -> bool:
        """Whether ``flow`` is the flow stage's break to a new numbering: empty, going back
        (``seq_next <= seq``), its problem naming the renumbering, and starting at or after the newest
        frame the path reached and not the one already taken (either is a stale copy)."""
        return (bool(flow.problem) and len(flow) == 0 and flow.seq_next <= flow.seq
                and restarts_numbering(flow.problem) and (self._last is None or flow.seq >= self._last)
                and self._break != (flow.seq, flow.seq_next))

    def frame_model(self, flow: SceneFlowResult) -> FrameModel | None:
        """The 3D points of the flow's second frame (x + v at the pixels the flow reached), for the crop budget."""
        b = self.planner.params.budget
        if not (self.planner.params.mode == "smooth" and b.enabled) or flow.problem or len(flow) == 0:
            return None
        K = flow.intrinsics_next
        return FrameModel.from_points(K.width, K.height, K, flow.pixels_next, flow.points + flow.displacements,
                                      b.model_points)

    def finish(self) -> list[list[Correction]]:
        """End of stream: the last segment's release (if any); flows still held far ahead are dropped."""
        self.ahead.drop()
        b = self.planner.finish() if self.started else []
        return [b] if b else []


def known_motions(flow: SceneFlowResult, estimator: MotionEstimator, bridge: MotionBridge) -> list[MotionEstimate]:
    """The motions of ``flow`` as the path takes them (docs/method.md 2.4): the estimator's fit, bridged by
    ``bridge`` when nothing could be fitted (never across a discontinuity), split across the frames the flow
    reached over (each part remembered by the bridge as a motion of its own)."""
    m = estimator.estimate(flow)
    if breaks_stream(flow.problem):  # a discontinuity: nothing may be guessed across it
        bridge.reset()
        return [m]
    if m.valid:
        return [bridge.take(part, part.seq_next - part.seq) for part in split_over(m, flow.over)]
    return split_over(bridge.take(m, flow.seq_next - flow.seq), flow.over)


def split_numberings(release: list[Correction]) -> list[list[Correction]]:
    """``release`` cut where its seqs go back (a path closed by a renumbering and restarted in the new
    numbering), so no release mixes two numberings."""
    cuts = [i for i in range(1, len(release)) if release[i].seq <= release[i - 1].seq]
    return [release[a:b] for a, b in zip([0, *cuts], [*cuts, len(release)])]


class MotionDriver:
    """The motion stage over a service's life: flows in; motions and the releases,
    tagged with their release (:class:`~quick_stream.core.release_tags.ReleaseNumbering`), out.

    ``resume_after``: a restarted motion service starts a new path after the last correction its
    predecessor released (flows up to it are skipped, ``taken_over``, until a renumbering or the
    end of the stream). A stale or duplicate flow is refused (``refused_flows``; of them ``jump_flows``:
    held far ahead, :meth:`MotionStage.push`, and dropped unconfirmed), an invalid
    motion counted (``invalid_motions``), both reported on ``log`` (None: silent); ``keep_segments``:
    the segment accounts the planner keeps (a service keeps a few: a live stream is endless). At the end of a
    stream :meth:`finish` closes the last segment; :meth:`restart` starts the next stream (the
    release numbers and the counters go on)."""

    def __init__(self, motion: MotionParams | None = None, planner: PlannerParams | None = None,
                 warp: WarpParams | None = None, *, resume_after: int | None = None,
                 log: logging.Logger | None = None, keep_segments: int | None = None) -> None:
        self._make = lambda: MotionStage(motion, planner, warp, keep_segments)
        self.stage = self._make()
        self.releases = ReleaseNumbering()
        self.resume_after, self.log = resume_after, log_or_quiet(log)
        self.refused = self.invalid = self.taken_over = 0
        self.kinds = dict.fromkeys(KINDS, 0)  # motions by how they were known (docs/method.md 2.4)
        self._renumberings = 0  # of the streams already ended
        self._jumped = 0  # flows held far ahead and dropped, of the streams already ended
        self._shed: dict[int, tuple[int, ...]] = {}  # frame -> the frames the flow stage shed before it

    def start(self, seq: int) -> list[tuple[Correction, Tag]]:
        """The stream's first frame, before any flow (in-process): its correction, released at once."""
        return self.releases.number([self.stage.start(seq)], closed_by=seq)

    def _named(self, released: list[list[Correction]]) -> list[list[Correction]]:
        """The releases, each correction carrying the frames the flow stage shed before its frame."""
        if self._shed:
            for c in (c for b in released for c in b):
                c.shed = self._shed.pop(c.seq, ())
        return released

    def push(self, flow: SceneFlowResult, shed: Collection[int] = ()) -> tuple[list[MotionEstimate],
                                                                              list[tuple[Correction, Tag]]] | None:
        """The motions made and the tagged corrections released by one flow; None when the flow is
        skipped (taken over) or refused. ``shed``: the frames the flow stage shed since its previous
        flow (the flow message's ``shed``), put on the correction of the frame the flow ends at."""
        if self.resume_after is not None and flow.seq <= self.resume_after:
            self.taken_over += 1  # its frames were corrected before the restart
            return None
        ahead, last = self.stage.ahead, self.stage.reached
        dropped = ahead.dropped
        try:
            motions, released = self.stage.push(flow)
        except ValueError as e:
            self.refused += 1
            self.log.log(logging.ERROR, "flow %d->%d refused: %s", flow.seq, flow.seq_next, e)
            return None
        if ahead.dropped > dropped:
            self.log.log(logging.ERROR, "%d flows held far ahead dropped: no run of flows confirmed a new numbering "
                      "(the stream went on from frame %s)", ahead.dropped - dropped, last)
        if not motions:  # held: far ahead of the path, until a run confirms it
            self.log.log(logging.WARNING, "flow %d->%d reaches %d frames beyond frame %d (more than %d): held until %d "
                      "flows in a row continue from it", flow.seq, flow.seq_next,
                      max(flow.seq, flow.seq_next) - last, last, ahead.guard.max_jump, ahead.guard.confirm)
            return [], []
        if flow.seq_next <= flow.seq:
            self.resume_after = None  # a new numbering: the predecessor's cursor says nothing of it
        if shed:
            self._shed[flow.seq_next] = tuple(shed)
            while len(self._shed) > 4096:  # frames whose correction never came (bounded)
                self._shed.pop(next(iter(self._shed)))
        released = self._named(released)
        for m in motions:
            self.kinds[m.kind] = self.kinds.get(m.kind, 0) + 1
            if not m.valid:
                self.invalid += 1
                self.log.log(logging.WARNING, "motion %d->%d not known, the path restarts: %s", m.seq, m.seq_next,
                          m.reason)
            elif m.kind != "fit":
                self.log.log(logging.INFO, "motion %d->%d by %s: %s", m.seq, m.seq_next, m.kind, m.reason)
        return motions, self.releases.number(released, closed_by=flow.seq_next)

    def finish(self) -> list[tuple[Correction, Tag]]:
        """End of stream: the last segment's corrections, tagged."""
        out = self.releases.number(self._named(self.stage.finish()))
        self.log.log(logging.INFO, "end of stream: %d segments, %d corrections", self.stage.planner.segment_count,
                  self.releases.sent)
        return out

    def restart(self) -> None:
        """After :meth:`finish`: a new stream may follow (a new path; the counters go on)."""
        self._renumberings += self.stage.renumberings
        self._jumped += self.stage.ahead.dropped
        self.stage = self._make()
        self.resume_after = None
        self._shed.clear()

    def stats(self) -> dict[str, int]:
        st = self.stage
        jumped = self._jumped + st.ahead.dropped
        return {"refused_flows": self.refused + jumped, "jump_flows": jumped, "invalid_motions": self.invalid,
                "taken_over": self.taken_over,
                **{f"motions_{k}": n for k, n in self.kinds.items() if k != "none"},
                "gaps": st.gaps, "segments": st.planner.segment_count, "corrections": self.releases.sent,
                "renumberings": self._renumberings + st.renumberings}

"""The whole QuICK stabilizer in one process, shaped like the stream it will become.

Frames go in one at a time (:meth:`Stabilizer.push`); stabilized frames come out
one segment later, when the planner has solved the segment their corrections
belong to. Stages, each driven by the library object the matching service runs
(quick_stream/core/stages.py, quick_stream/core/release.py):

    FlowStage (scene flow) -> MotionDriver (motion, keyframes, optimal path; releases tagged)
        -> RenderDriver (releases regrouped, rendered when due: content-preserving warp, framing,
           render; at the end, what is still held)

In one process every frame is in before its release, so a release renders as soon as it comes
(``force``): what the render service waits ``--frame-wait`` for cannot be missing here.

Only the frames of the open segment are buffered (at most one keyframe interval).
Bad frames are skipped and reported; frames whose correction fell back (invalid
motion, solver failure, failed warp) are still rendered, flagged in their record.
"""
from __future__ import annotations

import time

from .frame import BadFrame, RGBDFrame
from .params import StabilizerParams
from .path.planner import Correction, PathPlanner
from .release import RenderDriver
from .release_tags import Tag
from .render_stage import RenderStage, StabilizedFrame
from .sceneflow import SceneFlowResult
from .flow_stage import FlowStage
from .stages import MotionDriver, MotionStage
from .timing import StageTimer

__all__ = ["Stabilizer", "StabilizerParams", "StabilizedFrame"]


class Stabilizer:
    """One stream's stabilizer (not thread-safe)."""

    def __init__(self, params: StabilizerParams | None = None, keep_inputs: bool = False,
                 keep_motions: bool = False) -> None:
        """``keep_inputs``: attach each input image to its output (metrics); ``keep_motions``:
        record every motion estimate (reports, plots). Both off, memory stays bounded by one segment."""
        self.params = p = params or StabilizerParams()
        self.flow = FlowStage(p.flow, p.continuity)
        self.motion_driver = MotionDriver(p.motion, p.planner, p.warp)
        self.render_driver = RenderDriver(p.warp, p.framing, max_frames=1 << 30, keep_inputs=keep_inputs)
        self.timer = StageTimer()
        self.keep_motions = keep_motions
        self.bad_frames: list[dict] = []
        self.motions: list = []

    @property
    def motion(self) -> MotionStage:
        return self.motion_driver.stage

    @property
    def render(self) -> RenderStage:
        return self.render_driver.stage

    @property
    def planner(self) -> PathPlanner:
        return self.motion.planner

    def push(self, frame: RGBDFrame | BadFrame) -> list[StabilizedFrame]:
        """Add the next frame; returns the frames whose segment just closed (in order)."""
        if isinstance(frame, BadFrame):
            self.bad_frames.append({"seq": frame.seq, "origin": frame.origin, "error": frame.error})
            return []
        try:
            t0 = time.perf_counter()
            flows = self.flow.push(frame)
            t1 = time.perf_counter()
        except ValueError as e:
            self.bad_frames.append({"seq": frame.seq, "origin": frame.origin, "error": str(e)})
            # as the render service does: a refused frame it can hold is rendered uncorrected, flagged
            # (a duplicate or one out of order it refuses too: not rendered twice)
            self.render_driver.add_frame(frame.seq, frame)
            return []
        self.render_driver.add_frame(frame.seq, frame)
        if self.flow.began:
            return self._render(self.motion_driver.start(frame.seq))
        self.timer.add("flow", (t1 - t0) * 1e3)
        return self._motion(flows)

    def _motion(self, flows: list[SceneFlowResult]) -> list[StabilizedFrame]:
        out: list[StabilizedFrame] = []
        for flow in flows:
            pushed = self.motion_driver.push(flow)
            if pushed is None:
                continue
            if self.keep_motions:
                self.motions.extend(pushed[0])
            out += self._render(pushed[1])
        return out

    def finish(self) -> list[StabilizedFrame]:
        """End of stream: close the last segment and render what is left."""
        frames = self._motion(self.flow.finish())
        frames += self._render(self.motion_driver.finish())
        self.render_driver.end()
        for _, group in self.render_driver.finish():
            frames += [r.frame for r in group]
        self._merge_timers()
        return frames

    def _render(self, corrections: list[tuple[Correction, Tag]]) -> list[StabilizedFrame]:
        for c, tag in corrections:
            self.render_driver.add_correction(c, tag)
        out = [r.frame for rel in self.render_driver.due(force=True) for r in self.render_driver.render(rel)]
        self._merge_timers()
        return out

    def _merge_timers(self) -> None:
        for stage in (self.motion, self.render):
            for k, v in stage.timer.samples.items():
                self.timer.samples.setdefault(k, []).extend(v)
                v.clear()

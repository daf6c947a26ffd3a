"""The whole QuICK stabilizer in one process, shaped like the stream it will become.

Frames go in one at a time (:meth:`Stabilizer.push`); stabilized frames come out
one segment later, when the planner has solved the segment their corrections
belong to. Stages, each the library object the matching service calls:

    scene flow + motion (MotionPipeline) -> path planner (PathPlanner)
        -> content-preserving warp (solve_warp) -> framing (segment_zooms) -> render

Only the frames of the open segment are buffered (at most one keyframe interval).
Bad frames are skipped and reported; frames whose correction fell back (invalid
motion, solver failure, failed warp) are still rendered, flagged in their record.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .frame import BadFrame, RGBDFrame
from .motion import MotionParams
from .motion_pipeline import MotionPipeline, StageTimer
from .path.planner import Correction, PathPlanner, PlannerParams
from .render import FramingParams, MeshWarp, WarpParams, ZoomSmoother, render, segment_zooms, solve_warp
from .sceneflow import SceneFlowParams


@dataclass
class StabilizerParams:
    flow: SceneFlowParams = field(default_factory=SceneFlowParams)
    motion: MotionParams = field(default_factory=MotionParams)
    planner: PlannerParams = field(default_factory=PlannerParams)
    warp: WarpParams = field(default_factory=WarpParams)
    framing: FramingParams = field(default_factory=FramingParams)

    def __post_init__(self) -> None:
        if self.planner.group != self.motion.group:
            raise ValueError(f"motion group {self.motion.group!r} and path group {self.planner.group!r} differ")


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


class Stabilizer:
    """One stream's stabilizer (not thread-safe)."""

    def __init__(self, params: StabilizerParams | None = None, keep_inputs: bool = False,
                 keep_motions: bool = False) -> None:
        """``keep_inputs``: attach each input image to its output (metrics); ``keep_motions``:
        record every motion estimate (reports, plots). Both off, memory stays bounded by one segment."""
        self.params = p = params or StabilizerParams()
        p.framing.validate()
        self.motion = MotionPipeline(p.flow, p.motion)
        self.planner = PathPlanner(p.planner)
        self.zoom = ZoomSmoother(p.framing)
        self.timer = StageTimer()
        self.keep_inputs = keep_inputs
        self.keep_motions = keep_motions
        self.bad_frames: list[dict] = []
        self.motions: list = []
        self._frames: dict[int, RGBDFrame] = {}
        self._started = False

    def push(self, frame: RGBDFrame | BadFrame) -> list[StabilizedFrame]:
        """Add the next frame; returns the frames whose segment just closed (in order)."""
        if isinstance(frame, BadFrame):
            self.bad_frames.append({"seq": frame.seq, "origin": frame.origin, "error": frame.error})
            return []
        self._frames[frame.seq] = frame
        if not self._started:
            self._started = True
            self.motion.push(frame)
            return self._render(self.planner.start(frame.seq))
        out = self.motion.push(frame)
        if out is None:
            return []
        m, flow_ms, motion_ms, _ = out
        self.timer.add("flow", flow_ms)
        self.timer.add("motion", motion_ms)
        if self.keep_motions:
            self.motions.append(m)
        t0 = time.perf_counter()
        released = self.planner.push(m)
        self.timer.add("path", (time.perf_counter() - t0) * 1e3)
        return self._render(released)

    def finish(self) -> list[StabilizedFrame]:
        """End of stream: close the last segment and render what is left."""
        t0 = time.perf_counter()
        released = self.planner.finish()
        self.timer.add("path", (time.perf_counter() - t0) * 1e3)
        return self._render(released)

    def _render(self, corrections: list[Correction]) -> list[StabilizedFrame]:
        if not corrections:
            return []
        t0 = time.perf_counter()
        meshes = []
        for c in corrections:
            f = self._frames[c.seq]
            meshes.append(solve_warp(f, c.point_transform, self.params.warp))
        t1 = time.perf_counter()
        zooms = segment_zooms(meshes, self.params.framing, self.zoom)
        t2 = time.perf_counter()
        out = []
        for c, mesh, z in zip(corrections, meshes, zooms):
            f = self._frames.pop(c.seq)
            img = render(f.color, mesh, float(z))
            out.append(StabilizedFrame(c.seq, f.timestamp_ns, img, c, float(z), mesh,
                                       f.color if self.keep_inputs else None))
        t3 = time.perf_counter()
        n = len(corrections)
        for _ in range(n):  # per-frame samples (the batch's average)
            self.timer.add("warp", (t1 - t0) * 1e3 / n)
            self.timer.add("framing", (t2 - t1) * 1e3 / n)
            self.timer.add("render", (t3 - t2) * 1e3 / n)
        return out

"""In-process motion pipeline: source -> scene flow -> motion -> camera path.

The same per-stage objects (:class:`~quick_stream.core.flow_stage.FlowStage`,
:class:`~quick_stream.core.motion.MotionEstimator` through the motion stage's
:func:`~quick_stream.core.stages.known_motions`) are what the streaming services
call; this module only chains them and keeps books (timings, failures, the ground-truth
motion of each pair) for ``quick-stream motion``; the errors against ground truth are the
quality layer's (:func:`quick_stream.quality.evaluation.rpe.pair_error_stats`).

Bad frames (a :class:`~quick_stream.core.frame.BadFrame` from the source, or one the flow
stage's continuity check refuses) are reported and skipped: the next good frame is paired with
the last good one, so the camera path stays continuous. A flow the group's fit does not hold for
gets the rotation-only fit, a frame whose flow starves is reached over, a flow with nothing in it
gets the motion stage's constant-velocity bridge (:class:`~quick_stream.core.motion.chain.MotionBridge`,
docs/method.md 2.4), as in the services; only a motion that is not known at all is invalid (the
path holds still across it).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from .frame import BadFrame, RGBDFrame
from .motion import MotionEstimate, MotionEstimator, MotionParams
from .continuity import FrameRefused
from .motion.chain import MotionBridge
from .sceneflow import SceneFlowParams, SceneFlowResult
from .flow_stage import FlowStage
from .stages import known_motions
from .timing import StageTimer, timed_iter


REACH_KEPT = 64  # frames kept for the ground truth of motions that begin before the newest frame


@dataclass
class PairRecord:
    """One processed frame pair."""

    motion: MotionEstimate
    timestamp_ns: int  # of the pair's second frame
    truth: np.ndarray | None  # ground-truth camera motion, when both poses are known
    flow_ms: float
    motion_ms: float
    counts: dict[str, int] = field(default_factory=dict)
    displacement_px: float = float("nan")  # median image motion of the pair's kept samples (fast motion: large)
    span: tuple[int, int] | None = None  # the flow's frames when it reached over frames (this motion a part of it)


class MotionPipeline:
    """Scene flow + motion over a stream of frames (one instance per stream): the flow stage's
    :class:`~quick_stream.core.flow_stage.FlowStage` (its continuity check, frames reached over) and the
    motion stage's :func:`~quick_stream.core.stages.known_motions`, without the path."""

    def __init__(self, flow_params: SceneFlowParams | None = None, motion_params: MotionParams | None = None):
        self.flow = FlowStage(flow_params)
        self.motion = MotionEstimator(motion_params)
        self.bridge = MotionBridge(self.motion.params.bridge_frames)

    def push(self, frame: RGBDFrame) -> list[tuple]:
        """Add the next good frame; returns, per motion it completes (frame by frame: a flow reaching over
        a frame gives one into it and one out of it), (motion, flow ms, motion ms, mask counts, median image
        motion of the kept samples in px, the flow's frames when it reached over some or None), the flow's
        times shared among its motions. A frame the
        continuity check refuses raises :class:`~quick_stream.core.continuity.FrameRefused`."""
        t0 = time.perf_counter()
        flows = self.flow.push(frame)
        return self._motions(flows, (time.perf_counter() - t0) * 1e3)

    def finish(self) -> list[tuple]:
        """The end of the frames: the flow held for frames being reached over."""
        return self._motions(self.flow.finish(), 0.0)

    def _motions(self, flows: list[SceneFlowResult], flow_ms: float) -> list[tuple]:
        out = []
        for sf in flows:
            t1 = time.perf_counter()
            ms = known_motions(sf, self.motion, self.bridge)
            motion_ms = (time.perf_counter() - t1) * 1e3
            d = sf.pixels_next - sf.pixels
            moved = float(np.median(np.sqrt(np.einsum("ij,ij->i", d, d)))) if len(sf) else float("nan")
            share = 1.0 / (len(flows) * len(ms))
            span = (sf.seq, sf.seq_next) if sf.over else None
            out += [(m, flow_ms * share, motion_ms / len(ms), sf.counts, moved, span) for m in ms]
        return out


@dataclass
class MotionRunResult:
    pairs: list[PairRecord]
    failures: list[dict]  # bad frames: seq, origin, error
    timestamps_ns: list[int]  # of the good frames, in order
    timer: StageTimer
    first_pose: np.ndarray | None = None  # ground-truth pose of the first good frame

    @property
    def camera_motions(self) -> list[np.ndarray]:
        return [p.motion.matrix for p in self.pairs]


def true_motion(a: RGBDFrame, b: RGBDFrame) -> np.ndarray | None:
    """Ground-truth camera motion T_a^-1 T_b, when both frames carry a pose."""
    if a.pose is None or b.pose is None:
        return None
    return np.linalg.inv(a.pose) @ b.pose


def run_motion(
    frames: Iterable[RGBDFrame | BadFrame],
    pipeline: MotionPipeline,
    on_pair: Callable[[PairRecord], None] | None = None,
    on_failure: Callable[[dict], None] | None = None,
    extra: Callable[[RGBDFrame, RGBDFrame], None] | None = None,
) -> MotionRunResult:
    """Run ``pipeline`` over ``frames``; ``extra(prev, cur)`` is called per good pair (comparisons)."""
    timer = StageTimer()
    pairs: list[PairRecord] = []
    failures: list[dict] = []
    stamps: list[int] = []
    recent: dict[int, RGBDFrame] = {}  # the frames a motion may still begin at (a reach spans a few)
    prev: RGBDFrame | None = None
    first_pose = None

    def record(out) -> None:
        for m, fms, mms, counts, moved, span in out:
            timer.add("flow", fms)
            timer.add("motion", mms)
            a, b = recent.get(m.seq), recent.get(m.seq_next)
            truth = true_motion(a, b) if a is not None and b is not None else None
            rec = PairRecord(m, b.timestamp_ns if b is not None else -1, truth, fms, mms, counts, moved, span)
            pairs.append(rec)
            if on_pair:
                on_pair(rec)

    for fr in timed_iter(frames, timer, "read"):
        if isinstance(fr, BadFrame):
            rec = {"seq": fr.seq, "origin": fr.origin, "error": fr.error}
            failures.append(rec)
            if on_failure:
                on_failure(rec)
            continue
        try:
            out = pipeline.push(fr)
        except FrameRefused as e:
            rec = {"seq": fr.seq, "origin": fr.origin, "error": str(e)}
            failures.append(rec)
            if on_failure:
                on_failure(rec)
            continue
        if not stamps:
            first_pose = fr.pose
        stamps.append(fr.timestamp_ns)
        recent[fr.seq] = fr
        for s in [s for s in recent if s < fr.seq - REACH_KEPT]:
            del recent[s]
        record(out)
        if extra and prev is not None:
            extra(prev, fr)
        prev = fr
    record(pipeline.finish())
    return MotionRunResult(pairs, failures, stamps, timer, first_pose)

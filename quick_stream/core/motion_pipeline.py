"""In-process motion pipeline: source -> scene flow -> motion -> camera path.

The same per-stage objects (:class:`~quick_stream.core.sceneflow.SceneFlow`,
:class:`~quick_stream.core.motion.MotionEstimator`) are what the streaming services
call; this module only chains them and keeps books (timings, failures, the ground-truth
motion of each pair) for ``quick-stream motion``; the errors against ground truth are the
quality layer's (:func:`quick_stream.quality.evaluation.rpe.pair_error_stats`).

Bad frames (a :class:`~quick_stream.core.frame.BadFrame` from the source) are
reported and skipped: the next good frame is paired with the last good one, so
the camera path stays continuous. A flow the group's fit does not hold for gets the
rotation-only fit, a flow with nothing in it the motion stage's constant-velocity bridge
(:class:`~quick_stream.core.motion.chain.MotionBridge`, docs/method.md 2.4), as in the
services; only a motion that is not known at all is invalid (the path holds still across it).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from .frame import BadFrame, RGBDFrame
from .motion import MotionEstimate, MotionEstimator, MotionParams
from .motion.chain import MotionBridge
from .sceneflow import SceneFlow, SceneFlowParams
from .timing import StageTimer, timed_iter


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


class MotionPipeline:
    """Scene flow + motion over a stream of frames (one instance per stream)."""

    def __init__(self, flow_params: SceneFlowParams | None = None, motion_params: MotionParams | None = None):
        self.flow = SceneFlow(flow_params)
        self.motion = MotionEstimator(motion_params)
        self.bridge = MotionBridge(self.motion.params.bridge_frames)
        self._prev: RGBDFrame | None = None

    def push(self, frame: RGBDFrame) -> tuple[MotionEstimate, float, float, dict[str, int], float] | None:
        """Add the next good frame; returns (motion, flow ms, motion ms, mask counts, median image motion of the
        kept samples in px) from the previous one."""
        prev, self._prev = self._prev, frame
        if prev is None:
            return None
        t0 = time.perf_counter()
        sf = self.flow.compute(prev, frame)
        t1 = time.perf_counter()
        m = self.motion.estimate(sf)  # (the pipeline pairs consecutive good frames: no discontinuity check)
        m = self.bridge.take(m, sf.seq_next - sf.seq)
        t2 = time.perf_counter()
        d = sf.pixels_next - sf.pixels
        moved = float(np.median(np.sqrt(np.einsum("ij,ij->i", d, d)))) if len(sf) else float("nan")
        return m, (t1 - t0) * 1e3, (t2 - t1) * 1e3, sf.counts, moved


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
    prev: RGBDFrame | None = None
    first_pose = None
    for fr in timed_iter(frames, timer, "read"):
        if isinstance(fr, BadFrame):
            rec = {"seq": fr.seq, "origin": fr.origin, "error": fr.error}
            failures.append(rec)
            if on_failure:
                on_failure(rec)
            continue
        if not stamps:
            first_pose = fr.pose
        stamps.append(fr.timestamp_ns)
        out = pipeline.push(fr)
        if out is not None and prev is not None:
            m, fms, mms, counts, moved = out
            timer.add("flow", fms)
            timer.add("motion", mms)
            rec = PairRecord(m, fr.timestamp_ns, true_motion(prev, fr), fms, mms, counts, moved)
            pairs.append(rec)
            if on_pair:
                on_pair(rec)
            if extra:
                extra(prev, fr)
        prev = fr
    return MotionRunResult(pairs, failures, stamps, timer, first_pose)

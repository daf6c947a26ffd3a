"""Online path planning with one-segment latency: motions in, per-frame corrections out.

The planner integrates the camera path g_c, detects keyframes, and when a
segment closes solves its optimal path (:func:`~.optimal.solve_segment`) between
the end-constraints (:class:`~.constraints.EndConstraints`) and releases the
corrections g_s of the segment's frames. The streaming ``motion`` service and
the offline ``stabilize`` command both drive this same object.

Fallbacks are visible, never silent: an invalid motion closes the segment at
the frame before it, and the path restarts after it with no correction (those
frames carry ``valid=False`` and the reason); a segment whose solver does not
converge gets identity corrections, flagged the same way.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..lie import LieGroup, get_group
from ..motion import MotionEstimate
from .constraints import EndConstraints
from .keyframes import KeyframeDetector, KeyframeParams
from .optimal import PathParams, solve_segment


@dataclass
class PlannerParams:
    group: str = "se3"
    end: str = "smoothed"  # end-constraint mode: identity | smoothed
    alpha: float = 0.4  # smoothed mode: keyframe-pose filter gains
    beta: float = 0.4
    keyframes: KeyframeParams = field(default_factory=KeyframeParams)
    path: PathParams = field(default_factory=PathParams)


@dataclass
class Correction:
    """Stabilizing transformation g_s for one frame (virtual camera pose relative to the real one)."""

    seq: int
    matrix: np.ndarray
    segment: int
    keyframe: bool
    valid: bool = True
    reason: str = ""

    @property
    def point_transform(self) -> np.ndarray:
        """g_s^-1: maps real-camera coordinates of a point to virtual-camera coordinates."""
        return np.linalg.inv(self.matrix)


@dataclass
class SegmentInfo:
    segment: int
    start_seq: int
    end_seq: int
    closed_by: str  # interval | turn | invalid-motion | end-of-stream
    converged: bool
    iterations: int
    residual: float
    cost: float
    solve_ms: float
    reason: str = ""


class PathPlanner:
    """One stream's keyframes, end-constraints and optimal path."""

    def __init__(self, params: PlannerParams | None = None) -> None:
        self.params = p = params or PlannerParams()
        self.group: LieGroup = get_group(p.group)
        self.detector = KeyframeDetector(p.keyframes)
        self.ends = EndConstraints(self.group, p.end, p.alpha, p.beta)
        self.segments: list[SegmentInfo] = []
        self._pose = np.eye(4)  # g_c at the newest frame
        self._start: int | None = None  # seq of the open segment's first keyframe
        self._C0 = np.eye(4)
        self._seqs: list[int] = []  # frames after the start, in order
        self._zbar: list[np.ndarray] = []
        self._motions: list[np.ndarray] = []

    @property
    def open_frames(self) -> int:
        """Frames waiting for their segment to close."""
        return len(self._seqs)

    def start(self, seq: int) -> list[Correction]:
        """First frame of the stream (a keyframe, no correction)."""
        self._begin(seq, restart=True)
        return [Correction(seq, np.eye(4), len(self.segments), True)]

    def _begin(self, seq: int, restart: bool) -> None:
        self._start = seq
        self._seqs, self._zbar, self._motions = [], [], []
        self.detector.reset()
        if restart:
            self._C0 = np.eye(4)
            self.ends.reset(self._pose)

    def push(self, motion: MotionEstimate) -> list[Correction]:
        """Add the motion from frame ``motion.seq`` to ``motion.seq_next``; returns released corrections."""
        if self._start is None:
            raise RuntimeError("PathPlanner.start() must be called with the first frame")
        if not motion.valid:
            out = self._close("invalid-motion") if self._seqs else []
            self._begin(motion.seq_next, restart=True)
            out.append(Correction(motion.seq_next, np.eye(4), len(self.segments), True, False,
                                  f"motion {motion.seq}->{motion.seq_next} invalid ({motion.reason}): "
                                  "path restarted, frame not corrected"))
            return out
        zb = motion.zeta_bar if motion.zeta_bar is not None else self.group.log(self.group.inverse(motion.matrix))
        self._seqs.append(motion.seq_next)
        self._zbar.append(zb)
        self._motions.append(motion.matrix)
        self._pose = self._pose @ motion.matrix
        why = self.detector.push(motion.matrix)
        return self._close(why) if why else []

    def finish(self) -> list[Correction]:
        """End of stream: close the open segment at the last frame."""
        return self._close("end-of-stream") if self._seqs else []

    def _close(self, closed_by: str) -> list[Correction]:
        seg = len(self.segments)
        C1 = self.ends.at_keyframe(self._pose, len(self._seqs))
        t0 = time.perf_counter()
        sol = solve_segment(self.group, np.asarray(self._motions), self._C0, C1, self.params.path,
                            zbar=np.asarray(self._zbar))
        ms = (time.perf_counter() - t0) * 1e3
        info = SegmentInfo(seg, self._start, self._seqs[-1], closed_by, sol.converged, sol.iterations,
                           sol.residual, sol.cost, ms, sol.reason)
        self.segments.append(info)
        last = len(self._seqs) - 1
        if sol.converged:
            out = [Correction(s, sol.corrections[i + 1], seg, i == last) for i, s in enumerate(self._seqs)]
            next_C0 = sol.corrections[-1]
        else:
            why = f"segment {seg} not stabilized: {sol.reason}"
            out = [Correction(s, np.eye(4), seg, i == last, False, why) for i, s in enumerate(self._seqs)]
            next_C0 = np.eye(4)
            self.ends.reset(self._pose)
        end_seq = self._seqs[-1]
        self._begin(end_seq, restart=False)
        self._C0 = next_C0
        return out

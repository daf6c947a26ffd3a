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
    alpha: float = 0.1  # smoothed mode: keyframe-pose filter gains
    beta: float = 0.4
    lowpass_sigma: float = 20.0  # frames; > 0: keep the low-passed camera velocity (0: the paper, undo all)
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
        self._history: list[np.ndarray] = []  # camera-motion twists of recent frames (for the low-pass)

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
            self._history = []

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
        if self.params.lowpass_sigma > 0:
            self._history.append(motion.twist if motion.twist is not None else self.group.log(motion.matrix))
        self._pose = self._pose @ motion.matrix
        why = self.detector.push(motion.matrix)
        return self._close(why) if why else []

    def finish(self) -> list[Correction]:
        """End of stream: close the open segment at the last frame."""
        return self._close("end-of-stream") if self._seqs else []

    def _close(self, closed_by: str) -> list[Correction]:
        seg = len(self.segments)
        zbar, smooth = self._targets()
        C1 = self.ends.at_keyframe(self._pose, len(self._seqs), smooth)
        t0 = time.perf_counter()
        sol = solve_segment(self.group, np.asarray(self._motions), self._C0, C1, self.params.path, zbar=zbar)
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

    def _targets(self) -> tuple[np.ndarray, np.ndarray | None]:
        """zeta_bar of the open segment, plus the low-passed camera velocity when lowpass_sigma > 0.

        Beyond the paper: its zeta_bar undoes each frame's whole motion, so the
        stabilized camera moves at constant velocity between keyframes and a
        camera whose intended motion curves gets a kink at every keyframe. Adding
        back s_t, a Gaussian low-pass of the camera's own twists (frames up to the
        closing keyframe only, the window truncated there), keeps the slow
        motion's shape: the optimum becomes zeta = zeta_bar + s + c.
        """
        zbar = np.asarray(self._zbar)
        sigma = self.params.lowpass_sigma
        if sigma <= 0:
            return zbar, None
        n = len(zbar)
        self._history = self._history[-(n + int(np.ceil(3 * sigma))):]
        H = np.asarray(self._history)
        idx = np.arange(len(H))
        out = zbar.copy()
        for i, t in enumerate(range(len(H) - n, len(H))):
            w = np.exp(-0.5 * ((idx - t) / sigma) ** 2)
            out[i] = zbar[i] + (w @ H) / w.sum()
        smooth = np.eye(4)
        for E in self.group.exp(out - zbar):
            smooth = smooth @ E
        return out, smooth

"""The ``ep`` path (the paper's method): each keyframe segment's optimal path (docs/method.md 4.1-4.2).

Keyframes close the segments (:class:`~.keyframes.KeyframeDetector`: the interval or a turn); each
segment gets the optimal path of the Euler-Poincare problem (:func:`~.optimal.solve_segment`) between
its end-constraints (:class:`~.constraints.EndConstraints`), with the targets zeta_bar plus the
low-passed camera velocity when ``lowpass_sigma`` > 0. A restart frame keeps the last correction
released and the next segment starts from it (4.4).
"""
from __future__ import annotations

import time
import numpy as np

from ..lie import LieGroup
from ..motion import MotionEstimate
from .constraints import EndConstraints
from .keyframes import KeyframeDetector
from .optimal import solve_segment
from .plan_types import Correction, OpenSegment, PlannerParams, PlanState, SegmentInfo


class KeyframeSmoother:
    """The ``ep`` mode behind :class:`~.planner.PathPlanner` (module docstring)."""

    def __init__(self, params: PlannerParams, group: LieGroup) -> None:
        self.params, self.group = params, group
        self.detector = KeyframeDetector(params.keyframes)
        self.ends = EndConstraints(group, params.end, params.alpha, params.beta)
        self._C0 = np.eye(4)  # the correction the open segment starts from
        self._history: list[np.ndarray] = []  # camera-motion twists of recent frames (for the low-pass)

    def begin(self, pose: np.ndarray, restart: bool) -> None:
        """A new segment (the keyframe detector starts again); in a new pose chain (``restart``) it starts
        at the real camera ``pose``, uncorrected."""
        self.detector.reset()
        if not restart:
            return
        self._C0 = np.eye(4)
        self.ends.reset(pose)
        self._history = []

    def start(self, pl: PlanState, seq: int) -> list[Correction]:
        """The stream's first frame: a keyframe with no correction, released at once."""
        return [Correction(seq, np.eye(4), pl.segment_count, True, camera=pl.pose.copy(), chain=pl.chain)]

    def restart(self, pl: PlanState, motion: MotionEstimate, why: str) -> list[Correction]:
        """After an invalid motion: the frame keeps the last correction released and the next segment
        starts from it (docs/method.md 4.4)."""
        held, history = pl.held, self._history
        pl.begin(motion.seq_next, restart=True)
        self._C0, self._history = held.copy(), history
        return [Correction(motion.seq_next, held.copy(), pl.segment_count, True, True,
                           f"{why}; the last correction held", camera=pl.pose.copy(), chain=pl.chain,
                           motion="restart")]

    def push(self, motion: MotionEstimate, window: OpenSegment) -> str:
        """The new frame's motion kept for the low-pass; the keyframe detector's word on it (the interval,
        a turn, or not a keyframe)."""
        if self.params.lowpass_sigma > 0:
            self._history.append(motion.twist if motion.twist is not None else self.group.log(motion.matrix))
            self._history = self._history[-(len(window.seqs) + int(np.ceil(3 * self.params.lowpass_sigma))):]
        return self.detector.push(motion.matrix)

    def close(self, pl: PlanState, closed_by: str) -> list[Correction]:
        """The open segment's optimal path between its end-constraints (docs/method.md 4.1-4.2)."""
        seg, win = pl.segment_count, pl.window
        zbar, smooth = self._targets(win)
        C1 = self.ends.at_keyframe(pl.pose, len(win.seqs), smooth)
        t0 = time.perf_counter()
        sol = solve_segment(self.group, np.asarray(win.motions), self._C0, C1, self.params.path, zbar=zbar)
        ms = (time.perf_counter() - t0) * 1e3
        pl.account(SegmentInfo(seg, win.start, win.seqs[-1], closed_by, sol.converged, sol.iterations,
                                       sol.residual, sol.cost, ms, sol.reason))
        last = len(win.seqs) - 1
        frames = list(enumerate(zip(win.seqs, win.path, win.kinds)))
        if sol.converged:
            out = [Correction(s, sol.corrections[i + 1], seg, i == last, reason=pl.notes.pop(s, ""), camera=X,
                              chain=pl.chain, motion=k) for i, (s, X, k) in frames]
            next_C0 = sol.corrections[-1]
        elif sol.fallback:  # not optimal, but smooth and on the end-constraints: used (docs/method.md 4.1)
            why = f"segment {seg} stabilized by the fallback path: {sol.reason}"
            out = [Correction(s, sol.corrections[i + 1], seg, i == last, True, why, camera=X, chain=pl.chain,
                              motion=k) for i, (s, X, k) in frames]
            next_C0 = sol.corrections[-1]
        else:
            why = f"segment {seg} not stabilized: {sol.reason}"
            out = [Correction(s, np.eye(4), seg, i == last, False, why) for i, s in enumerate(win.seqs)]
            next_C0 = np.eye(4)
            self.ends.reset(pl.pose)
        pl.begin(win.seqs[-1], restart=False)
        self._C0 = pl.held = next_C0
        return out

    def _targets(self, win: OpenSegment) -> tuple[np.ndarray, np.ndarray | None]:
        """zeta_bar of the open segment, plus the low-passed camera velocity when lowpass_sigma > 0.

        Beyond the paper: its zeta_bar undoes each frame's whole motion, so the
        stabilized camera moves at constant velocity between keyframes and a
        camera whose intended motion curves gets a kink at every keyframe. Adding
        back s_t, a Gaussian low-pass of the camera's own twists (frames up to the
        closing keyframe only, the window truncated there), keeps the slow
        motion's shape: the optimum becomes zeta = zeta_bar + s + c.
        """
        zbar = np.asarray(win.zbar)
        sigma = self.params.lowpass_sigma
        if sigma <= 0:
            return zbar, None
        n = len(zbar)
        H = np.asarray(self._history[-(n + int(np.ceil(3 * sigma))):])
        idx = np.arange(len(H))
        out = zbar.copy()
        for i, t in enumerate(range(len(H) - n, len(H))):
            w = np.exp(-0.5 * ((idx - t) / sigma) ** 2)
            out[i] = zbar[i] + (w @ H) / w.sum()
        smooth = np.eye(4)
        for E in self.group.exp(out - zbar):
            smooth = smooth @ E
        return out, smooth

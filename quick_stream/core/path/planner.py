"""Online path planning with one-segment latency: motions in, per-frame corrections out.

The planner integrates the camera path g_c and, when a keyframe closes a segment,
releases the corrections g_s of the segment's frames. Two modes (docs/method.md section 4):

* ``smooth`` (default, :class:`~.window_smoother.WindowSmoother`): the smoothed path of a window
  of ``keyframes.interval`` frames (:mod:`.smoother`), kept inside the crop budget (:mod:`.budget`)
  with a planned zoom track, then the EP problem through it; the window's last ``lookahead``
  frames are planned again with the next window before they are released;
* ``ep`` (:class:`~.keyframe_smoother.KeyframeSmoother`): the optimal path of each segment
  (:func:`~.optimal.solve_segment`) between the end-constraints
  (:class:`~.constraints.EndConstraints`), the paper's method.

The planner keeps what both share (the camera path g_c, the open segment's frames, the pose chain,
the notes on fallbacks, the segments' accounts); each mode is one class behind one interface
(:class:`~.plan_types.PathSmoother`).

The streaming ``motion`` service and the offline ``stabilize`` command both drive
this same object.

Fallbacks are visible, never silent: each correction says how the motion into its frame was known
(``Correction.motion``, docs/method.md 2.4); a motion less certain pulls its frame's pose less (8a);
an invalid motion closes the segment at the frame before it and opens a new pose chain, the path
handed over without a jump (4.4: the restart frame corrected, named, with the reason); an ``ep``
segment whose solver does not converge gets the solver's fallback path (4.1), valid with the
reason, and identity corrections, flagged, only if that misses the end-constraint.
"""
from __future__ import annotations

import numpy as np

from ..lie import LieGroup, get_group
from ..motion import MotionEstimate
from ..render.warp import WarpParams
from .frame_model import FrameModel
from .keyframe_smoother import KeyframeSmoother
from .plan_types import (CORRECTION_MOTIONS, MIN_TRUST, PATH_MODES, Correction, OpenSegment, PathSmoother,
                         PlannerParams, PlanState, SegmentInfo)
from .window_smoother import WindowSmoother

__all__ = ["PathPlanner", "PathSmoother", "PlanState", "PlannerParams", "Correction", "SegmentInfo", "OpenSegment",
           "PATH_MODES", "CORRECTION_MOTIONS", "MIN_TRUST"]


class PathPlanner:
    """One stream's camera path and stabilized path: motions in, released corrections out."""

    def __init__(self, params: PlannerParams | None = None, warp: WarpParams | None = None,
                 keep_segments: int | None = None) -> None:
        """``warp``: the renderer's warp parameters (the crop budget fits the same mesh);
        ``keep_segments``: how many of the newest segments' accounts ``segments`` keeps (None: all, for
        a report; a live service keeps a few, so a stream of days does not grow it without end)."""
        self.params = p = params or PlannerParams()
        p.validate()
        self.warp = warp or WarpParams()
        self.group: LieGroup = get_group(p.group)
        self.smoother: PathSmoother = (WindowSmoother(p, self.group, self.warp) if p.mode == "smooth"
                                       else KeyframeSmoother(p, self.group))
        self.segments: list[SegmentInfo] = []  # the newest ``keep_segments`` segments' accounts, oldest first
        self.segment_count = 0  # segments closed in the stream
        self.keep_segments = keep_segments
        self.window = OpenSegment()  # the frames not released yet
        self.pose = np.eye(4)  # g_c at the newest frame
        self.chain = -1  # counts path restarts: camera poses compose within one chain only
        self._model: FrameModel | None = None  # the newest frame model (frames without one reuse it)
        self.held: np.ndarray = np.eye(4)  # the newest correction released (a restart holds it)
        self.notes: dict[int, str] = {}  # why a frame of the open segment is special (a fallback, a restart)

    def start(self, seq: int) -> list[Correction]:
        """First frame of the stream. ``ep``: a keyframe with no correction, released at once.
        ``smooth``: the first frame of the first window, corrected and released with it (nothing now)."""
        self.begin(seq, restart=True)
        return self.smoother.start(self, seq)

    def begin(self, seq: int, restart: bool) -> None:
        """An empty segment from frame ``seq``; ``restart``: in a new pose chain, at the camera's pose."""
        self.window.reset(seq)
        self.chain += restart
        self.smoother.begin(self.pose, restart)

    def account(self, info: SegmentInfo) -> None:
        """A segment closed: its account kept (the oldest let go beyond ``keep_segments``) and counted."""
        self.segments.append(info)
        self.segment_count += 1
        if self.keep_segments is not None and len(self.segments) > self.keep_segments:
            del self.segments[:len(self.segments) - self.keep_segments]

    def trust(self, sigma: float) -> float:
        """Closeness weight of a frame whose motion's rotation has standard deviation ``sigma`` (rad),
        docs/method.md (8a): 1 up to ``motion_sigma``, then (motion_sigma / sigma)^2, at least MIN_TRUST."""
        s = self.params.motion_sigma
        return 1.0 if not sigma > s else max((s / sigma) ** 2, MIN_TRUST)

    def push(self, motion: MotionEstimate, model: FrameModel | None = None) -> list[Correction]:
        """Add the motion from frame ``motion.seq`` to ``motion.seq_next``; returns released corrections.

        ``model``: 3D points of frame ``motion.seq_next`` for the crop budget (smooth mode;
        without one the frame reuses the newest model)."""
        if self.window.start is None:
            raise RuntimeError("PathPlanner.start() must be called with the first frame")
        if not motion.valid:
            out = self._close("invalid-motion") if self.window.seqs else []
            why = f"motion {motion.seq}->{motion.seq_next} not known ({motion.reason}): path restarted"
            return out + self.smoother.restart(self, motion, why)
        zb = motion.zeta_bar if motion.zeta_bar is not None else self.group.log(self.group.inverse(motion.matrix))
        if motion.kind in ("rotation", "bridge"):
            self.notes[motion.seq_next] = f"motion {motion.seq}->{motion.seq_next}: {motion.reason}"
        closeness = (1.0 if motion.covariance is None and motion.kind == "fit"
                     else self.trust(motion.rotation_sigma))
        self.pose = self.pose @ motion.matrix
        if model is not None:
            self._model = model
        self.window.add(motion.seq_next, zb, motion.matrix, self.pose.copy(), self._model, motion.kind, closeness)
        why = self.smoother.push(motion, self.window)
        return self._close(why) if why else []

    def finish(self) -> list[Correction]:
        """End of stream: close the open segment at the last frame."""
        return self._close("end-of-stream") if self.window.seqs else []

    def _close(self, closed_by: str) -> list[Correction]:
        out = self.smoother.close(self, closed_by)
        self.notes = {s: n for s, n in self.notes.items() if s in self.window.seqs}  # released frames' notes went out
        return out

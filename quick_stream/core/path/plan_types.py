"""What the path planner takes and gives (docs/method.md section 4): its parameters, the correction of
one frame, the account of one segment, the open segment's frames, and the two sides of the seam
between the planner (:mod:`.planner`) and its smoothers (:mod:`.window_smoother`,
:mod:`.keyframe_smoother`): :class:`PathSmoother`, what the planner asks of a smoother, and
:class:`PlanState`, what a smoother reads and changes of the planner.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..motion import MotionEstimate
from .budget import BudgetParams
from .frame_model import FrameModel
from .keyframes import KeyframeParams
from .optimal import PathParams

PATH_MODES = ("smooth", "ep")
CORRECTION_MOTIONS = ("start", "fit", "rotation", "bridge", "restart")  # Correction.motion: the stream's first
# frame, then how the motion into the frame was known (MotionEstimate.kind), or not at all (docs/method.md 2.4)
MIN_TRUST = 1e-4  # the least closeness weight of a frame (its motion not known at all: a restart), (8a)


@dataclass
class PlannerParams:
    group: str = "se3"
    mode: str = "smooth"  # smooth: smoothed path with a crop budget (docs/method.md 4.3) | ep: targets of 4.2
    smoothness: float = 1e4  # smooth: lam of docs/method.md (8); gain 0.5 at 0.47 Hz at 30 fps
    velocity_weight: float = 100.0  # smooth: weight of the low-passed camera velocity as the path's velocity target
    velocity_sigma: float = 20.0  # smooth: frames; Gaussian low-pass of that velocity (window ends at the keyframe)
    motion_sigma: float = 0.005  # smooth: rad; a motion whose rotation is less certain pulls its frame's pose
    # less: closeness weight (motion_sigma / sigma)^2 below 1 (docs/method.md (8a)); bridges and restarts
    lookahead: int = 15  # smooth: of each keyframe interval's frames, the last this many are planned but
    # released only with the next segment (re-planned with more frames after them); < the interval
    budget: BudgetParams = field(default_factory=BudgetParams)  # smooth: the crop budget
    zoom_smoothness: float = 1000.0  # smooth with a budget: mu of the zoom track, docs/method.md (11): gain 0.5 at 0.85 Hz
    zoom_hold: float = 1e-3  # smooth with a budget: pull towards zoom 1 of the look-ahead frames' zooms (1 = as released)
    # smooth: the corrections' tilt (the angle between the virtual and the real optical axis) held below this, the
    # rest of the turn given as an image shift (docs/method.md 4.5, (19)); 0 = no cap
    max_tilt_deg: float = 5.0
    tilt_knee_deg: float = 2.0  # smooth with a tilt cap: c(theta) leaves theta unchanged up to max_tilt - knee
    end: str = "smoothed"  # ep: end-constraint mode: identity | smoothed
    alpha: float = 0.1  # ep, smoothed ends: keyframe-pose filter gains
    beta: float = 0.4
    lowpass_sigma: float = 20.0  # ep: frames; > 0: keep the low-passed camera velocity (0: the paper, undo all)
    keyframes: KeyframeParams = field(default_factory=KeyframeParams)
    path: PathParams = field(default_factory=PathParams)

    def validate(self) -> None:
        if self.mode not in PATH_MODES:
            raise ValueError(f"path mode must be one of {PATH_MODES}, got {self.mode!r}")
        if not (np.isfinite(self.smoothness) and self.smoothness >= 0):
            raise ValueError(f"smoothness must be a finite number >= 0, got {self.smoothness!r}")
        if not (np.isfinite(self.motion_sigma) and self.motion_sigma > 0):
            raise ValueError(f"motion_sigma must be a finite number > 0, got {self.motion_sigma!r}")
        self.validate_tilt()
        self.budget.validate()
        self.keyframes.validate()
        if self.mode == "smooth" and not 0 <= self.lookahead < self.keyframes.interval:
            raise ValueError(f"look-ahead must be >= 0 and below the keyframe interval "
                             f"({self.keyframes.interval}), got {self.lookahead}")

    def validate_tilt(self) -> None:
        """The tilt cap's settings (docs/method.md 4.5): 0 <= max_tilt_deg < 90, 0 < tilt_knee_deg < 90."""
        if not (np.isfinite(self.max_tilt_deg) and 0 <= self.max_tilt_deg < 90
                and np.isfinite(self.tilt_knee_deg) and 0 < self.tilt_knee_deg < 90):
            raise ValueError(f"the tilt cap needs 0 <= max_tilt_deg < 90 (degrees; 0: no cap) and 0 < tilt_knee_deg < 90, "
                             f"got {self.max_tilt_deg!r} and {self.tilt_knee_deg!r}")


@dataclass
class Correction:
    """Stabilizing transformation g_s for one frame (virtual camera pose relative to the real one)."""

    seq: int
    matrix: np.ndarray
    segment: int
    keyframe: bool
    valid: bool = True
    reason: str = ""
    zoom: float | None = None  # framing zoom planned with the path (smooth mode with a budget), else None
    camera: np.ndarray | None = None  # g_c: the real camera's pose in the planner's chain (renderer's border fill)
    chain: int = -1  # the chain ``camera`` is in: poses of one chain compose (a path restart opens a new one)
    motion: str = "fit"  # how the motion into this frame was known (MotionEstimate.kind; "restart": not known)
    # frames before this one that the flow stage shed (never decoded by any stage; docs/architecture.md,
    # Overload): the render stage lets them go instead of rendering them uncorrected
    shed: tuple[int, ...] = ()

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
    budget_frames: int = 0  # smooth mode: frames that got crop-budget constraints
    budget_margin_px: float = float("inf")  # smooth mode: smallest margin to the border the released frames
    # keep at their released zoom (px; < 0: over budget; docs/method.md (10), (10a))
    budget_rounds: int = 0  # smooth mode: QPs the budget's SQP solved (0: the path was kept, zoom planned alone)
    budget_converged: bool = True  # smooth mode: the SQP met its stopping rule (False: stopped at max_rounds)
    budget_gap: float = 0.0  # smooth mode: share of the budget's cost its last QP still promised to save


@dataclass
class OpenSegment:
    """The frames of the segment (smooth: the window) not released yet, in order, one entry each: seq,
    zeta_bar of the motion into it, that motion, the camera pose g_c, the frame model for the crop
    budget, how the motion was known and the closeness weight (8a). ``start``: the seq of the frame the
    segment starts from (its opening keyframe, or the window's first frame)."""

    start: int | None = None
    seqs: list[int] = field(default_factory=list)
    zbar: list[np.ndarray] = field(default_factory=list)
    motions: list[np.ndarray] = field(default_factory=list)
    path: list[np.ndarray] = field(default_factory=list)
    models: list[FrameModel | None] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    closeness: list[float] = field(default_factory=list)

    def reset(self, start: int) -> None:
        """An empty segment starting from frame ``start``."""
        self.start = start
        self.seqs, self.zbar, self.motions, self.path, self.models, self.kinds, self.closeness = \
            [], [], [], [], [], [], []

    def add(self, seq: int, zbar: np.ndarray, motion: np.ndarray, pose: np.ndarray, model: FrameModel | None,
            kind: str, closeness: float) -> None:
        self.seqs.append(seq)
        self.zbar.append(zbar)
        self.motions.append(motion)
        self.path.append(pose)
        self.models.append(model)
        self.kinds.append(kind)
        self.closeness.append(closeness)

    def keep_from(self, i: int) -> None:
        """Only the frames from index ``i`` on stay open (the look-ahead, planned again); the segment
        then starts from the frame before them."""
        start = self.seqs[i - 1]
        for name in ("seqs", "zbar", "motions", "path", "models", "kinds", "closeness"):
            setattr(self, name, getattr(self, name)[i:])
        self.start = start


class PlanState(Protocol):
    """What a smoother reads and changes of the planner (:class:`~.planner.PathPlanner`): the open
    segment, the camera pose g_c at its newest frame, the pose chain, the notes on its frames, the
    newest correction released (``held``) and the segments' accounts."""

    window: OpenSegment
    pose: np.ndarray
    chain: int
    notes: dict[int, str]
    held: np.ndarray
    segment_count: int

    def begin(self, seq: int, restart: bool) -> None:
        """An empty segment from frame ``seq``; ``restart``: in a new pose chain."""

    def account(self, info: SegmentInfo) -> None:
        """A segment closed: its account kept and counted."""

    def trust(self, sigma: float) -> float:
        """Closeness weight of a frame whose motion's rotation has standard deviation ``sigma``, (8a)."""


class PathSmoother(Protocol):
    """One way of smoothing the path (``PlannerParams.mode``): what the planner asks of it."""

    def begin(self, pose: np.ndarray, restart: bool) -> None:
        """A new segment opens; ``restart``: in a new pose chain, at the real camera ``pose`` (the
        stream's start or after an invalid motion)."""

    def start(self, pl: PlanState, seq: int) -> list[Correction]:
        """The stream's first frame ``seq``; the corrections released at once."""

    def restart(self, pl: PlanState, motion: MotionEstimate, why: str) -> list[Correction]:
        """After the invalid ``motion``: a new pose chain from ``motion.seq_next``, handed over without a
        jump (docs/method.md 4.4); the corrections released at once."""

    def push(self, motion: MotionEstimate, window: OpenSegment) -> str:
        """Take the motion into the window's newest frame; whether that frame closes the segment: why, or ''."""

    def close(self, pl: PlanState, closed_by: str) -> list[Correction]:
        """The open segment's path: the corrections it releases (the frames it keeps stay open)."""

"""Online path planning with one-segment latency: motions in, per-frame corrections out.

The planner integrates the camera path g_c and, when a keyframe closes a segment,
releases the corrections g_s of the segment's frames. Two modes (docs/method.md section 4):

* ``smooth`` (default): the smoothed path of a window of ``keyframes.interval`` frames
  (:mod:`.smoother`), kept inside the crop budget (:mod:`.budget`) with a planned zoom
  track (:mod:`.zoom`), then the EP problem through it; the window's last ``lookahead``
  frames are planned again with the next window before they are released;
* ``ep``: the optimal path of each segment (:func:`~.optimal.solve_segment`) between
  the end-constraints (:class:`~.constraints.EndConstraints`), the paper's method.

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

import time
from dataclasses import dataclass, field

import numpy as np

from ..lie import LieGroup, get_group
from ..motion import MotionEstimate
from ..render.warp import WarpParams
from .budget import BudgetParams, BudgetReport, constrain
from .frame_model import FrameModel, SegmentMeshes
from .constraints import EndConstraints
from .coverage import bounded_zoom_track, fill_need
from .keyframes import KeyframeDetector, KeyframeParams
from .optimal import PathParams, solve_segment
from .smoother import SegmentSystem, chart_path, segment_system


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
        self.budget.validate()
        self.keyframes.validate()
        if self.mode == "smooth" and not 0 <= self.lookahead < self.keyframes.interval:
            raise ValueError(f"look-ahead must be >= 0 and below the keyframe interval "
                             f"({self.keyframes.interval}), got {self.lookahead}")


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


class PathPlanner:
    """One stream's keyframes, end-constraints and optimal path."""

    def __init__(self, params: PlannerParams | None = None, warp: WarpParams | None = None) -> None:
        """``warp``: the renderer's warp parameters (the crop budget fits the same mesh)."""
        self.params = p = params or PlannerParams()
        p.validate()
        self.warp = warp or WarpParams()
        self.group: LieGroup = get_group(p.group)
        self.detector = KeyframeDetector(p.keyframes)
        self.ends = EndConstraints(self.group, p.end, p.alpha, p.beta)
        self.segments: list[SegmentInfo] = []
        self._pose = np.eye(4)  # g_c at the newest frame
        self._chain = -1  # counts path restarts: camera poses compose within one chain only
        self._start: int | None = None  # seq of the open segment's first keyframe
        self._C0 = np.eye(4)
        self._seqs: list[int] = []  # frames after the start, in order
        self._zbar: list[np.ndarray] = []
        self._motions: list[np.ndarray] = []
        self._history: list[np.ndarray] = []  # camera-motion twists of recent frames (for the low-pass)
        self._path: list[np.ndarray] = []  # smooth mode: camera poses g_c of the open segment's frames
        self._models: list[FrameModel | None] = []  # smooth mode: frame models of the open segment's frames
        self._model: FrameModel | None = None  # the newest frame model (frames without one reuse it)
        self._committed: list[np.ndarray] = [np.eye(4)]  # smooth mode: last <= 3 stabilized poses, oldest first
        self._systems: dict[tuple[int, int], SegmentSystem] = {}
        self._zooms: list[float] = [1.0]  # smooth mode with a budget: last <= 3 planned zooms
        self._real: list[np.ndarray] = [np.eye(4)]  # smooth mode: real camera poses up to the open segment's start
        self._real_c: list[float] = [1.0]  # ... and how much each is to be trusted (closeness weight, (8a))
        self._kinds: list[str] = []  # how the motion into each frame of the open segment was known
        self._closeness: list[float] = []  # smooth mode: each open frame's closeness weight (8a)
        self._held: np.ndarray = np.eye(4)  # the newest correction released (a restart holds it)
        self._notes: dict[int, str] = {}  # why a frame of the open segment is special (a fallback, a restart)
        if p.mode == "smooth" and p.budget.enabled:
            # The budget's QP solver (scipy.optimize, ~0.2 s to import) is loaded here, before the
            # stream, not inside the first segment's close, where it would delay the first release.
            import scipy.optimize  # noqa: F401

    def start(self, seq: int) -> list[Correction]:
        """First frame of the stream. ``ep``: a keyframe with no correction, released at once.
        ``smooth``: the first frame of the first window, corrected and released with it (nothing now)."""
        self._begin(seq, restart=True)
        self._zooms = []
        if self.params.mode == "smooth":
            self._committed, self._real, self._real_c = [], [], []  # no past: the first window places its first frame
            self._open_with(seq, "start", 1.0)
            return []
        return [Correction(seq, np.eye(4), len(self.segments), True, camera=self._pose.copy(), chain=self._chain)]

    def _begin(self, seq: int, restart: bool) -> None:
        self._start = seq
        self._seqs, self._zbar, self._motions, self._path, self._models = [], [], [], [], []
        self._kinds, self._closeness = [], []
        self.detector.reset()
        if restart:
            self._chain += 1
            self._C0 = np.eye(4)
            self.ends.reset(self._pose)
            self._history = []
            self._committed = [self._pose.copy()]  # the path restarts at the real camera, at rest
            self._real, self._real_c = [self._pose.copy()], [1.0]

    def _open_with(self, seq: int, kind: str, closeness: float) -> None:
        """Smooth mode: the open window's first frame is ``seq`` itself, placed with the window."""
        self._seqs, self._path, self._models = [seq], [self._pose.copy()], [None]
        self._zbar, self._motions = [np.zeros(self.group.dim)], [np.eye(4)]
        self._kinds, self._closeness = [kind], [closeness]

    def _restart(self, motion: MotionEstimate) -> list[Correction]:
        """After an invalid motion into ``motion.seq_next``: a new pose chain (the motion is not known, so
        no pose before it composes with one after it), and a handover with no jump (docs/method.md 4.4):
        the stabilized path goes on from its committed past (smooth mode: the restart frame is placed with
        the next window, its pose barely trusted; ``ep``: the frame keeps the last correction released
        and the next segment starts from it)."""
        held, committed, real, real_c, history = self._held, self._committed, self._real, self._real_c, self._history
        self._begin(motion.seq_next, restart=True)
        why = f"motion {motion.seq}->{motion.seq_next} not known ({motion.reason}): path restarted"
        if self.params.mode == "smooth":
            self._committed, self._real, self._real_c = committed, real, real_c
            self._open_with(motion.seq_next, "restart", self._trust(float("inf")))
            self._notes[motion.seq_next] = why
            return []
        self._C0, self._history = held.copy(), history
        return [Correction(motion.seq_next, held.copy(), len(self.segments), True, True,
                           f"{why}; the last correction held", camera=self._pose.copy(), chain=self._chain,
                           motion="restart")]

    def _trust(self, sigma: float) -> float:
        """Closeness weight of a frame whose motion's rotation has standard deviation ``sigma`` (rad),
        docs/method.md (8a): 1 up to ``motion_sigma``, then (motion_sigma / sigma)^2, at least MIN_TRUST."""
        s = self.params.motion_sigma
        return 1.0 if not sigma > s else max((s / sigma) ** 2, MIN_TRUST)

    def push(self, motion: MotionEstimate, model: FrameModel | None = None) -> list[Correction]:
        """Add the motion from frame ``motion.seq`` to ``motion.seq_next``; returns released corrections.

        ``model``: 3D points of frame ``motion.seq_next`` for the crop budget (smooth mode;
        without one the frame reuses the newest model)."""
        if self._start is None:
            raise RuntimeError("PathPlanner.start() must be called with the first frame")
        if not motion.valid:
            out = self._close("invalid-motion") if self._seqs else []
            return out + self._restart(motion)
        zb = motion.zeta_bar if motion.zeta_bar is not None else self.group.log(self.group.inverse(motion.matrix))
        self._seqs.append(motion.seq_next)
        self._kinds.append(motion.kind)
        if motion.kind in ("rotation", "bridge"):
            self._notes[motion.seq_next] = f"motion {motion.seq}->{motion.seq_next}: {motion.reason}"
        self._closeness.append(1.0 if motion.covariance is None and motion.kind == "fit"
                               else self._trust(motion.rotation_sigma))
        self._zbar.append(zb)
        self._motions.append(motion.matrix)
        if self.params.lowpass_sigma > 0:
            self._history.append(motion.twist if motion.twist is not None else self.group.log(motion.matrix))
        self._pose = self._pose @ motion.matrix
        self._path.append(self._pose.copy())
        if model is not None:
            self._model = model
        self._models.append(self._model)
        if self.params.mode == "smooth":  # the window is the keyframe interval; the smoother needs no turn keyframes
            why = "interval" if len(self._path) >= self.params.keyframes.interval else ""
        else:
            why = self.detector.push(motion.matrix)
        return self._close(why) if why else []

    def finish(self) -> list[Correction]:
        """End of stream: close the open segment at the last frame."""
        return self._close("end-of-stream") if self._seqs else []

    def _close(self, closed_by: str) -> list[Correction]:
        out = self._close_smooth(closed_by) if self.params.mode == "smooth" else self._close_ep(closed_by)
        self._notes = {s: n for s, n in self._notes.items() if s in self._seqs}  # released frames' notes went out
        return out

    def _close_smooth(self, closed_by: str) -> list[Correction]:
        """Smoothed path with the crop budget (docs/method.md 4.3), then the EP path through it."""
        seg = len(self.segments)
        g, p = self.group, self.params
        t0 = time.perf_counter()
        # Released: the segment up to its closing keyframe; the look-ahead frames after it are
        # planned again with the next segment (none at the end of the stream or a break).
        X = np.asarray(self._path)
        N = len(X)
        R = N - p.lookahead if closed_by == "interval" else N
        base = self._committed[-1] if self._committed else X[0]
        x = chart_path(g, base, X)
        committed = chart_path(g, base, np.asarray(self._committed)) if self._committed else np.zeros((0, g.dim))
        trust = np.asarray(self._closeness)
        key = (N, len(committed))
        if not np.all(trust == 1.0):  # a frame whose motion is less certain pulls less (docs/method.md (8a))
            system = segment_system(N, len(committed), p.smoothness, p.velocity_weight, closeness=trust)
        else:
            if key not in self._systems:
                self._systems[key] = segment_system(N, len(committed), p.smoothness, p.velocity_weight)
            system = self._systems[key]
        q = system.unconstrained(x, committed, self._velocity_targets(base) if p.velocity_weight > 0 else None)
        rep = BudgetReport()
        zooms: list[float | None] = [None] * N
        if p.budget.enabled:
            meshes = SegmentMeshes(self._models, self.warp)
            Xinv_base = np.linalg.inv(X) @ base

            def correction(frames: np.ndarray, P: np.ndarray) -> np.ndarray:
                return Xinv_base[frames][:, None] @ g.exp(P)

            hold = np.ones(N)  # the look-ahead frames' zooms are provisional: not pulled towards 1
            hold[R:] = p.zoom_hold
            zoom_system = segment_system(N, len(self._zooms), p.zoom_smoothness, closeness=hold)
            q, w, rep = constrain(g, system, q, correction, meshes, p.budget, zoom_system,
                                  1.0 / np.asarray(self._zooms))
            if p.budget.fill > 0 and p.budget.fill_reach > 0:
                w = self._fill_zoom(meshes, correction, X, base @ g.exp(q), q, w, rep.upper, zoom_system)
            zooms = [float(z) for z in np.clip(1.0 / np.maximum(w, 1e-9), 1.0, p.budget.max_zoom)]
            rep.worst_margin_px = rep.margin_px(1.0 / np.asarray(zooms[:R]), p.budget.margin_px)  # as released
        # The EP problem (docs/method.md (4)-(6)) with the smoothed path's own velocities as
        # targets and its keyframe pose as end-constraint: its solution is that path.
        Q = g.exp(q[:R])
        targets = g.log(np.linalg.inv(np.concatenate([np.eye(4)[None], Q[:-1]])) @ Q)
        sol = solve_segment(g, np.eye(4)[None].repeat(R, 0), None, Q[-1], p.path, zbar=targets)
        path = base[None] @ (sol.corrections[1:] if sol.converged else Q)
        corrections = np.linalg.inv(X[:R]) @ path
        ms = (time.perf_counter() - t0) * 1e3
        self.segments.append(SegmentInfo(seg, self._start, self._seqs[R - 1], closed_by, sol.converged,
                                         sol.iterations, sol.residual, sol.cost, ms, sol.reason, rep.constrained,
                                         rep.worst_margin_px, rep.rounds, rep.converged, rep.gap))
        if zooms[0] is not None:
            self._zooms = (self._zooms + zooms[:R])[-3:]
        out = [Correction(s, corrections[i], seg, i == R - 1, reason=self._notes.pop(s, ""), zoom=zooms[i],
                          camera=X[i], chain=self._chain, motion=self._kinds[i])
               for i, s in enumerate(self._seqs[:R])]
        self._held = corrections[R - 1]
        self._committed = (self._committed + list(path))[-3:]
        keep = int(3 * p.velocity_sigma) + 2
        self._real, self._real_c = (self._real + list(X[:R]))[-keep:], (self._real_c + list(trust[:R]))[-keep:]
        kept = (self._seqs[R:], self._zbar[R:], self._motions[R:], self._path[R:], self._models[R:],
                self._kinds[R:], self._closeness[R:])
        self._begin(self._seqs[R - 1], restart=False)
        (self._seqs, self._zbar, self._motions, self._path, self._models, self._kinds,
         self._closeness) = (list(k) for k in kept)
        return out

    def _fill_zoom(self, meshes: SegmentMeshes, correction, X: np.ndarray, virtual: np.ndarray, q: np.ndarray,
                   w: np.ndarray, upper: np.ndarray, zoom_system: SegmentSystem) -> np.ndarray:
        """The zoom track ``w`` re-planned where the border fill will not cover what the budget's fill
        band leaves (docs/method.md (10b)): neighbours within the fill's reach, the committed past included."""
        b = self.params.budget
        if upper is None:  # no frame model in the window: nothing to plan with
            return w
        has = np.flatnonzero(meshes.frames >= 0)
        has = has[upper[has] - b.fill < w[has]]  # frames whose own mesh does not cover the planned crop
        if has.size == 0:
            return w
        past = np.asarray(self._real[-b.fill_reach:]).reshape(-1, 4, 4)
        cams = np.concatenate([past, X])
        virt = np.concatenate([past, virtual])  # the past's virtual poses are never read
        lo = 1.0 / np.clip(w[has], 1e-9, 1.0)
        need = fill_need(meshes, has, correction(has, q[has][:, None, :])[:, 0], cams, virt, lo, b.max_zoom,
                         b.fill_reach)
        if np.all(need <= lo * (1 + 1e-9)):
            return w
        bound = upper.copy()
        bound[has] = np.minimum(bound[has], 1.0 / need)
        return bounded_zoom_track(zoom_system, 1.0 / np.asarray(self._zooms), bound, 1.0 / b.max_zoom)

    def _velocity_targets(self, base: np.ndarray) -> np.ndarray:
        """Low-passed velocity of the real path, in the segment's chart, for the steps into its frames; each
        step weighted by the trust in the less certain of its two frames (docs/method.md (8a))."""
        p, g = self.params, self.group
        k = len(self._path) + int(3 * p.velocity_sigma) + 1
        hist, hist_c = (self._real[-k:], self._real_c[-k:]) if self._real else (self._path[:1], self._closeness[:1])
        xs = chart_path(g, base, np.asarray(hist + self._path))
        vel = np.diff(xs, axis=0)
        c = np.asarray(hist_c + self._closeness)
        trust = np.minimum(c[:-1], c[1:])  # a step is as certain as the less certain of its two frames
        n = len(self._path)
        idx = np.arange(len(vel))
        out = np.empty((n, vel.shape[1]))
        for i, t in enumerate(range(len(vel) - n, len(vel))):
            w = np.exp(-0.5 * ((idx - t) / p.velocity_sigma) ** 2) * trust
            out[i] = w @ vel / w.sum()
        return out

    def _close_ep(self, closed_by: str) -> list[Correction]:
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
            out = [Correction(s, sol.corrections[i + 1], seg, i == last, reason=self._notes.pop(s, ""), camera=X,
                              chain=self._chain, motion=k)
                   for i, (s, X, k) in enumerate(zip(self._seqs, self._path, self._kinds))]
            next_C0 = sol.corrections[-1]
        elif sol.fallback:  # not optimal, but smooth and on the end-constraints: used (docs/method.md 4.1)
            why = f"segment {seg} stabilized by the fallback path: {sol.reason}"
            out = [Correction(s, sol.corrections[i + 1], seg, i == last, True, why, camera=X, chain=self._chain,
                              motion=k) for i, (s, X, k) in enumerate(zip(self._seqs, self._path, self._kinds))]
            next_C0 = sol.corrections[-1]
        else:
            why = f"segment {seg} not stabilized: {sol.reason}"
            out = [Correction(s, np.eye(4), seg, i == last, False, why) for i, s in enumerate(self._seqs)]
            next_C0 = np.eye(4)
            self.ends.reset(self._pose)
        end_seq = self._seqs[-1]
        self._begin(end_seq, restart=False)
        self._C0 = self._held = next_C0
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

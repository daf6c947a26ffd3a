"""The ``smooth`` path (the default): a window's smoothed path in the crop budget (docs/method.md 4.3).

Each window of ``keyframes.interval`` frames gets the smoothed path (8) in the stabilized camera's own
chart, continuing the committed past (:mod:`.smoother`), bent into the crop budget (10)-(11) with a
planned zoom track (:mod:`.budget`, :mod:`.coverage`), then the EP problem through it (its solution is
that path); the last ``lookahead`` frames are planned again with the next window before they are
released. A restart frame is placed with the next window, its pose barely trusted (4.4).
"""
from __future__ import annotations

import time
import numpy as np

from ..lie import LieGroup
from ..motion import MotionEstimate
from ..render.warp import WarpParams
from .budget import BudgetReport, constrain
from .coverage import bounded_zoom_track, fill_need
from .frame_model import SegmentMeshes
from .optimal import solve_segment
from .plan_types import Correction, OpenSegment, PlannerParams, PlanState, SegmentInfo
from .smoother import SegmentSystem, chart_path, segment_system
from .tilt import limit_tilt


class WindowSmoother:
    """The ``smooth`` mode behind :class:`~.planner.PathPlanner` (module docstring)."""

    def __init__(self, params: PlannerParams, group: LieGroup, warp: WarpParams) -> None:
        self.params, self.group, self.warp = params, group, warp
        self._committed: list[np.ndarray] = [np.eye(4)]  # last <= 3 stabilized poses, oldest first
        self._systems: dict[tuple[int, int], SegmentSystem] = {}
        self._zooms: list[float] = [1.0]  # with a budget: last <= 3 planned zooms
        self._real: list[np.ndarray] = [np.eye(4)]  # real camera poses up to the open window's start
        self._real_c: list[float] = [1.0]  # ... and how much each is to be trusted (closeness weight, (8a))
        if params.budget.enabled:
            # The budget's QP solver (scipy.optimize, ~0.2 s to import) is loaded here, before the
            # stream, not inside the first window's close, where it would delay the first release.
            import scipy.optimize  # noqa: F401

    def begin(self, pose: np.ndarray, restart: bool) -> None:
        """Nothing to reset: the stabilized path goes on from its committed past across a new pose chain
        (:meth:`restart`), and the stream's start clears it (:meth:`start`)."""

    def start(self, pl: PlanState, seq: int) -> list[Correction]:
        """The stream's first frame: the first window's first frame, placed with it (no past), nothing now."""
        self._zooms, self._committed, self._real, self._real_c = [], [], [], []
        self._open_with(pl, seq, "start", 1.0)
        return []

    def restart(self, pl: PlanState, motion: MotionEstimate, why: str) -> list[Correction]:
        """After an invalid motion: the stabilized path goes on from its committed past; the restart frame
        is placed with the next window, its pose barely trusted (docs/method.md 4.4)."""
        pl.begin(motion.seq_next, restart=True)
        self._open_with(pl, motion.seq_next, "restart", pl.trust(float("inf")))
        pl.notes[motion.seq_next] = why
        return []

    def _open_with(self, pl: PlanState, seq: int, kind: str, closeness: float) -> None:
        """The open window's first frame is ``seq`` itself, placed with the window."""
        pl.window.reset(seq)
        pl.window.add(seq, np.zeros(self.group.dim), np.eye(4), pl.pose.copy(), None, kind, closeness)

    def push(self, motion: MotionEstimate, window: OpenSegment) -> str:
        """The window is the keyframe interval (the smoother needs no turn keyframes)."""
        return "interval" if len(window.path) >= self.params.keyframes.interval else ""

    def close(self, pl: PlanState, closed_by: str) -> list[Correction]:
        """Smoothed path with the crop budget (docs/method.md 4.3), then the EP path through it."""
        seg = pl.segment_count
        g, p, win = self.group, self.params, pl.window
        t0 = time.perf_counter()
        # Released: the window up to its closing keyframe; the look-ahead frames after it are
        # planned again with the next window (none at the end of the stream or a break).
        X = np.asarray(win.path)
        N = len(X)
        R = N - p.lookahead if closed_by == "interval" else N
        base = self._committed[-1] if self._committed else X[0]
        x = chart_path(g, base, X)
        committed = chart_path(g, base, np.asarray(self._committed)) if self._committed else np.zeros((0, g.dim))
        trust = np.asarray(win.closeness)
        key = (N, len(committed))
        if not np.all(trust == 1.0):  # a frame whose motion is less certain pulls less (docs/method.md (8a))
            system = segment_system(N, len(committed), p.smoothness, p.velocity_weight, closeness=trust)
        else:
            if key not in self._systems:
                self._systems[key] = segment_system(N, len(committed), p.smoothness, p.velocity_weight)
            system = self._systems[key]
        q = system.unconstrained(x, committed, self._velocity_targets(win, base) if p.velocity_weight > 0 else None)
        rep = BudgetReport()
        zooms: list[float | None] = [None] * N
        if p.budget.enabled:
            meshes = SegmentMeshes(win.models, self.warp)
            Xinv_base = np.linalg.inv(X) @ base

            def correction(frames: np.ndarray, P: np.ndarray) -> np.ndarray:
                return self._capped(Xinv_base[frames][:, None] @ g.exp(P))

            hold = np.ones(N)  # the look-ahead frames' zooms are provisional: not pulled towards 1
            hold[R:] = p.zoom_hold
            zoom_system = segment_system(N, len(self._zooms), p.zoom_smoothness, closeness=hold)
            q, w, rep = constrain(g, system, q, correction, meshes, p.budget, zoom_system,
                                  1.0 / np.asarray(self._zooms))
            if p.budget.fill > 0 and p.budget.fill_reach > 0:
                virtual = base @ g.exp(q) if p.max_tilt_deg <= 0 else X @ correction(np.arange(N), q[:, None, :])[:, 0]
                w = self._fill_zoom(meshes, correction, X, virtual, q, w, rep.upper, zoom_system)
            zooms = [float(z) for z in np.clip(1.0 / np.maximum(w, 1e-9), 1.0, p.budget.max_zoom)]
            rep.worst_margin_px = rep.margin_px(1.0 / np.asarray(zooms[:R]), p.budget.margin_px)  # as released
        # The EP problem (docs/method.md (4)-(6)) with the smoothed path's own velocities as
        # targets and its keyframe pose as end-constraint: its solution is that path.
        Q = g.exp(q[:R])
        targets = g.log(np.linalg.inv(np.concatenate([np.eye(4)[None], Q[:-1]])) @ Q)
        sol = solve_segment(g, np.eye(4)[None].repeat(R, 0), None, Q[-1], p.path, zbar=targets)
        path = base[None] @ (sol.corrections[1:] if sol.converged else Q)
        corrections = self._capped(np.linalg.inv(X[:R]) @ path)
        ms = (time.perf_counter() - t0) * 1e3
        pl.account(SegmentInfo(seg, win.start, win.seqs[R - 1], closed_by, sol.converged,
                                       sol.iterations, sol.residual, sol.cost, ms, sol.reason, rep.constrained,
                                       rep.worst_margin_px, rep.rounds, rep.converged, rep.gap))
        if zooms[0] is not None:
            self._zooms = (self._zooms + zooms[:R])[-3:]
        out = [Correction(s, corrections[i], seg, i == R - 1, reason=pl.notes.pop(s, ""), zoom=zooms[i],
                          camera=X[i], chain=pl.chain, motion=win.kinds[i])
               for i, s in enumerate(win.seqs[:R])]
        pl.held = corrections[R - 1]
        self._committed = (self._committed + list(path))[-3:]
        keep = int(3 * p.velocity_sigma) + 2
        self._real, self._real_c = (self._real + list(X[:R]))[-keep:], (self._real_c + list(trust[:R]))[-keep:]
        win.keep_from(R)
        return out

    def _capped(self, corrections: np.ndarray) -> np.ndarray:
        """``corrections`` (..., 4, 4) with the tilt cap (docs/method.md (19)) when one is set."""
        p = self.params
        if p.max_tilt_deg <= 0:
            return corrections
        return limit_tilt(corrections, np.radians(p.max_tilt_deg), np.radians(min(p.tilt_knee_deg, p.max_tilt_deg)))

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

    def _velocity_targets(self, win: OpenSegment, base: np.ndarray) -> np.ndarray:
        """Low-passed velocity of the real path, in the window's chart, for the steps into its frames; each
        step weighted by the trust in the less certain of its two frames (docs/method.md (8a))."""
        p, g = self.params, self.group
        k = len(win.path) + int(3 * p.velocity_sigma) + 1
        hist, hist_c = (self._real[-k:], self._real_c[-k:]) if self._real else (win.path[:1], win.closeness[:1])
        xs = chart_path(g, base, np.asarray(hist + win.path))
        vel = np.diff(xs, axis=0)
        c = np.asarray(hist_c + win.closeness)
        trust = np.minimum(c[:-1], c[1:])  # a step is as certain as the less certain of its two frames
        n = len(win.path)
        idx = np.arange(len(vel))
        out = np.empty((n, vel.shape[1]))
        for i, t in enumerate(range(len(vel) - n, len(vel))):
            w = np.exp(-0.5 * ((idx - t) / p.velocity_sigma) ** 2) * trust
            out[i] = w @ vel / w.sum()
        return out

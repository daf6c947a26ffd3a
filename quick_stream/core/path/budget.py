"""Crop budget: every frame of the path stays border-free at a zoom <= Z (docs/method.md (10)-(11)).

The renderer warps a frame with a mesh fitted to where the stabilized camera sees the
frame's 3D points, and the output pixels with a source are exactly the polygon of the
mesh's outer vertices (docs/method.md (12)). So whether a correction leaves a border at
zoom Z is decided by the mesh, and the planner can decide it before any image exists
(:mod:`.frame_model`: the frame's 3D points, the same mesh fitted to them, and per outer mesh edge
how far a centred crop rectangle stays inside it).

:func:`constrain` then plans the path and its zoom track together (:class:`BudgetProblem`: the
smoother's problem, :mod:`.smoother`, plus the price of the crop, with those margins as inequality
constraints, split into the smooth pieces of :func:`edge_pieces`), by sequential quadratic
programming with a line search (:func:`_sqp`), each QP solved in its dual (:mod:`.qp`); its report says how many rounds it took, whether it met its stopping rule
and what the last QP still promised. A path that already keeps every frame border-free at Z comes
back unchanged, with only its zoom track planned.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..lie import LieGroup
from ..render.framing import ZOOM_LIMIT
from .frame_model import FrameModel, SegmentMeshes
from .qp import dual_qp, working_set_qp
from .smoother import SegmentSystem


Correct = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (window frames (F,), chart points (F, B, n)) -> (F, B, 4, 4)


@dataclass
class BudgetParams:
    """Crop budget of the smoothed path (each parameter documented where it acts)."""

    max_zoom: float = 1.25  # every frame border-free at this zoom (0: no budget, the path is unconstrained;
    # docs/method.md 4.3, "The zoom limit under fast motion")
    margin_px: float = 1.0  # kept between the crop rectangle and the border, in pixels (model error)
    model_points: int = 128  # 3D points per frame model (a regular subset of the flow's)
    near_px: float = 16.0  # frames whose crop comes this close (px) to the border get constraints
    max_rounds: int = 12  # SQP rounds at most: linearise the margins at the path, solve the QP, line search
    stop_gain: float = 1e-3  # the SQP stops once the QP at its path promises less than this share of its cost
    crop_weight: float = 1.0  # price of one pixel of crop (per frame, squared) against one pixel of path
    # deviation in the smoother's cost: docs/method.md (11)
    fill: float = 0.4  # share of half the short side the mesh may leave uncovered inside the crop: the
    # renderer fills it from neighbouring frames (docs/method.md 5.4); 0 when the renderer does not fill
    fill_reach: int = 30  # frames on each side the renderer's fill reads (the zoom track plans with them)

    @property
    def enabled(self) -> bool:
        return self.max_zoom > 0

    def validate(self) -> None:
        if not (np.isfinite(self.max_zoom) and (self.max_zoom == 0 or 1.0 <= self.max_zoom <= ZOOM_LIMIT)):
            raise ValueError(f"max zoom must be 0 (no budget) or in [1, {ZOOM_LIMIT:g}], got {self.max_zoom}")
        if not (self.margin_px >= 0 and self.near_px > self.margin_px and self.model_points >= 8
                and self.max_rounds >= 1 and self.stop_gain > 0 and self.crop_weight >= 0 and 0 <= self.fill < 0.5
                and self.fill_reach >= 0):
            raise ValueError("budget needs margin_px >= 0, near_px > margin_px, model_points >= 8, max_rounds >= 1, "
                             "stop_gain > 0, crop_weight >= 0, 0 <= fill < 0.5, fill_reach >= 0")


def rotation_directions(group: LieGroup) -> np.ndarray:
    """(n, 3) twist coordinates of the three rotation generators [[hat(e_i), 0], [0, 0]] (every group here
    contains the rotations): the directions in which the crop budget may bend a path."""
    E = np.zeros((3, 4, 4))
    for i, (a, b) in enumerate(((2, 1), (0, 2), (1, 0))):
        E[i, a, b], E[i, b, a] = 1.0, -1.0
    return group.vee(E).T


def rotation_scales(model: FrameModel, h: float = 1e-4) -> np.ndarray:
    """Pixels moved per radian of rotation about each camera axis (RMS over the model's points):
    the budget QP's metric, so its objective is image motion."""
    from ..lie import get_group
    so = get_group("se3")
    E = so.exp(h * np.hstack([np.zeros((3, 3)), np.eye(3)]))
    x = model.points
    y = np.einsum("bij,mj->bmi", E[:, :3, :3], x)
    K2 = model.K[:2, :2]
    uv = np.einsum("ij,bmj->bmi", K2, y[..., :2] / y[..., 2:])
    uv0 = (x[:, :2] / x[:, 2:]) @ K2.T
    return np.sqrt(np.mean(np.sum((uv - uv0[None]) ** 2, axis=-1), axis=-1)) / h


@dataclass
class BudgetReport:
    """What :func:`constrain` did to one window."""

    constrained: int = 0  # frames that got constraints
    worst_margin_px: float = float("inf")  # smallest margin to the border at the planned zoom (px; < 0: over budget)
    upper: np.ndarray | None = None  # (N,) largest w = 1/zoom each frame's own mesh allows (fill band included)
    half: np.ndarray | None = None  # (N,) half the short side of each frame with a model (px; nan without one)
    rounds: int = 0  # QPs the SQP solved (0: the path kept every frame inside the budget and was kept)
    converged: bool = True  # the SQP met its stopping rule (False: it stopped at max_rounds, or stalled)
    gap: float = 0.0  # share of its cost the last QP still promised to save (<= stop_gain when converged)
    cost: float = 0.0  # docs/method.md (11) at the answer, less its unconstrained minimum (px^2)

    def margin_px(self, w: np.ndarray, margin_px: float) -> float:
        """Smallest margin (px) between the crop at scales ``w`` of the first len(w) frames and the border the
        budget allows (docs/method.md (10), (10a)): < 0 where a frame is over budget; inf without frame models."""
        if self.upper is None:
            return float("inf")
        m = (self.upper[:len(w)] - np.asarray(w, dtype=np.float64)) * self.half[:len(w)]
        m = m[np.isfinite(m)]
        return float(m.min()) + margin_px if m.size else float("inf")


class BudgetProblem:
    """docs/method.md (11) on one window, in the variables the budget bends (docs/method.md 4.3).

    The path is p = p0 + r R^T (R = :func:`rotation_directions`, r (N, 3) radians: the orientation
    only), the crop scales w = 1/zoom (N,). Cost: f(r, w) = 1/2 [sum_k s_k^2 r_k^T A r_k +
    c h^2 (w - w0)^T A_w (w - w0)], half of (11) less its unconstrained minimum: A the smoother's
    matrix (J_s(p0 + d) = J_s(p0) + d^T A d per component, docs/method.md (8)), s_k the pixels a
    radian about axis k moves (:func:`rotation_scales`, of the window's last frame model), A_w the
    zoom form continuing the committed scales and w0 its minimiser. Constraints (10): for every frame
    t with a model, g_t(r_t) >= w_t and w_t >= 1/Z, where g_t = t_e - delta/h (+ the fill band, (10a))
    per outer mesh edge e (:meth:`edges`) or, the same set, per piece of :func:`edge_pieces`
    (:meth:`margins`, what the SQP linearises). ``correction(frames, P)`` maps chart coordinates
    P (F, B, n) to corrections (F, B, 4, 4).
    """

    def __init__(self, group: LieGroup, system: SegmentSystem, p0: np.ndarray, correction: Correct,
                 meshes: SegmentMeshes, params: BudgetParams, zoom_system: SegmentSystem, committed_w: np.ndarray,
                 h: float = 1e-6) -> None:
        self.N = len(p0)
        self.system, self.p0, self.correction, self.meshes = system, p0, correction, meshes
        self.params, self.zoom_system, self.h = params, zoom_system, h
        self.w0 = zoom_system.unconstrained(np.ones((self.N, 1)),
                                            np.asarray(committed_w, dtype=np.float64).reshape(-1, 1))[:, 0]
        self.has = np.flatnonzero(meshes.frames >= 0)  # window frames with a model
        self.idx = meshes.frames[self.has]
        self.half = np.array([meshes.half(f) for f in self.idx])
        self.Rd = rotation_directions(group)  # (n, 3)
        self.m = self.Rd.shape[1]
        self.cw = params.crop_weight * float(np.mean(self.half)) ** 2 if self.has.size else 0.0
        self.slack = params.margin_px / self.half - params.fill  # the margin, less the band fill covers (t units)
        self.n_edges = 2 * (meshes.shape[0] + meshes.shape[1] - 2)
        self.v0 = np.concatenate([np.zeros(self.N * self.m), self.w0])

    @property
    def scale2(self) -> np.ndarray:
        """s_k^2 (3,): the metric on r, (pixels per radian)^2; cached."""
        s = self.__dict__.get("_scale2")
        if s is None:
            s = self.__dict__["_scale2"] = rotation_scales(self.meshes.models[self.idx[-1]]) ** 2
        return s

    def edges(self, sel: np.ndarray, P: np.ndarray) -> np.ndarray:
        """g per outer edge, t_e - delta/h (+ the fill band), of frames ``has[sel]`` at chart points P (F, B, n):
        (F, B, E)."""
        return self.meshes.margins(self.idx[sel], self.correction(self.has[sel], P), 1.0, 0.0) + 1.0 \
            - self.slack[sel][:, None, None]

    def _pieces(self, sel: np.ndarray, P: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """g per piece of :func:`edge_pieces` (less delta/h, plus the fill band) of frames ``has[sel]`` at chart
        points P (F, B, n): (F, B, 3 E) twice, counting the crossings on their edges, then those within ``reach``
        edge lengths of them; inf for the others."""
        t, lam = self.meshes.pieces(self.idx[sel], self.correction(self.has[sel], P))
        g = t - self.slack[sel][:, None, None]
        E = self.n_edges
        out = []
        for lo, hi in ((0.0, 1.0), (-reach, 1.0 + reach)):
            gi = g.copy()
            gi[..., E:] = np.where((lam > lo) & (lam < hi), g[..., E:], np.inf)
            out.append(gi)
        return out[0], out[1]

    def margins(self, r: np.ndarray, reach: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """g (F, 3 E) per piece of every frame with a model at the path bent by r (N, 3), docs/method.md (10):
        exactly, and with the crossings within ``reach`` of their edges (:meth:`_pieces`)."""
        return tuple(x[:, 0] for x in self._pieces(np.arange(self.has.size),
                                                   (self.p0 + r @ self.Rd.T)[self.has][:, None, :], reach))

    def jacobian(self, r: np.ndarray, g: np.ndarray, sel: np.ndarray, reach: float = 0.0) -> np.ndarray:
        """d g / d r_t (R, 3 E, 3) of frames ``has[sel]`` at r, forward differences from their :meth:`margins`
        ``g`` of the same ``reach`` (0 for a piece the step makes or unmakes)."""
        P = (self.p0 + r @ self.Rd.T)[self.has[sel]][:, None, :] + self.h * self.Rd.T[None]
        with np.errstate(invalid="ignore"):
            J = (self._pieces(sel, P, reach)[1] - g[sel][:, None, :]).transpose(0, 2, 1) / self.h
        return np.where(np.isfinite(J), J, 0.0)

    def cost(self, r: np.ndarray, w: np.ndarray) -> float:
        """f(r, w) (class docstring)."""
        dw = w - self.w0
        path = float(np.sum((self.system.A @ r) * r * self.scale2)) if np.any(r) else 0.0
        return 0.5 * (path + self.cw * float(dw @ (self.zoom_system.A @ dw)))

    def gradient(self, r: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(df/dr (N, 3), df/dw (N,))."""
        return (self.system.A @ r) * self.scale2, self.cw * (self.zoom_system.A @ (w - self.w0))

    def violation(self, g: np.ndarray, w: np.ndarray) -> float:
        """sum of how far (t units) the margins ``g`` (F, K) and w >= 1/Z are broken at scales ``w``."""
        return float(np.sum(np.maximum(w[self.has, None] - g, 0.0))
                     + np.sum(np.maximum(1.0 / self.params.max_zoom - w, 0.0)))

    def hinv_ct(self, C: np.ndarray, Minv: np.ndarray) -> np.ndarray:
        """H^-1 C^T for rows C over [r (N m), w (N)]: H = A (x) metric for r (Minv its inverse), c h^2 A_w for w."""
        N, m = self.N, self.m
        Cr, Cw = C[:, :N * m], C[:, N * m:]
        Hr = np.einsum("tkc,kj->tjc", self.system.solve(Cr.T.reshape(N, -1)).reshape(N, m, -1), Minv)
        return np.vstack([Hr.reshape(N * m, -1), self.zoom_system.solve(Cw.T) / self.cw])

    def rows(self, r: np.ndarray, g: np.ndarray, near: np.ndarray, J: np.ndarray | None,
             sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(C, d): J (r' - r) + g - w' >= 0 for the ``near`` (F, K) edges or pieces of frames ``has[sel]``, as
        C v' >= d (J (R, K, 3) their Jacobian; None: the path is fixed, w' <= g exactly)."""
        N, m = self.N, self.m
        fr, ed = np.nonzero(near[sel])
        t_of = self.has[sel][fr]
        C = np.zeros((fr.size, N * m + N))
        Jr = np.zeros((fr.size, m)) if J is None else J[fr, ed]
        for k in range(m):
            C[np.arange(fr.size), t_of * m + k] = Jr[:, k]
        C[np.arange(fr.size), N * m + t_of] = -1.0
        return C, np.einsum("ck,ck->c", Jr, r[t_of]) - g[sel][fr, ed]


def constrain(group: LieGroup, system: SegmentSystem, p0: np.ndarray, correction: Correct, meshes: SegmentMeshes,
              params: BudgetParams, zoom_system: SegmentSystem, committed_w: np.ndarray,
              h: float = 1e-6) -> tuple[np.ndarray, np.ndarray, BudgetReport]:
    """The smoothed path (N, n) and its crop scales w = 1/zoom (N,), planned together (docs/method.md (10)-(11)):
    :class:`BudgetProblem`'s minimum (``system``: the smoother's problem, whose unconstrained minimiser is
    ``p0``; ``zoom_system``: the zoom form continuing the ``committed_w`` of the frames released before).

    When ``p0`` keeps every frame border-free at Z it is returned unchanged and only the zoom track is
    planned, under w_t <= min_e g_te exactly (a budget far away reproduces the unconstrained path).
    Otherwise sequential quadratic programming (:func:`_sqp`). The report holds the margins, the rounds, the
    stopping rule's verdict and the share of the cost the last QP still promised to save.
    """
    pb = BudgetProblem(group, system, p0, correction, meshes, params, zoom_system, committed_w, h)
    N, m, has, Z = pb.N, pb.m, pb.has, params.max_zoom
    rep = BudgetReport()
    if has.size == 0:
        return p0, np.maximum(pb.w0, 1.0 / Z), rep
    rep.half = np.full(N, np.nan)
    rep.half[has] = pb.half
    g0 = pb.edges(np.arange(has.size), p0[has][:, None, :])[:, 0]
    if np.all(g0 >= 1.0 / Z):
        r, g = np.zeros((N, m)), g0
        w, near = _zoom_track(pb, g0)
    else:
        r, w, g, near = _sqp(pb, rep)
    rep.constrained = int(np.count_nonzero(near.any(axis=1)))
    rep.upper = np.full(N, np.inf)
    rep.upper[has] = g.min(axis=1)
    rep.worst_margin_px = rep.margin_px(np.clip(w, 1.0 / Z, 1.0), params.margin_px)  # at the zoom as clipped
    rep.cost = 2.0 * pb.cost(r, w)
    return p0 + r @ pb.Rd.T, w, rep


def _zoom_track(pb: BudgetProblem, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fixed path's zoom track: (11) in w alone, w_t <= min_e g_te (``g`` (F, E)) and w_t >= 1/Z, rows for the
    frames within ``near_px`` of their crop (more if the answer comes closer). Returns (w, the near edges)."""
    p, N, m, has = pb.params, pb.N, pb.m, pb.has
    near = np.zeros((has.size, pb.n_edges), bool)
    rows_c = [np.hstack([np.zeros((N, N * m)), np.eye(N)])]
    rows_d = [np.full(N, 1.0 / p.max_zoom)]
    w = pb.w0.copy()
    for rnd in range(p.max_rounds + 1):
        cur = (g - w[has, None]) * pb.half[:, None]  # px between the crop at zoom 1/w and the border
        if (rnd > 0 and cur.min() >= -1e-3) or rnd == p.max_rounds:
            break
        near |= cur < p.near_px
        sel = np.flatnonzero(near.any(axis=1))
        C, d = pb.rows(np.zeros((N, m)), g, near, None, sel)
        rows_c.append(C)
        rows_d.append(d)
        Cc = np.concatenate(rows_c)
        w = dual_qp(Cc, np.concatenate(rows_d), pb.hinv_ct(Cc, np.eye(m)), pb.v0)[0][N * m:]
    return w, near


def _sqp(pb: BudgetProblem, rep: BudgetReport, reach: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                          np.ndarray]:
    """docs/method.md (11) by sequential quadratic programming from the unconstrained path (r = 0, w = w0).

    Each round linearises, at the current path, the pieces (:func:`edge_pieces`; the diagonal crossings
    within ``reach`` edge lengths of their edge too) within ``near_px`` of the crop, by forward
    differences; solves that QP (:func:`dual_qp`; the margin rows soft, w >= 1/Z exact) and steps
    towards its answer, halving the step until the L1 merit f + rho * violation (the exact margins)
    falls (Armijo; rho twice the largest multiplier so far). Only the current linearisation is kept:
    no round is bound by a stale one. Stops when the frames are inside the budget (their violations
    summing to at most 0.01 px) and the QP at the path promises less than ``stop_gain`` of the cost,
    after ``max_rounds`` QPs, or when no step lowers the merit; a frame then left over its margin gets
    the zoom it needs, up to Z. Fills the report's rounds, converged and gap. Returns (r, w, the exact
    margins g, the pieces that got rows)."""
    p, N, m, has = pb.params, pb.N, pb.m, pb.has
    Minv = np.diag(1.0 / pb.scale2)
    C0, d0 = np.hstack([np.zeros((N, N * m)), np.eye(N)]), np.full(N, 1.0 / p.max_zoom)
    r, w = np.zeros((N, m)), pb.w0.copy()
    g, gx = pb.margins(r, reach)
    near = np.zeros(g.shape, bool)
    f, viol, rho = pb.cost(r, w), pb.violation(g, w), 0.0
    rep.converged = False
    for rnd in range(p.max_rounds):
        near |= (gx - w[has, None]) * pb.half[:, None] < p.near_px
        now = near & np.isfinite(gx)  # a crossing that left its edge's reach is a vertex's piece now
        sel = np.flatnonzero(now.any(axis=1))
        C, d = pb.rows(r, gx, now, pb.jacobian(r, gx, sel, reach), sel)
        Cc, dd = np.concatenate([C0, C]), np.concatenate([d0, d])
        soft = np.concatenate([np.zeros(N), np.ones(len(C))])
        # rows within 1 px of holding at the current path (and w >= 1/Z) first: the rest rarely bind
        start = np.concatenate([np.ones(N, bool), (C @ np.concatenate([r.ravel(), w]) - d) * pb.half.max() < 1.0])
        v, y = working_set_qp(Cc, dd, lambda rows: pb.hinv_ct(rows, Minv), pb.v0, soft, start)
        rep.rounds = rnd + 1
        r_qp, w_qp = v[:N * m].reshape(N, m), v[N * m:]
        rep.gap = (f - pb.cost(r_qp, w_qp)) / max(f, 1e-12)
        if rep.gap <= p.stop_gain and viol * float(pb.half.max()) <= 1e-2:
            rep.converged = True
            break
        rho = max(rho, 2.0 * float(y.max(initial=0.0)))
        gr, gw = pb.gradient(r, w)
        dr, dw = r_qp - r, w_qp - w
        slope = float(np.sum(gr * dr) + gw @ dw) - rho * viol  # the merit's directional derivative, at most
        merit, a = f + rho * viol, 1.0
        for _ in range(12):
            rt, wt = r + a * dr, w + a * dw
            gt, gxt = pb.margins(rt, reach)
            ft, vt = pb.cost(rt, wt), pb.violation(gt, wt)
            if ft + rho * vt <= merit + 1e-4 * a * min(slope, 0.0):
                break
            a *= 0.5
        else:
            break  # no step lowers the merit: the last accepted path stays
        r, w, g, gx, f, viol = rt, wt, gt, gxt, ft, vt
    short = np.flatnonzero(w[has] > g.min(axis=1))  # left (slightly) over its margin: the zoom it needs, up to Z
    w = w.copy()
    w[has[short]] = np.maximum(g[short].min(axis=1), 1.0 / p.max_zoom)
    return r, w, g, near

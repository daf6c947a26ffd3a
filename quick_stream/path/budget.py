"""Crop budget: every frame of the path stays border-free at a zoom <= Z (docs/method.md (10)-(11)).

The renderer warps a frame with a mesh fitted to where the stabilized camera sees the
frame's 3D points, and the output pixels with a source are exactly the polygon of the
mesh's outer vertices (docs/method.md (12)). So whether a correction leaves a border at
zoom Z is decided by the mesh, and the planner can decide it before any image exists:
a :class:`FrameModel` holds a few hundred of the frame's 3D points (from the scene flow
that reached the frame), :func:`edge_margins` fits the same mesh to them and returns, per
outer mesh edge, how far the zoom-Z crop rectangle stays inside it.

:func:`constrain` then solves the smoother's problem (:mod:`.smoother`) with those
margins as inequality constraints, by sequential quadratic programming: margins
linearised by finite differences at the current path, the quadratic program solved in
its dual (non-negative least squares over the constraints that can become active), the
margins re-evaluated on the new path, up to ``max_rounds`` times. A path far from the
budget has no constraint near activity and comes back unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy.optimize import nnls

from ..frame import Intrinsics
from ..lie import LieGroup
from ..render.framing import edge_extents
from ..render.warp import WarpParams, bilinear_weights, grid_geometry, rotation_references, similarity_normal
from .smoother import SegmentSystem


@dataclass
class BudgetParams:
    """Crop budget of the smoothed path (each parameter documented where it acts)."""

    max_zoom: float = 1.12  # every frame border-free at this zoom (0: no budget, the path is unconstrained)
    margin_px: float = 1.0  # kept between the crop rectangle and the border, in pixels (model error)
    model_points: int = 128  # 3D points per frame model (a regular subset of the flow's)
    near_px: float = 16.0  # frames whose crop comes this close (px) to the border get constraints
    max_rounds: int = 4  # SQP rounds: re-linearise the margins at the new path
    zoom_rise: float = 0.01  # a window's frames may need at most this much more zoom per frame than the last
    # committed zoom (docs/method.md (10)): the zoom track never has to jump at a window's start

    @classmethod
    def describe(cls) -> dict[str, str]:
        return {f.name: repr(f.default) for f in fields(cls)}

    @property
    def enabled(self) -> bool:
        return self.max_zoom > 0

    def validate(self) -> None:
        if not (np.isfinite(self.max_zoom) and (self.max_zoom == 0 or self.max_zoom >= 1.0)):
            raise ValueError(f"max zoom must be 0 (no budget) or >= 1, got {self.max_zoom}")
        if not (self.margin_px >= 0 and self.near_px > self.margin_px and self.model_points >= 8
                and self.max_rounds >= 1 and self.zoom_rise > 0):
            raise ValueError("budget needs margin_px >= 0, near_px > margin_px, model_points >= 8, max_rounds >= 1, "
                             "zoom_rise > 0")

    def frame_limits(self, n: int, last_zoom: float, planned: list[float] | None = None) -> np.ndarray:
        """Largest zoom each of a window's ``n`` frames may need (docs/method.md (10)): Z, or less near the
        window's start when the last committed zoom is lower (it may rise by ``zoom_rise`` per frame),
        unless the previous window's zoom track (``planned``, for the frames it did not release) already
        rose further for them."""
        lim = max(last_zoom, 1.0) + self.zoom_rise * np.arange(1, n + 1)
        if planned:
            k = min(len(planned), n)
            lim[:k] = np.maximum(lim[:k], np.asarray(planned[:k]) + self.zoom_rise)
        return np.minimum(self.max_zoom, lim)


@dataclass
class FrameModel:
    """What the planner knows of a frame's geometry: size, intrinsics and some 3D points with their pixels."""

    width: int
    height: int
    K: np.ndarray  # (3, 3)
    pixels: np.ndarray  # (M, 2)
    points: np.ndarray  # (M, 3), camera coordinates

    @classmethod
    def from_points(cls, width: int, height: int, intrinsics: Intrinsics, pixels: np.ndarray,
                    points: np.ndarray, max_points: int) -> "FrameModel | None":
        """A model from a regular subset of at most ``max_points`` pixel/point pairs (None if too few)."""
        n = len(points)
        if n < 8:
            return None
        keep = np.linspace(0, n - 1, min(n, max_points)).round().astype(np.intp) if n > max_points else slice(None)
        return cls(int(width), int(height), intrinsics.K, np.asarray(pixels, np.float64)[keep],
                   np.asarray(points, np.float64)[keep])

    def design(self, warp: WarpParams) -> tuple[np.ndarray, np.ndarray]:
        """(B^T / M (n, M), the data term's block of the normal matrix (2n, 2n), plus alpha S for the
        input-grid reference) of the renderer's fit on this model (docs/method.md (13)); cached, since a
        frame serves every window that plans it."""
        key = (tuple(int(g) for g in warp.grid), warp.alpha, warp.shape_reference)
        cache = self.__dict__.setdefault("_design", {})
        if key not in cache:
            gx, gy = key[0]
            geo = grid_geometry(self.width, self.height, gx, gy)
            n = (gx + 1) * (gy + 1)
            ks, ws = bilinear_weights(self.pixels, geo)
            B = np.zeros((len(self.pixels), n))
            np.put_along_axis(B, ks, ws, axis=1)
            G = np.zeros((2 * n, 2 * n))
            G[:n, :n] = G[n:, n:] = B.T @ B / len(B)
            if warp.shape_reference == "input":
                G += warp.alpha * geo.sim_normal
            cache[key] = (B.T / len(B), G)
        return cache[key]


class SegmentMeshes:
    """The renderer's mesh fit (docs/method.md (13)) on the frame models of one segment, batched.

    Frame f's model gives the data term's design B_f (its points' bilinear weights) and the
    normal matrix G_f = blockdiag(B_f^T B_f, B_f^T B_f) / M_f + alpha S of render/warp.py, so
    the output vertices for any corrections are one linear solve away. Frames are padded to
    the same number of points with zero rows (no weight). ``frames`` maps each segment frame
    to its model's index (-1: no model, no constraint).
    """

    def __init__(self, models: list[FrameModel | None], warp: WarpParams) -> None:
        uniq: list[FrameModel] = []
        index: dict[int, int] = {}
        self.frames = np.full(len(models), -1, dtype=np.intp)
        for t, m in enumerate(models):
            if m is None:
                continue
            if id(m) not in index:
                index[id(m)] = len(uniq)
                uniq.append(m)
            self.frames[t] = index[id(m)]
        gx, gy = (int(g) for g in warp.grid)
        self.shape = (gy + 1, gx + 1)
        self.n = n = (gx + 1) * (gy + 1)
        self.warp = warp
        F = len(uniq)
        M = max((len(m.points) for m in uniq), default=0)
        self.points = np.zeros((F, 3, M))  # component-major: each coordinate contiguous over the points
        self.points[:, 2] = 1.0
        self.BtN = np.zeros((F, n, M))
        self.G0 = np.zeros((F, 2 * n, 2 * n))  # the data term's block of G (and G itself for the input reference)
        self.src = np.zeros((F, gy + 1, gx + 1, 2))
        self.K = np.zeros((F, 3, 3))
        self.size = np.zeros((F, 2))
        for f, m in enumerate(uniq):
            BtN, self.G0[f] = m.design(warp)
            self.points[f, :, :len(m.points)] = m.points.T
            self.BtN[f, :, :len(m.points)] = BtN
            self.src[f] = grid_geometry(m.width, m.height, gx, gy).src
            self.K[f] = m.K
            self.size[f] = (m.width, m.height)
        self.models = uniq

    def vertices(self, idx: np.ndarray, point_transforms: np.ndarray) -> np.ndarray:
        """Output vertices (F, P, gy+1, gx+1, 2) of models ``idx`` (F,) under point transforms (F, P, 4, 4).

        The same normal equations as render/warp.py's solve (docs/method.md (13)): data term
        on the model's points, similarity term against the input grid or, by default, the
        grid moved by each correction's rotation."""
        T = np.asarray(point_transforms, dtype=np.float64)
        y = np.einsum("fpij,fjm->fpim", T[..., :3, :3], self.points[idx], optimize=True)  # (F, P, 3, M)
        y += T[..., :3, 3, None]
        iz = 1.0 / np.maximum(y[:, :, 2], 1e-6)
        K = self.K[idx][:, None]
        u = (K[..., 0, 0, None] * iz) * y[:, :, 0] + K[..., 0, 2, None]
        v = (K[..., 1, 1, None] * iz) * y[:, :, 1] + K[..., 1, 2, None]
        BtN = np.swapaxes(self.BtN[idx], -1, -2)  # (F, M, n)
        rhs = np.concatenate((u @ BtN, v @ BtN), axis=-1)  # (F, P, 2n)
        G = np.broadcast_to(self.G0[idx][:, None], T.shape[:2] + self.G0.shape[1:])
        if self.warp.shape_reference == "rotation":
            ref, _ = rotation_references(self.K[idx][:, None], T, self.src[idx][0])
            G = G + self.warp.alpha * similarity_normal(ref)
        X = np.linalg.solve(G, rhs[..., None])[..., 0]
        return np.stack((X[..., :self.n], X[..., self.n:]), axis=-1).reshape(*T.shape[:2], *self.shape, 2)

    def margins(self, idx: np.ndarray, corrections: np.ndarray, max_zoom: float | np.ndarray,
                margin_px: float) -> np.ndarray:
        """Per model in ``idx`` (F,), correction (F, P, 4, 4) and outer mesh edge: t_e - t_Z (F, P, E).

        >= 0 where the budget holds (docs/method.md (10)); t_e from
        :func:`~quick_stream.render.framing.edge_extents`, t_Z = 1/Z plus the margin in the
        same normalised units, Z a number or one per model (F,). Multiply by :meth:`half` to read pixels.
        """
        zmax = np.broadcast_to(np.asarray(max_zoom, dtype=np.float64), (len(idx),))
        V = self.vertices(idx, np.linalg.inv(corrections))
        out = np.empty(V.shape[:2] + (2 * (self.shape[0] + self.shape[1] - 2),))
        sizes = self.size[idx]
        for w, h in np.unique(sizes, axis=0):  # frames of one size share edge_extents' normalisation
            sel = np.flatnonzero(np.all(sizes == (w, h), axis=1))
            out[sel] = edge_extents(V[sel], int(w), int(h)) - (1.0 / zmax[sel, None, None]
                                                               + margin_px / (0.5 * (min(w, h) - 1)))
        return out

    def half(self, f: int) -> float:
        """Half the short side of model f's frame (px): margins times this are pixels."""
        return 0.5 * (float(self.size[f].min()) - 1.0)


def component_scales(group: LieGroup, model: FrameModel, h: float = 1e-4) -> np.ndarray:
    """Pixels moved per unit of each twist component (RMS over the model's points): the QP's metric."""
    E = group.exp(h * np.eye(group.dim))
    x = model.points
    y = np.einsum("bij,mj->bmi", E[:, :3, :3], x) + E[:, None, :3, 3]
    K2 = model.K[:2, :2]
    uv = np.einsum("ij,bmj->bmi", K2, y[..., :2] / y[..., 2:])
    uv0 = (x[:, :2] / x[:, 2:]) @ K2.T
    d = np.sqrt(np.mean(np.sum((uv - uv0[None]) ** 2, axis=-1), axis=-1)) / h
    return np.maximum(d, 1e-6 * max(float(d.max()), 1.0))


@dataclass
class BudgetReport:
    """What :func:`constrain` did to one segment."""

    constrained: int = 0  # frames that got constraints
    rounds: int = 0
    worst_margin_px: float = float("inf")  # smallest margin left after the last round (px; < 0: over budget)


def constrain(group: LieGroup, system: SegmentSystem, p0: np.ndarray, correction, meshes: SegmentMeshes,
              params: BudgetParams, limits: np.ndarray, h: float = 1e-6) -> tuple[np.ndarray, BudgetReport]:
    """The smoothed path (N, n) minimising J_s with every frame's margins >= 0 (docs/method.md (11)).

    ``p0`` is the unconstrained minimiser of J_s (:mod:`.smoother`); ``correction(frames, P)``
    maps chart coordinates P (F, B, n) of those frames to corrections (F, B, 4, 4);
    ``meshes`` holds the frames' mesh models; ``limits`` (N,) the zoom each frame may need
    (:meth:`BudgetParams.frame_limits`). J_s is measured in
    the metric of :func:`component_scales` (pixels), the margins linearised by finite
    differences at the current path, the quadratic program solved in its dual (non-negative
    least squares over the constraints that can become active).
    """
    N, n = p0.shape
    rep = BudgetReport()
    has = np.flatnonzero(meshes.frames >= 0)
    if has.size == 0:
        return p0, rep
    idx = meshes.frames[has]
    half = np.array([meshes.half(f) for f in idx])
    s2 = component_scales(group, meshes.models[idx[-1]]) ** 2
    probes = np.vstack([np.zeros(n), h * np.eye(n)])
    lim = np.asarray(limits, dtype=np.float64)[has]
    near = np.zeros((has.size, 2 * (meshes.shape[0] + meshes.shape[1] - 2)), bool)

    p = p0
    for rnd in range(params.max_rounds):
        P = p[has][:, None, :]
        cur = meshes.margins(idx, correction(has, P), lim, params.margin_px)[:, 0] * half[:, None]
        rep.worst_margin_px = float(cur.min()) + params.margin_px
        if rnd > 0 and cur.min() >= -1e-3:
            break
        near |= cur < params.near_px
        rows = np.flatnonzero(near.any(axis=1))
        if rows.size == 0:
            break
        mk = meshes.margins(idx[rows], correction(has[rows], p[has[rows]][:, None, :] + probes[None]),
                            lim[rows], params.margin_px)  # (R, n+1, E)
        J = (mk[:, 1:] - mk[:, :1]).transpose(0, 2, 1) / h  # (R, E, n)
        fr, ed = np.nonzero(near[rows])
        C = np.zeros((fr.size, N, n))
        C[np.arange(fr.size), has[rows][fr]] = J[fr, ed]
        C = C.reshape(fr.size, N * n)
        d = np.einsum("ck,ck->c", J[fr, ed], p[has[rows][fr]]) - mk[fr, 0, ed]  # J (p_t - p_bar) + m >= 0
        HinvCt = (system.solve(C.T.reshape(N, -1)).reshape(N, n, -1) / s2[None, :, None]).reshape(N * n, -1)
        M = C @ HinvCt
        q = d - C @ p0.ravel()
        M[np.diag_indices_from(M)] += 1e-10 * max(float(np.trace(M)) / len(M), 1e-30)
        L = np.linalg.cholesky(M)
        y, _ = nnls(L.T, np.linalg.solve(L, q), maxiter=50 * len(q))
        p = (p0.ravel() + HinvCt @ y).reshape(N, n)
        rep.rounds = rnd + 1
    rep.constrained = int(np.count_nonzero(near.any(axis=1)))
    return p, rep

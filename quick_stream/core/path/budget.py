"""Crop budget: every frame of the path stays border-free at a zoom <= Z (docs/method.md (10)-(11)).

The renderer warps a frame with a mesh fitted to where the stabilized camera sees the
frame's 3D points, and the output pixels with a source are exactly the polygon of the
mesh's outer vertices (docs/method.md (12)). So whether a correction leaves a border at
zoom Z is decided by the mesh, and the planner can decide it before any image exists:
a :class:`FrameModel` holds up to ``model_points`` of the frame's 3D points (from the scene
flow that reached the frame), :class:`SegmentMeshes` fits the same mesh to them and returns,
per outer mesh edge, how far a centred crop rectangle stays inside it.

:func:`constrain` then plans the path and its zoom track together (the smoother's problem,
:mod:`.smoother`, plus the price of the crop, with those margins as inequality constraints),
by sequential quadratic programming. A path that already keeps every frame border-free at
Z comes back unchanged, with only its zoom track planned.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..frame import Intrinsics
from ..lie import LieGroup
from ..render.framing import edge_extents
from ..render.shape_term import rotation_references, similarity_normal
from ..render.warp import WarpParams, bilinear_weights, grid_geometry
from .smoother import SegmentSystem


@dataclass
class BudgetParams:
    """Crop budget of the smoothed path (each parameter documented where it acts)."""

    max_zoom: float = 1.15  # every frame border-free at this zoom (0: no budget, the path is unconstrained)
    margin_px: float = 1.0  # kept between the crop rectangle and the border, in pixels (model error)
    model_points: int = 128  # 3D points per frame model (a regular subset of the flow's)
    near_px: float = 16.0  # frames whose crop comes this close (px) to the border get constraints
    max_rounds: int = 4  # SQP rounds: re-linearise the margins at the new path
    crop_weight: float = 1.0  # price of one pixel of crop (per frame, squared) against one pixel of path
    # deviation in the smoother's cost: docs/method.md (11)
    fill: float = 0.08  # share of half the short side the mesh may leave uncovered inside the crop: the
    # renderer fills it from neighbouring frames (docs/method.md 5.4); 0 when the renderer does not fill
    fill_reach: int = 8  # frames on each side the renderer's fill reads (the zoom track plans with them)

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
                and self.max_rounds >= 1 and self.crop_weight >= 0 and 0 <= self.fill < 0.5
                and self.fill_reach >= 0):
            raise ValueError("budget needs margin_px >= 0, near_px > margin_px, model_points >= 8, max_rounds >= 1, "
                             "crop_weight >= 0, 0 <= fill < 0.5, fill_reach >= 0")


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

    @property
    def median_depth(self) -> float:
        """Median depth of the model's points (m): the border fill's plane (docs/method.md (10b)); cached."""
        d = self.__dict__.get("_median_depth")
        if d is None:
            d = self.__dict__["_median_depth"] = float(np.median(self.points[:, 2]))
        return d

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
        self._seen: dict[tuple[int, bytes], np.ndarray] = {}  # single-transform vertices by (model, transform)

    def vertices(self, idx: np.ndarray, point_transforms: np.ndarray) -> np.ndarray:
        """Output vertices (F, P, gy+1, gx+1, 2) of models ``idx`` (F,) under point transforms (F, P, 4, 4).

        The same normal equations as render/warp.py's solve (docs/method.md (13)): data term
        on the model's points, similarity term against the input grid or, by default, the
        grid moved by each correction's rotation."""
        T = np.asarray(point_transforms, dtype=np.float64)
        keys = [(int(f), t.tobytes()) for f, t in zip(idx, T)] if T.shape[1] == 1 else None
        if keys is not None and all(k in self._seen for k in keys):  # the budget's final check, asked again
            return np.stack([self._seen[k] for k in keys])
        V = self._vertices(idx, T)
        if keys is not None:
            self._seen.update(zip(keys, V))
        return V

    def _vertices(self, idx: np.ndarray, T: np.ndarray) -> np.ndarray:
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
        :func:`~quick_stream.core.render.framing.edge_extents` (the border-free zoom is 1 / min t_e),
        t_Z = 1/Z plus the margin in the same normalised units, Z a number or one per model (F,).
        Times :meth:`half`: pixels.
        """
        zmax = np.broadcast_to(np.asarray(max_zoom, dtype=np.float64), (len(idx),))
        V = self.vertices(idx, np.linalg.inv(corrections))
        t = np.empty(V.shape[:2] + (2 * (self.shape[0] + self.shape[1] - 2),))
        sizes = self.size[idx]
        if np.all(sizes == sizes[0]):  # the usual case: one frame size
            t[:] = edge_extents(V, int(sizes[0, 0]), int(sizes[0, 1]))
        else:
            for w, h in np.unique(sizes, axis=0):  # frames of one size share the normalisation
                sel = np.flatnonzero(np.all(sizes == (w, h), axis=1))
                t[sel] = edge_extents(V[sel], int(w), int(h))
        half = 0.5 * (sizes.min(axis=1) - 1.0)
        return t - (1.0 / zmax + margin_px / half)[:, None, None]

    def half(self, f: int) -> float:
        """Half the short side of model f's frame (px): margins times this are pixels."""
        return 0.5 * (float(self.size[f].min()) - 1.0)


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
    """What :func:`constrain` did to one segment."""

    constrained: int = 0  # frames that got constraints
    worst_margin_px: float = float("inf")  # smallest margin to the border at the planned zoom (px; < 0: border)
    upper: np.ndarray | None = None  # (N,) largest w = 1/zoom each frame's own mesh allows (fill band included)


def constrain(group: LieGroup, system: SegmentSystem, p0: np.ndarray, correction, meshes: SegmentMeshes,
              params: BudgetParams, zoom_system: SegmentSystem, committed_w: np.ndarray,
              h: float = 1e-6) -> tuple[np.ndarray, np.ndarray, BudgetReport]:
    """The smoothed path (N, n) and its crop scales w = 1/zoom (N,), planned together (docs/method.md (10)-(11)).

    When the unconstrained path ``p0`` keeps every frame border-free at Z it is returned unchanged
    and only the zoom track is planned (a budget far away reproduces the unconstrained path).
    Otherwise:

    Minimises J_s (:mod:`.smoother`, whose unconstrained minimiser is ``p0``) plus the crop cost
    c h^2 [sum_t z_w,t (1 - w_t)^2 + mu sum_t (w_{t+1} - 2 w_t + w_{t-1})^2] (``zoom_system``: that
    quadratic form, continuing the ``committed_w`` of the frames released before; h = half the
    short side, so both costs are in pixels^2) subject to, for every frame with a model and every
    outer mesh edge, t_e(g_s(t)) - delta / h >= w_t (border-free at zoom 1/w_t, delta the margin),
    and w_t >= 1/Z. ``correction(frames, P)`` maps chart coordinates P (F, B, n) to corrections
    (F, B, 4, 4). With a border fill (``params.fill`` > 0) the margin allows the band the renderer
    fills from neighbouring frames (docs/method.md 5.4). The budget bends the path's orientation only (p = p0 + R r, R =
    :func:`rotation_directions`): moving the virtual camera would buy border-free frames with
    parallax, or with a magnified view. Sequential quadratic programming: margins linearised by
    finite differences at the current path (the linearisations of earlier rounds are kept, which
    stops the rounds cycling between them), each QP solved in its dual by non-negative least squares.
    """
    from scipy.optimize import nnls  # not at module level: only the motion stage needs it (PathPlanner loads it)

    N, n = p0.shape
    rep = BudgetReport()
    w0 = zoom_system.unconstrained(np.ones((N, 1)), np.asarray(committed_w, dtype=np.float64).reshape(-1, 1))[:, 0]
    has = np.flatnonzero(meshes.frames >= 0)
    if has.size == 0:
        return p0, np.maximum(w0, 1.0 / params.max_zoom), rep
    idx = meshes.frames[has]
    half = np.array([meshes.half(f) for f in idx])
    Rd = rotation_directions(group)  # (n, 3)
    m = Rd.shape[1]
    cw = params.crop_weight * float(np.mean(half)) ** 2
    probes = np.vstack([np.zeros(n), h * Rd.T])  # (m+1, n)
    n_edges = 2 * (meshes.shape[0] + meshes.shape[1] - 2)
    near = np.zeros((has.size, n_edges), bool)
    slack = params.margin_px / half - params.fill  # (F,) the margin, less the band fill covers, in t units

    def edges(sel: np.ndarray, P: np.ndarray) -> np.ndarray:
        """t_e - delta/h (+ the fill band) of frames ``has[sel]`` at chart points P (F, B, n): (F, B, E)."""
        return meshes.margins(idx[sel], correction(has[sel], P), 1.0, 0.0) + 1.0 - slack[sel][:, None, None]

    def solve_h(C: np.ndarray) -> np.ndarray:
        """H^-1 C^T for rows C over [r (N m), w (N)]: A (x) metric for r, cw * zoom form for w."""
        Cr, Cw = C[:, :N * m], C[:, N * m:]
        Hr = np.einsum("tkc,kj->tjc", system.solve(Cr.T.reshape(N, -1)).reshape(N, m, -1), Minv).reshape(N * m, -1)
        return np.vstack([Hr, zoom_system.solve(Cw.T) / cw])

    # A path that keeps every frame border-free at Z is kept as it is (a budget far away reproduces the
    # unconstrained path exactly) and only its zoom track is planned: r stays 0, no Jacobians needed.
    every = np.arange(has.size)
    g0 = edges(every, p0[has][:, None, :])[:, 0]
    free = bool(np.all(g0 >= 1.0 / params.max_zoom))
    # the metric on r, per frame (a free path's constraints never involve r: any metric gives r = 0)
    Minv = np.eye(m) if free else np.linalg.inv(np.diag(rotation_scales(meshes.models[idx[-1]]) ** 2))
    # w_t >= 1/Z on every frame: the zoom limit
    C0 = np.hstack([np.zeros((N, N * m)), np.eye(N)])
    rows_c, rows_d = [C0], [np.full(N, 1.0 / params.max_zoom)]
    r = np.zeros((N, m))
    w = w0.copy()
    for rnd in range(params.max_rounds + 1):
        # t_e - delta/h at the current path (a free path is never bent: its margins stay g0)
        g = g0 if free else edges(every, (p0 + r @ Rd.T)[has][:, None, :])[:, 0]
        cur = (g - w[has, None]) * half[:, None]  # px between the crop at zoom 1/w and the border
        rep.worst_margin_px = float(cur.min()) + params.margin_px
        if (rnd > 0 and cur.min() >= -1e-3) or rnd == params.max_rounds:
            break
        near |= cur < params.near_px
        rows = np.flatnonzero(near.any(axis=1))
        if free:  # the path is fixed: w_t <= t_e exactly, no linearisation
            J = np.zeros((rows.size, n_edges, m))
        else:
            Pn = (p0 + r @ Rd.T)[has[rows]][:, None, :] + probes[None]
            mk = edges(rows, Pn)  # (R, m+1, E)
            J = (mk[:, 1:] - mk[:, :1]).transpose(0, 2, 1) / h  # (R, E, m): d t_e / d r
        fr, ed = np.nonzero(near[rows])
        t_of = has[rows][fr]
        C = np.zeros((fr.size, N * m + N))
        for k in range(m):
            C[np.arange(fr.size), t_of * m + k] = J[fr, ed, k]
        C[np.arange(fr.size), N * m + t_of] = -1.0
        rows_c.append(C)  # J (r - r_bar) + g(r_bar) - w >= 0
        rows_d.append(np.einsum("ck,ck->c", J[fr, ed], r[t_of]) - g[rows][fr, ed])
        Cc, d = np.concatenate(rows_c), np.concatenate(rows_d)
        HinvCt = solve_h(Cc)
        Mm = Cc @ HinvCt
        Mm[np.diag_indices_from(Mm)] += 1e-10 * max(float(np.trace(Mm)) / len(Mm), 1e-30)
        L = np.linalg.cholesky(Mm)
        v0 = np.concatenate([np.zeros(N * m), w0])
        y, _ = nnls(L.T, np.linalg.solve(L, d - Cc @ v0), maxiter=50 * len(d))
        v = v0 + HinvCt @ y
        r, w = v[:N * m].reshape(N, m), v[N * m:]
    rep.constrained = int(np.count_nonzero(near.any(axis=1)))
    rep.upper = np.full(N, np.inf)
    rep.upper[has] = g.min(axis=1)
    return p0 + r @ Rd.T, w, rep

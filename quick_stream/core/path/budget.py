"""Crop budget: every frame of the path stays border-free at a zoom <= Z (docs/method.md (10)-(11)).

The renderer warps a frame with a mesh fitted to where the stabilized camera sees the
frame's 3D points, and the output pixels with a source are exactly the polygon of the
mesh's outer vertices (docs/method.md (12)). So whether a correction leaves a border at
zoom Z is decided by the mesh, and the planner can decide it before any image exists:
a :class:`FrameModel` holds up to ``model_points`` of the frame's 3D points (from the scene
flow that reached the frame), :class:`SegmentMeshes` fits the same mesh to them and returns,
per outer mesh edge, how far a centred crop rectangle stays inside it.

:func:`constrain` then plans the path and its zoom track together (:class:`BudgetProblem`: the
smoother's problem, :mod:`.smoother`, plus the price of the crop, with those margins as inequality
constraints, split into the smooth pieces of :func:`edge_pieces`), by sequential quadratic
programming with a line search (:func:`_sqp`), each QP solved in its dual (:func:`dual_qp`,
:func:`working_set_qp`); its report says how many rounds it took, whether it met its stopping rule
and what the last QP still promised. A path that already keeps every frame border-free at Z comes
back unchanged, with only its zoom track planned.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Callable

import numpy as np

from ..frame import Intrinsics
from ..lie import LieGroup
from ..render.framing import edge_extents, outline
from ..render.shape_term import rotation_references, similarity_normal
from ..render.warp import WarpParams, bilinear_weights, grid_geometry
from .smoother import SegmentSystem


Correct = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (window frames (F,), chart points (F, B, n)) -> (F, B, 4, 4)


@dataclass
class BudgetParams:
    """Crop budget of the smoothed path (each parameter documented where it acts)."""

    max_zoom: float = 1.15  # every frame border-free at this zoom (0: no budget, the path is unconstrained)
    margin_px: float = 1.0  # kept between the crop rectangle and the border, in pixels (model error)
    model_points: int = 128  # 3D points per frame model (a regular subset of the flow's)
    near_px: float = 16.0  # frames whose crop comes this close (px) to the border get constraints
    max_rounds: int = 12  # SQP rounds at most: linearise the margins at the path, solve the QP, line search
    stop_gain: float = 1e-3  # the SQP stops once the QP at its path promises less than this share of its cost
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
                and self.max_rounds >= 1 and self.stop_gain > 0 and self.crop_weight >= 0 and 0 <= self.fill < 0.5
                and self.fill_reach >= 0):
            raise ValueError("budget needs margin_px >= 0, near_px > margin_px, model_points >= 8, max_rounds >= 1, "
                             "stop_gain > 0, crop_weight >= 0, 0 <= fill < 0.5, fill_reach >= 0")


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
        t = self._per_size(idx, self.vertices(idx, np.linalg.inv(corrections)), edge_extents, 1)
        half = 0.5 * (self.size[idx].min(axis=1) - 1.0)
        return t - (1.0 / zmax + margin_px / half)[:, None, None]

    def pieces(self, idx: np.ndarray, corrections: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`edge_pieces` of models ``idx`` (F,) under corrections (F, P, 4, 4): the values (F, P, 3 E) and
        the crossings' edge parameters (F, P, 2 E); the least value on its edge is :meth:`margins`' min t_e."""
        out = self._per_size(idx, self.vertices(idx, np.linalg.inv(corrections)), edge_pieces, 5)
        E = out.shape[-1] // 5
        return out[..., :3 * E], out[..., 3 * E:]

    def _per_size(self, idx: np.ndarray, V: np.ndarray, fn, k: int) -> np.ndarray:
        """fn(vertices, width, height) -> (..., k E) over vertices V (F, P, gy+1, gx+1, 2) of models ``idx``."""
        out = np.empty(V.shape[:2] + (k * 2 * (self.shape[0] + self.shape[1] - 2),))
        sizes = self.size[idx]
        if np.all(sizes == sizes[0]):  # the usual case: one frame size
            out[:] = fn(V, int(sizes[0, 0]), int(sizes[0, 1]))
        else:
            for w, h in np.unique(sizes, axis=0):  # frames of one size share the normalisation
                sel = np.flatnonzero(np.all(sizes == (w, h), axis=1))
                out[sel] = fn(V[sel], int(w), int(h))
        return out

    def half(self, f: int) -> float:
        """Half the short side of model f's frame (px): margins times this are pixels."""
        return 0.5 * (float(self.size[f].min()) - 1.0)


def edge_pieces(dst: np.ndarray, width: int, height: int) -> np.ndarray:
    """The values whose minimum is min_e t_e of :func:`~quick_stream.core.render.framing.edge_extents`
    (docs/method.md (12)), kept apart, for mesh vertices ``dst`` (..., gy+1, gx+1, 2) with M outer edges:
    (..., 5 M) = each outer vertex's max(|x|, |y|) (centred, normalised; M), then per edge |x| where its
    line crosses the diagonals x = y and x = -y (2 M), then the edge parameter of those crossings (2 M;
    in (0, 1): on the edge; nan: parallel); all values 0 for a polygon that does not contain the centre.
    min_e t_e is the minimum over the vertices and the crossings on their edges. Each value is smooth
    in the vertices, and the minimum switches between them (a crop corner on an edge, a vertex on a
    crop side), so the budget's SQP linearises them one by one: one linearisation of the minimum holds
    on one side of a switch only. A crossing just past its edge's end is a half-plane a crop corner
    must also keep to where the polygon is convex there: the SQP linearises those too, before they come
    onto the edge."""
    a, b = (width - 1) / 2.0, (height - 1) / 2.0
    p = (outline(np.asarray(dst, dtype=np.float64)) - (a, b)) / (a, b)
    d = np.roll(p, -1, axis=-2) - p
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.stack([(p[..., 1] - p[..., 0]) / (d[..., 0] - d[..., 1]),  # x = y
                        -(p[..., 0] + p[..., 1]) / (d[..., 0] + d[..., 1])], axis=-1)  # x = -y
        cross = np.abs(p[..., None, 0] + lam * d[..., None, 0])
    t = np.concatenate([np.abs(p).max(axis=-1), cross.reshape(*cross.shape[:-2], -1)], axis=-1)
    inside = np.any(edge_extents(dst, width, height) > 0, axis=-1)
    return np.concatenate([np.where(inside[..., None], t, 0.0), lam.reshape(*lam.shape[:-2], -1)], axis=-1)


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


def dual_qp(C: np.ndarray, d: np.ndarray, HinvCt: np.ndarray, v0: np.ndarray,
            soft: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """min 1/2 (v - v0)^T H (v - v0) s.t. C v >= d, solved in its dual: y >= 0 minimising
    1/2 y^T C H^-1 C^T y - y^T (d - C v0) by non-negative least squares on the Cholesky factor,
    v = v0 + H^-1 C^T y (docs/method.md (11)). ``HinvCt``: H^-1 C^T. Returns (v, y).

    The dual's matrix gets 1e-10 of its mean diagonal on the rows ``soft`` (bool, default all):
    a quadratic penalty that keeps an infeasible set of those rows solvable, met as closely as it
    can be; the other rows hold exactly."""
    from scipy.optimize import nnls  # not at module level: only the motion stage needs it (PathPlanner loads it)

    M = C @ HinvCt
    eps = 1e-10 * max(float(np.trace(M)) / len(M), 1e-30)
    M[np.diag_indices_from(M)] += eps if soft is None else eps * soft
    L = np.linalg.cholesky(M)
    y, _ = nnls(L.T, np.linalg.solve(L, d - C @ v0), maxiter=50 * len(d))
    return v0 + HinvCt @ y, y


def working_set_qp(C: np.ndarray, d: np.ndarray, hinv_ct: Callable[[np.ndarray], np.ndarray], v0: np.ndarray,
                   soft: np.ndarray, start: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """:func:`dual_qp` (docs/method.md (11)) on a working set of the rows: first ``start`` (bool per row),
    then, while its answer breaks other rows by more than ``tol``, those too. A convex QP's answer under
    some of its constraints that meets the others is its answer under all, so this is :func:`dual_qp`'s
    answer (y 0 off the set), at the cost of the rows that matter. ``hinv_ct(rows)``: H^-1 rows^T.
    Returns (v, y)."""
    work = start.copy()
    while True:
        idx = np.flatnonzero(work)
        v, y_work = dual_qp(C[idx], d[idx], hinv_ct(C[idx]), v0, soft[idx])
        broken = ~work & (C @ v < d - tol)
        if not broken.any():
            y = np.zeros(len(d))
            y[idx] = y_work
            return v, y
        work |= broken


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

"""The renderer's mesh fitted to each frame's 3D points, before any image exists (docs/method.md (10), (12)).

A :class:`FrameModel` holds up to ``model_points`` of a frame's 3D points (from the scene flow that
reached the frame); :class:`SegmentMeshes` fits the renderer's own mesh (docs/method.md (13)) to them,
batched over a window's corrections, and returns per outer mesh edge how far a centred crop rectangle
stays inside it; :func:`edge_pieces` splits that margin into the smooth pieces whose minimum it is. The
crop budget (:mod:`.budget`) and the border fill's zoom plan (:mod:`.coverage`) read them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..frame import Intrinsics
from ..render.framing import edge_extents, outline
from ..render.shape_term import rotation_references, similarity_normal
from ..render.warp import WarpParams, bilinear_weights, grid_geometry


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

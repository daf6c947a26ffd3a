"""The zoom the border fill cannot make unnecessary, planned with the path (docs/method.md (10b)).

The crop budget (:mod:`.budget`) lets each frame's own mesh leave a band of the crop uncovered
for the renderer to fill from neighbouring frames (:mod:`quick_stream.render.fill`). Whether a
neighbour saw a missing pixel is geometry only: the pixel's ray from the virtual camera, at the
frame's depth, projected into the neighbour's real camera (docs/method.md (14)). So the planner,
which holds the window's real and virtual camera poses, can tell per frame the smallest zoom at
which the frame's own mesh plus its neighbours cover the crop, and plan the zoom track with it,
look-ahead frames included, instead of leaving the renderer to raise a zoom the track did not
see coming. :func:`fill_need` estimates that zoom from the crop rectangle's boundary (the
uncovered region touches the frame's border); :func:`bounded_zoom_track` re-plans the zoom
track under the resulting upper bounds on w = 1 / zoom.
"""
from __future__ import annotations

import numpy as np

from ..render.framing import outline
from .budget import SegmentMeshes
from .smoother import SegmentSystem


def inside(poly: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points ``pts`` (F, P, 2) inside the closed polygons ``poly`` (F, M, 2) (even-odd rule): (F, P) bool."""
    a = poly[:, :, None, :]
    b = np.roll(poly, -1, axis=1)[:, :, None, :]
    y = pts[:, None, :, 1]
    cross = (a[..., 1] > y) != (b[..., 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = a[..., 0] + (y - a[..., 1]) * (b[..., 0] - a[..., 0]) / (b[..., 1] - a[..., 1])
    return (np.count_nonzero(cross & (pts[:, None, :, 0] < xi), axis=1) % 2) == 1


def rim(per_edge: int = 16) -> np.ndarray:
    """Points on the boundary of the square max(|x|, |y|) = 1, corners included: (4 n, 2)."""
    t = np.linspace(-1.0, 1.0, per_edge, endpoint=False)
    one = np.ones_like(t)
    return np.concatenate([np.column_stack([t, -one]), np.column_stack([one, t]),
                           np.column_stack([-t, one]), np.column_stack([-one, -t])])


def fill_need(meshes: SegmentMeshes, frames: np.ndarray, corrections: np.ndarray, cameras: np.ndarray,
              virtual: np.ndarray, zoom_lo: np.ndarray, zoom_hi: float, reach: int, steps: int = 7) -> np.ndarray:
    """Per frame in ``frames`` (F,) (window indices with a model), the smallest zoom in
    [``zoom_lo``, ``zoom_hi``] at which the crop is covered by the frame's own mesh under its
    correction (F, 4, 4) or seen by a frame within ``reach``: (F,), ``zoom_hi`` when none is.

    ``cameras`` (S, 4, 4) real camera poses of the window's frames preceded by committed past
    ones, ``virtual`` (S, 4, 4) the virtual camera's at the same indices (only the window's are
    used), window frame j at index ``S - N + j``. Depth of a missing pixel: the median of the
    frame model's points (a plane). The crop's boundary is tested (the uncovered region touches
    the frame's border), bisecting the zoom ``steps`` times.
    """
    idx = meshes.frames[frames]
    F, S, N = len(frames), len(cameras), len(meshes.frames)
    lo = np.asarray(zoom_lo, dtype=np.float64).copy()
    if F == 0:
        return lo
    poly = outline(meshes.vertices(idx, np.linalg.inv(corrections)[:, None])[:, 0])  # (F, M, 2)
    half = (meshes.size[idx] - 1.0) / 2.0  # (F, 2): centre and half-size
    K = meshes.K[idx]
    depth = np.array([m.median_depth for m in meshes.models])[idx]
    k = S - N + np.asarray(frames)
    offs = np.concatenate([np.arange(-reach, 0), np.arange(1, reach + 1)])
    src = k[:, None] + offs[None]  # (F, R) neighbour indices
    ok_src = (src >= 0) & (src < S)
    src = np.clip(src, 0, S - 1)
    T = np.linalg.solve(cameras[src], virtual[k][:, None])  # (F, R, 4, 4): virtual t -> real camera s
    Kinv = np.linalg.inv(K)
    square = rim()

    def covered(z: np.ndarray) -> np.ndarray:
        pts = half[:, None, :] * (1.0 + square[None] / z[:, None, None])  # (F, P, 2) crop boundary
        own = inside(poly, pts)
        rays = (Kinv @ np.concatenate([pts, np.ones(pts.shape[:2] + (1,))], axis=2).transpose(0, 2, 1)) \
            * depth[:, None, None]  # (F, 3, P)
        X = T[..., :3, :3] @ rays[:, None] + T[..., :3, 3:4]  # (F, R, 3, P)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[:, None, 0, 0, None] * X[:, :, 0] / X[:, :, 2] + K[:, None, 0, 2, None]
            v = K[:, None, 1, 1, None] * X[:, :, 1] / X[:, :, 2] + K[:, None, 1, 2, None]
        w, h = 2.0 * half[:, None, None, 0], 2.0 * half[:, None, None, 1]
        seen = (X[:, :, 2] > 0) & (u >= 0) & (u <= w) & (v >= 0) & (v <= h) & ok_src[..., None]
        return np.all(own | seen.any(axis=1), axis=1)

    done = covered(lo)
    hi = np.full(F, max(float(zoom_hi), float(lo.max())))
    todo = ~done
    if todo.any():
        a, b = lo.copy(), hi.copy()
        for _ in range(steps):
            mid = 0.5 * (a + b)
            c = covered(mid)
            b = np.where(todo & c, mid, b)
            a = np.where(todo & ~c, mid, a)
        lo = np.where(todo, b, lo)
    return lo


def bounded_zoom_track(zoom_system: SegmentSystem, committed_w: np.ndarray, upper: np.ndarray,
                       lower: float) -> np.ndarray:
    """The zoom track w (N,) of docs/method.md (11) (``zoom_system`` continuing ``committed_w``) with
    ``lower`` <= w_t <= ``upper``_t (an upper bound below ``lower`` gives way to it), solved in its
    dual by non-negative least squares like :func:`.budget.constrain`."""
    from scipy.optimize import nnls  # imported when first needed (service start time)

    N = len(upper)
    w0 = zoom_system.unconstrained(np.ones((N, 1)), np.asarray(committed_w, dtype=np.float64).reshape(-1, 1))[:, 0]
    u = np.maximum(np.asarray(upper, dtype=np.float64), lower)
    bounded = np.flatnonzero(np.isfinite(u))
    C = np.vstack([-np.eye(N)[bounded], np.eye(N)])  # C w >= d: -w >= -u (where bounded), w >= lower
    d = np.concatenate([-u[bounded], np.full(N, lower)])
    if np.all(C @ w0 >= d - 1e-12):
        return w0
    HinvCt = zoom_system.solve(C.T)
    M = C @ HinvCt
    M[np.diag_indices_from(M)] += 1e-10 * max(float(np.trace(M)) / len(M), 1e-30)
    L = np.linalg.cholesky(M)
    y, _ = nnls(L.T, np.linalg.solve(L, d - C @ w0), maxiter=50 * len(d))
    return w0 + HinvCt @ y

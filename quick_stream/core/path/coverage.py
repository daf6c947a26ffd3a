"""The zoom the border fill cannot make unnecessary, planned with the path (docs/method.md (10b)).

The crop budget (:mod:`.budget`) lets each frame's own mesh leave a band of the crop uncovered
for the renderer to fill from neighbouring frames (:mod:`quick_stream.core.render.fill`). Whether a
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
from .frame_model import SegmentMeshes
from .qp import dual_qp
from .smoother import SegmentSystem


def rim(per_edge: int = 16) -> np.ndarray:
    """Points on the boundary of the square max(|x|, |y|) = 1, corners included: (4 n, 2)."""
    t = np.linspace(-1.0, 1.0, per_edge, endpoint=False)
    one = np.ones_like(t)
    return np.concatenate([np.column_stack([t, -one]), np.column_stack([one, t]),
                           np.column_stack([-t, one]), np.column_stack([-one, -t])])


def exit_distance(poly: np.ndarray, centre: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """How far along each ray from ``centre`` (..., 2) in direction ``rays`` (..., P, 2) the polygons
    ``poly`` (..., M, 2) reach before their first edge, in units of the ray vector: (..., P);
    0 for a polygon that does not contain the centre (conservative: it is not counted)."""
    a = poly[..., None, :, :] - centre[..., None, None, :]  # (..., 1, M, 2) edge starts, centred
    e = np.roll(poly, -1, axis=-2)[..., None, :, :] - poly[..., None, :, :]
    v = rays[..., :, None, :]  # (..., P, 1, 2)
    det = v[..., 1] * e[..., 0] - v[..., 0] * e[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (a[..., 1] * e[..., 0] - a[..., 0] * e[..., 1]) / det
        mu = (v[..., 0] * a[..., 1] - v[..., 1] * a[..., 0]) / det
    hit = (np.abs(det) > 1e-12) & (mu >= 0) & (mu <= 1) & (lam > 0)
    out = np.min(np.where(hit, lam, np.inf), axis=-1)
    # the centre is inside a polygon an odd number of edges crosses in one direction
    crossings = np.count_nonzero(hit, axis=-1)
    return np.where((crossings % 2 == 1) & np.isfinite(out), out, 0.0)


def convex_exit_distance(poly: np.ndarray, centre: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """:func:`exit_distance` for convex polygons ``poly`` (..., M, 2) of either orientation: each
    edge is a half-plane n . x <= b, the ray leaves through the nearest one it heads out of; 0 where
    the centre is outside. A fraction of the general function's cost (no edge-crossing tests)."""
    a = poly - centre[..., None, :]  # (..., M, 2) centred
    e = np.roll(a, -1, axis=-2) - a
    area = np.sum(a[..., 0] * np.roll(a[..., 1], -1, axis=-1) - np.roll(a[..., 0], -1, axis=-1) * a[..., 1], axis=-1)
    sgn = np.where(area >= 0, 1.0, -1.0)[..., None]  # counter-clockwise: the inside is left of each edge
    n = np.stack([e[..., 1], -e[..., 0]], axis=-1) * sgn[..., None]  # outward normals (..., M, 2)
    b = np.sum(n * a, axis=-1)  # n . x <= b inside; b >= 0 for every edge iff the centre is inside
    inside = np.all(b >= 0, axis=-1) & (area != 0)
    out = np.full(np.broadcast_shapes(n.shape[:-2], rays.shape[:-2]) + rays.shape[-2:-1], np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for m in range(n.shape[-2]):  # edge by edge: a reduction over a short last axis is slow
            nv = n[..., m, None, 0] * rays[..., 0] + n[..., m, None, 1] * rays[..., 1]  # (..., P)
            np.minimum(out, np.where(nv > 1e-12, b[..., m, None] / nv, np.inf), out=out)
    return np.where(inside[..., None] & np.isfinite(out), out, 0.0)


def fill_need(meshes: SegmentMeshes, frames: np.ndarray, corrections: np.ndarray, cameras: np.ndarray,
              virtual: np.ndarray, zoom_lo: np.ndarray, zoom_hi: float, reach: int) -> np.ndarray:
    """Per frame in ``frames`` (F,) (window indices with a model), the smallest zoom in
    [``zoom_lo``, ``zoom_hi``] at which the crop is covered by the frame's own mesh under its
    correction (F, 4, 4) or seen by a frame within ``reach``: (F,), ``zoom_hi`` when none is.

    ``cameras`` (S, 4, 4) real camera poses of the window's frames preceded by committed past
    ones, ``virtual`` (S, 4, 4) the virtual camera's at the same indices (only the window's are
    used), window frame j at index ``S - N + j``. Each neighbour sees, at the median depth d of
    the frame model's points (a plane), the quadrilateral its image rectangle maps to under
    H = K (d R + t e_3^T) K^-1 inverted ((R, t) the virtual camera in the neighbour's); along
    each ray from the centre through the crop's boundary the frame is covered as far as the
    farthest of those regions, or its own mesh, reaches, counting only regions that contain the
    centre. The crop's boundary at zoom z lies at 1/z of the way to the frame's border.
    """
    idx = meshes.frames[frames]
    F, S, N = len(frames), len(cameras), len(meshes.frames)
    lo = np.asarray(zoom_lo, dtype=np.float64).copy()
    if F == 0:
        return lo
    poly = outline(meshes.vertices(idx, np.linalg.inv(corrections)[:, None])[:, 0])  # (F, M, 2)
    half = (meshes.size[idx] - 1.0) / 2.0  # (F, 2): the centre, and the half-size
    K = meshes.K[idx]
    depth = np.array([m.median_depth for m in meshes.models])[idx]
    k = S - N + np.asarray(frames)
    offs = np.concatenate([np.arange(-reach, 0), np.arange(1, reach + 1)])
    src = k[:, None] + offs[None]  # (F, R) neighbour indices
    ok_src = (src >= 0) & (src < S)
    T = np.linalg.solve(cameras[np.clip(src, 0, S - 1)], virtual[k][:, None])  # (F, R, 4, 4): virtual -> neighbour
    A = depth[:, None, None, None] * T[..., :3, :3]
    A[..., :, 2] += T[..., :3, 3]  # d R + t e_3^T
    H = K[:, None] @ A @ np.linalg.inv(K)[:, None]  # virtual pixel -> neighbour pixel
    w, h = 2.0 * half[:, 0], 2.0 * half[:, 1]
    corners = np.stack([np.stack([np.zeros(F), np.zeros(F)], -1), np.stack([w, np.zeros(F)], -1),
                        np.stack([w, h], -1), np.stack([np.zeros(F), h], -1)], axis=1)  # (F, 4, 2)
    back = np.linalg.inv(H) @ np.concatenate([corners, np.ones((F, 4, 1))], axis=-1).transpose(0, 2, 1)[:, None]
    front = np.all(back[..., 2, :] > 0, axis=-1) & ok_src  # (F, R): the whole rectangle in front
    quads = (back[..., :2, :] / np.where(back[..., 2:, :] > 0, back[..., 2:, :], 1.0)).transpose(0, 1, 3, 2)
    rays = rim(8)[None] * half[:, None, :]  # (F, P, 2): centre -> crop boundary at zoom 1
    reach_own = exit_distance(poly, half, rays)  # (F, P)
    reach_src = convex_exit_distance(quads, np.broadcast_to(half[:, None], quads.shape[:2] + (2,)),
                                     rays[:, None])  # a rectangle's image, wholly in front: convex
    reach_src = np.where(front[..., None], reach_src, 0.0)
    far = np.maximum(reach_own, reach_src.max(axis=1))  # (F, P) covered out to this share of the way
    need = 1.0 / np.maximum(far.min(axis=1), 1e-9)
    return np.clip(np.maximum(lo, need), None, max(float(zoom_hi), float(lo.max())))


def bounded_zoom_track(zoom_system: SegmentSystem, committed_w: np.ndarray, upper: np.ndarray,
                       lower: float) -> np.ndarray:
    """The zoom track w (N,) of docs/method.md (11) (``zoom_system`` continuing ``committed_w``) with
    ``lower`` <= w_t <= ``upper``_t (an upper bound below ``lower`` gives way to it), solved in its
    dual by non-negative least squares (:func:`.budget.dual_qp`)."""
    N = len(upper)
    w0 = zoom_system.unconstrained(np.ones((N, 1)), np.asarray(committed_w, dtype=np.float64).reshape(-1, 1))[:, 0]
    u = np.maximum(np.asarray(upper, dtype=np.float64), lower)
    bounded = np.flatnonzero(np.isfinite(u))
    C = np.vstack([-np.eye(N)[bounded], np.eye(N)])  # C w >= d: -w >= -u (where bounded), w >= lower
    d = np.concatenate([-u[bounded], np.full(N, lower)])
    if np.all(C @ w0 >= d - 1e-12):
        return w0
    return dual_qp(C, d, zoom_system.solve(C.T), w0)[0]

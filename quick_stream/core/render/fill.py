"""Border fill: output pixels a frame's own mesh leaves uncovered, taken from its neighbours (docs/method.md 5.4).

A stabilised frame shows the virtual camera's view, and where the virtual camera looks past
the real frame's edge (a shake peak) the mesh leaves a band uncovered. Cropping that band
away costs every frame around the peak its zoom; the neighbouring frames, shaken the other
way, saw what is missing. With the camera poses the motion stage integrated (the correction's
``camera``, g_c) and depth, each missing pixel is a 3D point whose image in a neighbour is
known exactly:

    X_v = d(q) K^-1 Z^-1 q,      X_s = g_c(s)^-1 g_c(t) g_s(t) X_v,      q_s = pi(K_s X_s)     (14)

with q the zoomed output pixel, Z the zoom about the centre (:func:`.mapping.zoom_matrix`),
d(q) the depth of the frame's own nearest covered output pixel, looked up on every 4th pixel
(the surface continued past the edge) and g_s(t) the correction (virtual camera relative to
the real one). Neighbours are tried nearest first (the smallest camera motion, so the least parallax error from d), past
and future alike, and only within one pose chain (a path restart breaks the chain). What no
neighbour saw stays uncovered; the caller then zooms in (:func:`raise_for`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import cv2
import numpy as np

from .framing import scale_from_mask
from .mapping import map_points, sample_map, zoom_matrix


@dataclass
class FillSource:
    """A frame the border fill can read: its input colour, intrinsics and camera pose in ``chain``."""

    seq: int
    chain: int
    camera: np.ndarray  # g_c (4, 4)
    image: np.ndarray  # BGR input frame
    K: np.ndarray  # (3, 3)


def nearest_depth(depth: np.ndarray) -> np.ndarray | None:
    """``depth`` with every pixel that has none (<= 0) given its nearest known pixel's; None when no
    pixel has depth."""
    known = depth > 0
    if not known.any():
        return None
    # distance to the nearest zero of src: zeros are the known pixels; each gets its own label
    _, labels = cv2.distanceTransformWithLabels((~known).astype(np.uint8), cv2.DIST_L2, 3,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    value = np.zeros(int(labels.max()) + 1, np.float64)
    value[labels[known]] = depth[known]
    return value[labels]


def ordered_sources(seq: int, chain: int, sources: Iterable[FillSource], reach: int) -> list[FillSource]:
    """The sources of ``chain`` within ``reach`` frames of ``seq`` (itself excluded), nearest first,
    the earlier of two equally near first, each frame once."""
    near = {s.seq: s for s in sources if s.chain == chain and s.seq != seq and abs(s.seq - seq) <= reach}
    return sorted(near.values(), key=lambda s: (abs(s.seq - seq), s.seq))


def project(src: FillSource, virtual: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, inside) in ``src`` of virtual-camera points (3, n), (14): pixel coordinates and
    whether each lands in front of the source camera and inside its image."""
    T = np.linalg.solve(src.camera, virtual)
    P = T[:3, :3] @ points + T[:3, 3:4]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = src.K[0, 0] * P[0] / P[2] + src.K[0, 2]
        v = src.K[1, 1] * P[1] / P[2] + src.K[1, 2]
    sh, sw = src.image.shape[:2]
    return u, v, (P[2] > 0) & (u >= 0) & (u <= sw - 1) & (v >= 0) & (v <= sh - 1)


FEATHER_PX = 4  # the fill fades into the frame's own pixels over this many pixels
DEPTH_STEP = 4  # a hole's depth is its nearest known depth on every DEPTH_STEP-th pixel


def fill_border(out: np.ndarray, uncovered: np.ndarray, depth: np.ndarray, K: np.ndarray, zoom: float,
                virtual: np.ndarray, sources: list[FillSource], feather: int = FEATHER_PX) -> np.ndarray:
    """Fill ``out``'s ``uncovered`` pixels from ``sources`` (in the order given), (14); returns what is left.

    ``out`` (H, W, 3) is changed in place. ``depth`` (H, W): the output's own depth (0 = none), from
    which each uncovered pixel takes its nearest; ``virtual`` = g_c(t) g_s(t), the virtual
    camera's pose in the sources' chain; ``K`` the frame's intrinsics (the virtual camera's too).
    The seam is hidden twice: each source's pixels are offset by its mean colour difference to the
    frame over the covered pixels within ``feather`` px of the hole (exposure), and the fill fades
    into those pixels over that distance.
    """
    left = uncovered.copy()
    if not left.any() or not sources:
        return left
    coarse = nearest_depth(depth[::DEPTH_STEP, ::DEPTH_STEP])  # the hole's depth: nearest on a coarse grid
    if coarse is None:
        return left
    h, w = left.shape
    dist = cv2.distanceTransform((~uncovered).astype(np.uint8), cv2.DIST_L2, 3) if feather > 0 else None
    near = (dist > 0) & (dist <= feather) if feather > 0 else np.zeros_like(left)
    ys, xs = np.nonzero(uncovered | near)
    d = depth[ys, xs].astype(np.float64)
    d = np.where(d > 0, d, coarse[np.minimum(ys // DEPTH_STEP, coarse.shape[0] - 1),
                                  np.minimum(xs // DEPTH_STEP, coarse.shape[1] - 1)])
    q = zoom_matrix(w, h, zoom) @ np.vstack([xs, ys, np.ones(xs.size)])
    rays = np.linalg.solve(K, q) * d  # virtual-camera points (3, n)
    vals = np.zeros((xs.size, out.shape[2]), np.float32)
    which = np.full(xs.size, -1)
    todo = np.arange(xs.size)
    for i, src in enumerate(sources):
        u, v, ok = project(src, virtual, rays[:, todo])
        if not ok.any():
            continue
        got = todo[ok]
        vals[got] = cv2.remap(src.image, u[ok].astype(np.float32)[None], v[ok].astype(np.float32)[None],
                              cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
        which[got] = i
        todo = todo[~ok]
        if todo.size == 0:
            break
    hole = uncovered[ys, xs]
    own = out[ys, xs].astype(np.float32)
    for i in np.unique(which[which >= 0]):
        mine = which == i
        ring = mine & ~hole
        if np.count_nonzero(ring) >= 16:  # exposure: the source's mean colour difference to the frame
            vals[mine] += np.mean(own[ring] - vals[ring], axis=0)
    alpha = np.where(hole, 1.0, 1.0 - dist[ys, xs] / (feather + 1.0) if feather > 0 else 0.0)
    alpha = np.where(which >= 0, alpha, 0.0)[:, None]
    out[ys, xs] = np.clip(alpha * vals + (1.0 - alpha) * own + 0.5, 0, 255).astype(out.dtype)
    left[ys[hole & (which >= 0)], xs[hole & (which >= 0)]] = False
    return left


def raise_for(left: np.ndarray, zoom: float) -> float:
    """The zoom that crops the uncovered pixels ``left`` (a mask of the output at ``zoom``) away:
    the largest centred rectangle free of them becomes the frame."""
    s = scale_from_mask(left)
    return zoom / s if s > 0 else float("inf")


def _reached(points: np.ndarray, virtual: np.ndarray, sources: list[FillSource]) -> np.ndarray:
    """Which virtual-camera points (3, n) some source sees inside its image: (n,) bool."""
    seen = np.zeros(points.shape[1], bool)
    todo = np.arange(points.shape[1])
    for src in sources:
        ok = project(src, virtual, points[:, todo])[2]
        seen[todo[ok]] = True
        todo = todo[~ok]
        if todo.size == 0:
            break
    return seen


def covered_zoom(mesh, depth: np.ndarray, K: np.ndarray, zoom: float, virtual: np.ndarray | None,
                 sources: list[FillSource], step: int = 4) -> float:
    """The smallest zoom >= ``zoom`` at which the frame's mesh plus the fill from ``sources`` leave no
    border, estimated before anything is rendered (docs/method.md 5.4) on every ``step``-th output
    pixel and along the output's edges, where a border starts (a sample stands for its step x step
    block). ``virtual`` None: the mesh alone."""
    q, src = sample_map(mesh, zoom, step)
    h, w = depth.shape
    gh, gw = q.shape[:2]
    ring = _edge_points(w, h, step)
    pts = np.concatenate([q.reshape(-1, 2), ring])
    at = np.concatenate([src.reshape(-1, 2), map_points(mesh, ring, zoom)])
    inside = (at[:, 0] >= 0) & (at[:, 0] <= w - 1) & (at[:, 1] >= 0) & (at[:, 1] <= h - 1)
    left = ~inside
    if not left.any():
        return zoom
    if virtual is not None and sources:
        iu = np.clip(np.rint(at[:, 0]), 0, w - 1).astype(np.intp)
        iv = np.clip(np.rint(at[:, 1]), 0, h - 1).astype(np.intp)
        grid = nearest_depth(np.where(inside[:gh * gw], depth[iv[:gh * gw], iu[:gh * gw]], 0.0).reshape(gh, gw))
        if grid is not None:
            # each uncovered sample takes the depth of the grid cell nearest to it (the grid's own
            # uncovered cells already carry their nearest covered cell's)
            x0, y0 = q[0, 0]
            ci = np.clip(np.rint((pts[left, 0] - x0) / step), 0, gw - 1).astype(np.intp)
            ri = np.clip(np.rint((pts[left, 1] - y0) / step), 0, gh - 1).astype(np.intp)
            ql = pts[left]
            rays = np.linalg.solve(K, zoom_matrix(w, h, zoom) @ np.vstack([ql.T, np.ones(len(ql))])) * grid[ri, ci]
            idx = np.flatnonzero(left)
            left[idx[_reached(rays, virtual, sources)]] = False
    if not left.any():
        return zoom
    a, b = (w - 1) / 2.0, (h - 1) / 2.0
    ql = pts[left]
    dx = np.maximum(np.abs(ql[:, 0] - a) - step / 2.0, 0.0) / a
    dy = np.maximum(np.abs(ql[:, 1] - b) - step / 2.0, 0.0) / b
    s = float(np.min(np.maximum(dx, dy)))
    return zoom / s if s > 0 else float("inf")


def _edge_points(w: int, h: int, step: int) -> np.ndarray:
    """Output positions every ``step`` px along the four edges of a w x h output (corners included): (n, 2)."""
    xs = np.unique(np.append(np.arange(0, w, step, dtype=np.float64), w - 1))
    ys = np.unique(np.append(np.arange(0, h, step, dtype=np.float64), h - 1))
    return np.concatenate([np.column_stack([xs, np.zeros_like(xs)]), np.column_stack([xs, np.full_like(xs, h - 1)]),
                           np.column_stack([np.zeros_like(ys), ys]), np.column_stack([np.full_like(ys, w - 1), ys])])

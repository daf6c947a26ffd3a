"""Rendering a :class:`MeshWarp` with one ``cv2.remap``: design note section 5.

The inverse map (output pixel -> input pixel) is piecewise projective: in each
cell, the homography taking the cell's output quad to its input rectangle.
Output pixels outside the warped mesh use the homography of the nearest cell
(nearest in input space: the cell whose rectangle is closest to where its own
homography sends the pixel), so they land outside the source image and come
out as ``border`` (BORDER_CONSTANT). Because the grid's outer edges are the
source's border (vertices on pixel centres 0 .. W-1), the covered part of the
output is exactly the polygon of the mesh's outer output vertices.

Speed: the map is evaluated at every ``step``-th pixel (plus one sample of
padding on each side, so no output pixel is extrapolated), upsampled with one
``cv2.resize`` (INTER_LINEAR), converted to fixed point and used by one remap.
Within a cell the map is a homography (smooth); across an inner cell edge it is
continuous in the direction across the edge, but two neighbouring homographies
can parametrise the shared edge differently (a tangential slip: measured
0.001 px for a 1 degree + 1 cm stabilising motion, 0.008 px for 3 degrees + 5 cm),
which the interpolation smooths over one step. Measured against the exact map
(step 1) for those motions: max error 0.005 / 0.01 px at step 4, 0.02 px at step 8.
640x480 BGR on one core: ~2 ms per render at step 4 (~1 ms of it the remap itself).

Zoom ("framing scale" s >= 1): output pixel q shows what the unzoomed output
shows at c + (q - c) / s, with c the image centre ((W-1)/2, (H-1)/2).
"""
from __future__ import annotations

import threading
from functools import lru_cache

import cv2
import numpy as np

from .warp import MeshWarp, grid_geometry

# Map values are clipped to +-_CLIP_FACTOR * max(W, H) (far outside the source
# either way) so the 16-bit fixed-point conversion never overflows.
_CLIP_FACTOR = 4


def cell_homographies(mesh: MeshWarp) -> tuple[np.ndarray, np.ndarray]:
    """Per-cell homographies (C, 3, 3) output quad -> input rectangle, and the rectangles (C, 4).

    Cells are in row-major order; a rectangle is ``[x0, x1, y0, y1]``. Built in
    closed form (unit square -> quad, Heckbert 1989), vectorised over cells.
    """
    gx, gy = mesh.grid
    geo = grid_geometry(mesh.width, mesh.height, gx, gy)
    d = mesh.dst
    p0 = d[:-1, :-1].reshape(-1, 2)
    p1 = d[:-1, 1:].reshape(-1, 2)
    p2 = d[1:, 1:].reshape(-1, 2)
    p3 = d[1:, :-1].reshape(-1, 2)
    s = p0 - p1 + p2 - p3
    d1 = p1 - p2
    d2 = p3 - p2
    den = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    g = (s[:, 0] * d2[:, 1] - d2[:, 0] * s[:, 1]) / den
    h = (d1[:, 0] * s[:, 1] - s[:, 0] * d1[:, 1]) / den
    Q = np.empty((len(p0), 3, 3))
    Q[:, 0, 0] = p1[:, 0] - p0[:, 0] + g * p1[:, 0]
    Q[:, 0, 1] = p3[:, 0] - p0[:, 0] + h * p3[:, 0]
    Q[:, 0, 2] = p0[:, 0]
    Q[:, 1, 0] = p1[:, 1] - p0[:, 1] + g * p1[:, 1]
    Q[:, 1, 1] = p3[:, 1] - p0[:, 1] + h * p3[:, 1]
    Q[:, 1, 2] = p0[:, 1]
    Q[:, 2, 0] = g
    Q[:, 2, 1] = h
    Q[:, 2, 2] = 1.0
    x0, y0 = np.meshgrid(geo.xs[:-1], geo.ys[:-1])
    x1, y1 = np.meshgrid(geo.xs[1:], geo.ys[1:])
    rects = np.column_stack((x0.ravel(), x1.ravel(), y0.ravel(), y1.ravel()))
    R = np.zeros_like(Q)
    R[:, 0, 0] = rects[:, 1] - rects[:, 0]
    R[:, 0, 2] = rects[:, 0]
    R[:, 1, 1] = rects[:, 3] - rects[:, 2]
    R[:, 1, 2] = rects[:, 2]
    R[:, 2, 2] = 1.0
    return R @ np.linalg.inv(Q), rects


def zoom_matrix(width: int, height: int, framing_scale: float) -> np.ndarray:
    """3x3 map from zoomed output pixels to unzoomed ones (zoom about the image centre)."""
    if not (np.isfinite(framing_scale) and framing_scale > 0):
        raise ValueError(f"framing_scale must be finite and > 0, got {framing_scale}")
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    k = 1.0 / framing_scale
    return np.array([[k, 0.0, cx * (1 - k)], [0.0, k, cy * (1 - k)], [0.0, 0.0, 1.0]])


class _Workspace:
    """Preallocated buffers for mapping ``K`` points through ``C`` cells (and, for maps, the images).

    Reusing them matters: the map's temporaries are a few hundred kB each, and
    fresh allocations of that size come from the OS with page faults (measured:
    the same arithmetic 3-4x slower). One workspace per thread and size.
    """

    def __init__(self, cells: int, k: int) -> None:
        self.M = np.empty((cells, 3, k))
        self.x = np.empty((cells, k))
        self.y = np.empty((cells, k))
        self.dist = np.empty((cells, k))
        self.tmp = np.empty((cells, k))
        self.bad = np.empty((cells, k), bool)
        self.best = np.empty(k, np.intp)
        self.col = np.arange(k)
        self.xs = np.empty(k)
        self.ys = np.empty(k)


class _MapWorkspace(_Workspace):
    """A :class:`_Workspace` for one output size and map step, with the image-sized buffers."""

    def __init__(self, width: int, height: int, step: int, cells: int) -> None:
        self.P, (nh, nw) = _samples(width, height, step)
        super().__init__(cells, self.P.shape[1])
        self.low = np.empty((nh, nw, 2), np.float32)
        self.up = np.empty((nh * step, nw * step, 2), np.float32) if step > 1 else None
        self.m1 = np.empty((height, width, 2), np.int16)
        self.m2 = np.empty((height, width), np.uint16)


_local = threading.local()


def _map_workspace(width: int, height: int, step: int, cells: int) -> _MapWorkspace:
    """This thread's workspace for the size (a few kept, most recent first)."""
    cache = getattr(_local, "cache", None)
    if cache is None:
        cache = _local.cache = {}
    key = (width, height, step, cells)
    ws = cache.pop(key, None)
    if ws is None:
        ws = _MapWorkspace(width, height, step, cells)
        while len(cache) >= 3:
            del cache[next(iter(cache))]
    cache[key] = ws
    return ws


def _apply(Hs: np.ndarray, rects: np.ndarray, P: np.ndarray, ws: _Workspace | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """Map homogeneous output points P (3, K) through the piecewise homography -> input (x, y).

    Every cell's homography maps every point; each point keeps the cell whose
    input rectangle is nearest (L1) to where that cell's homography sends it
    (distance 0 = the point is inside the cell's output quad). A cell sending a
    point beyond its horizon (w <= 0) is never chosen; a point beyond every
    cell's horizon maps to -inf. Results are views into ``ws`` when given.
    """
    C, K = len(Hs), P.shape[1]
    ws = ws or _Workspace(C, K)
    M, x, y, dist, tmp, bad = ws.M, ws.x, ws.y, ws.dist, ws.tmp, ws.bad
    np.matmul(Hs, P, out=M)
    w = M[:, 2]
    np.less_equal(w, 1e-12, out=bad)
    any_bad = bool(bad.any())
    if any_bad:
        np.putmask(w, bad, 1.0)
    np.divide(M[:, 0], w, out=x)
    np.divide(M[:, 1], w, out=y)
    if C == 1:
        xs, ys = x[0], y[0]
    else:
        np.subtract(rects[:, 0:1], x, out=dist)
        np.subtract(x, rects[:, 1:2], out=tmp)
        np.maximum(dist, tmp, out=dist)
        np.maximum(dist, 0.0, out=dist)
        np.subtract(rects[:, 2:3], y, out=tmp)
        np.add(dist, np.maximum(tmp, 0.0, out=tmp), out=dist)  # + max(y0 - y, 0) + max(y - y1, 0):
        np.subtract(y, rects[:, 3:4], out=tmp)
        np.add(dist, np.maximum(tmp, 0.0, out=tmp), out=dist)  # the distance outside [y0, y1]
        if any_bad:
            np.putmask(dist, bad, np.inf)
        np.argmin(dist, axis=0, out=ws.best)
        idx = ws.best
        np.multiply(idx, K, out=idx)
        np.add(idx, ws.col, out=idx)
        xs = np.take(x, idx, out=ws.xs)
        ys = np.take(y, idx, out=ws.ys)
    if any_bad:
        lost = bad.all(axis=0)
        if C == 1:
            xs, ys = xs.copy(), ys.copy()
        xs[lost] = -np.inf
        ys[lost] = -np.inf
    return xs, ys


def map_points(mesh: MeshWarp, points: np.ndarray, framing_scale: float = 1.0) -> np.ndarray:
    """Exact inverse map: input-image positions (M, 2) shown at output ``points`` (M, 2)."""
    Hs, rects = cell_homographies(mesh)
    Hs = Hs @ zoom_matrix(mesh.width, mesh.height, framing_scale)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    P = np.vstack((pts.T, np.ones(len(pts))))
    x, y = _apply(Hs, rects, P)
    return np.column_stack((x, y))


@lru_cache(maxsize=8)
def _samples(width: int, height: int, step: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Homogeneous low-resolution sample positions (3, K) and the low-res shape (nh, nw), cached.

    Sample j sits at full-resolution position step * (j - 1) + (step - 1) / 2, so
    cv2.resize by exactly ``step`` puts output pixel x at upsampled column x + step.
    """
    nw = -(-width // step) + 2
    nh = -(-height // step) + 2
    xs = step * (np.arange(nw) - 1) + (step - 1) / 2.0
    ys = step * (np.arange(nh) - 1) + (step - 1) / 2.0
    gx, gy = np.meshgrid(xs, ys)
    P = np.vstack((gx.ravel(), gy.ravel(), np.ones(gx.size)))
    P.setflags(write=False)
    return P, (nh, nw)


def _lowres_map(mesh: MeshWarp, framing_scale: float, ws: _MapWorkspace) -> np.ndarray:
    """The inverse map at the low-resolution samples, (nh, nw, 2) float32 (a view of ``ws.low``)."""
    Hs, rects = cell_homographies(mesh)
    Hs = Hs @ zoom_matrix(mesh.width, mesh.height, framing_scale)
    x, y = _apply(Hs, rects, ws.P, ws)
    lim = _CLIP_FACTOR * max(mesh.width, mesh.height)
    nh, nw = ws.low.shape[:2]
    np.clip(x.reshape(nh, nw), -lim, lim, out=ws.low[..., 0], casting="unsafe")
    np.clip(y.reshape(nh, nw), -lim, lim, out=ws.low[..., 1], casting="unsafe")
    return ws.low


def _full_map(mesh: MeshWarp, framing_scale: float, step: int) -> tuple[np.ndarray, _MapWorkspace]:
    """Full-resolution inverse map as a view into this thread's workspace, and the workspace."""
    if int(step) != step or step < 1:
        raise ValueError(f"map step must be an integer >= 1, got {step}")
    step = int(step)
    w, h = mesh.width, mesh.height
    gx, gy = mesh.grid
    ws = _map_workspace(w, h, step, gx * gy)
    low = _lowres_map(mesh, framing_scale, ws)
    if step == 1:
        return low[1:h + 1, 1:w + 1], ws
    cv2.resize(low, ws.up.shape[1::-1], dst=ws.up, interpolation=cv2.INTER_LINEAR)
    return ws.up[step:step + h, step:step + w], ws


def inverse_map(mesh: MeshWarp, framing_scale: float = 1.0, step: int = 4) -> np.ndarray:
    """Full-resolution inverse map (H, W, 2) float32: input position shown at each output pixel.

    Evaluated every ``step`` pixels and upsampled bilinearly (``step=1``: exact at every pixel).
    """
    return _full_map(mesh, framing_scale, step)[0].copy()


def _border(border: int | float | tuple) -> tuple:
    if np.isscalar(border):
        return (border,) * 4
    return tuple(border)


def _remap(image: np.ndarray, inv_map: np.ndarray, border, interpolation: int, out: np.ndarray | None,
           ws: _MapWorkspace | None) -> np.ndarray:
    """One cv2.remap; bilinear and better use OpenCV's fixed-point maps (1/32 pixel, what remap
    uses internally anyway; the conversion is cheaper than remap's own per-block one)."""
    bv = (border,) * 4 if np.isscalar(border) else tuple(border)
    if interpolation == cv2.INTER_NEAREST:
        return cv2.remap(image, inv_map, None, interpolation, dst=out, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=bv)
    if ws is not None:
        m1, m2 = cv2.convertMaps(inv_map, None, cv2.CV_16SC2, dstmap1=ws.m1, dstmap2=ws.m2)
    else:
        m1, m2 = cv2.convertMaps(inv_map, None, cv2.CV_16SC2)
    return cv2.remap(image, m1, m2, interpolation, dst=out, borderMode=cv2.BORDER_CONSTANT, borderValue=bv)


def remap(image: np.ndarray, inv_map: np.ndarray, border: int | float | tuple = 0,
          interpolation: int = cv2.INTER_LINEAR, out: np.ndarray | None = None) -> np.ndarray:
    """Warp ``image`` with an inverse map from :func:`inverse_map` (one ``cv2.remap``)."""
    return _remap(image, inv_map, border, interpolation, out, None)


def render(image: np.ndarray, mesh: MeshWarp, framing_scale: float = 1.0, border: int | float | tuple = 0,
           step: int = 4, interpolation: int = cv2.INTER_LINEAR, out: np.ndarray | None = None) -> np.ndarray:
    """The stabilised frame: ``image`` warped by ``mesh`` and zoomed by ``framing_scale`` about the centre.

    ``image`` is any image of the mesh's size (BGR, grey, depth with INTER_NEAREST, ...);
    pixels with no source are ``border`` (black by default). ``out`` (same shape and
    type as ``image``) receives the result when given.
    """
    if image.shape[:2] != (mesh.height, mesh.width):
        raise ValueError(f"image is {image.shape[1]}x{image.shape[0]} but the mesh is for "
                         f"{mesh.width}x{mesh.height}")
    inv_map, ws = _full_map(mesh, framing_scale, step)
    return _remap(image, inv_map, border, interpolation, out, ws)


def valid_mask(inv_map: np.ndarray, width: int, height: int) -> np.ndarray:
    """Boolean (H, W): output pixels whose source position lies in [0, W-1] x [0, H-1]."""
    x = inv_map[..., 0]
    y = inv_map[..., 1]
    return (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)


def coverage(mesh: MeshWarp, framing_scale: float = 1.0, step: int = 4) -> float:
    """Fraction of the output covered by source pixels, from the map's low-resolution samples."""
    gx, gy = mesh.grid
    ws = _map_workspace(mesh.width, mesh.height, int(step), gx * gy)
    low = _lowres_map(mesh, framing_scale, ws)[1:-1, 1:-1]
    return float(np.mean(valid_mask(low, mesh.width, mesh.height)))

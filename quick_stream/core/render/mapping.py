"""Rendering a :class:`MeshWarp` with one ``cv2.remap``: docs/method.md 5.2.

The renderer uses the same cell model as the fit (:mod:`.warp`): each cell maps
its input rectangle to its output quad *bilinearly*, so an input pixel goes
exactly where the fit put it (B X, docs/method.md (13a)). The inverse map (output
pixel -> input pixel) is therefore the inverse of a bilinear map, solved per
output sample in closed form (a quadratic per cell, docs/method.md (13b)) and
vectorised over cells and samples. The previous renderer used one homography
per cell (quad -> rectangle): it agrees with the bilinear cell only at the 4
corners, and showed control points up to 0.9 px away from where the fit put them
(7scenes, 0.5-3 degree + 1-5 cm corrections; now < 0.001 px).

Every cell's inverse maps every sample; each sample keeps the cell whose input
rectangle is nearest (L1) to where that cell's inverse sends it (distance 0 =
the sample is inside the cell's output quad). Output pixels outside the warped
mesh thus use the nearest cell's analytic continuation and land outside the
source image: they come out as ``border`` (BORDER_CONSTANT). A bilinear map is
affine along each cell edge, so the outer edges of the mesh stay straight and
the covered part of the output is exactly the polygon of the mesh's outer
output vertices (what :func:`.framing.border_free_zoom` assumes). Neighbouring
cells parametrise a shared inner edge identically (affinely between its two
vertices), so the map is continuous across inner edges with no tangential slip.

Speed: the map is evaluated at every ``step``-th pixel (plus one sample of
padding on each side, so no output pixel is extrapolated), upsampled with one
``cv2.resize`` (INTER_LINEAR), converted to fixed point and used by one remap.
Within a cell the inverse map is smooth; across an inner cell edge it is
continuous with a kink, which the interpolation smooths over one step.
Measured against the exact map (step 1) on 7scenes frames with 0.5-3 degree +
1-5 cm corrections: see docs/method.md section 5 for the numbers.

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


def zoom_matrix(width: int, height: int, framing_scale: float) -> np.ndarray:
    """3x3 map from zoomed output pixels to unzoomed ones (zoom about the image centre)."""
    if not (np.isfinite(framing_scale) and framing_scale > 0):
        raise ValueError(f"framing_scale must be finite and > 0, got {framing_scale}")
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    k = 1.0 / framing_scale
    return np.array([[k, 0.0, cx * (1 - k)], [0.0, k, cy * (1 - k)], [0.0, 0.0, 1.0]])


def cell_inverse_bilinear(mesh: MeshWarp) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients of each cell's inverse bilinear map (output quad -> input rectangle), docs/method.md (13b).

    Returns ``R`` (C, 3, 3), ``consts`` (C, 4) and the rectangles (C, 4) ``[x0, x1, y0, y1]``
    (cells in row-major order). For an output point q (homogeneous column [qx, qy, 1])
    the rows of ``R @ q`` are ``a = 2 w_c cross(q - p0, f)``, ``b = 2 h_c cross(q - p0, e)``
    and ``t = cross(e, f) + cross(q - p0, g)``; with ``consts = [2 cross(e, f), kappa, x0, y0]``,
    ``kappa = 2 cross(g, f) / h_c``, the input point is::

        D = t^2 - kappa b,   x = x0 + a / (2 cross(e, f) - t + sqrt(D)),   y = y0 - b / (t + sqrt(D))

    where p0..p3 are the cell's output corners 00, 10, 11, 01, e = p1 - p0, f = p3 - p0,
    g = p0 - p1 + p2 - p3 and (w_c, h_c) the input cell's size. Both roots are the
    ones that stay finite as g -> 0 (the parallelogram case, where the map is affine).
    """
    gx, gy = mesh.grid
    geo = grid_geometry(mesh.width, mesh.height, gx, gy)
    d = mesh.dst
    p0 = d[:-1, :-1].reshape(-1, 2)
    p1 = d[:-1, 1:].reshape(-1, 2)
    p2 = d[1:, 1:].reshape(-1, 2)
    p3 = d[1:, :-1].reshape(-1, 2)
    e = p1 - p0
    f = p3 - p0
    g = p0 - p1 + p2 - p3
    x0, y0 = np.meshgrid(geo.xs[:-1], geo.ys[:-1])
    x1, y1 = np.meshgrid(geo.xs[1:], geo.ys[1:])
    rects = np.column_stack((x0.ravel(), x1.ravel(), y0.ravel(), y1.ravel()))
    cw = (rects[:, 1] - rects[:, 0])[:, None]
    ch = (rects[:, 3] - rects[:, 2])[:, None]

    def cross_row(v: np.ndarray) -> np.ndarray:
        """Rows r with r . [qx, qy, 1] = cross(q - p0, v) = (qx - p0x) v_y - (qy - p0y) v_x."""
        return np.column_stack((v[:, 1], -v[:, 0], p0[:, 1] * v[:, 0] - p0[:, 0] * v[:, 1]))

    cef = e[:, 0] * f[:, 1] - e[:, 1] * f[:, 0]
    cgf = g[:, 0] * f[:, 1] - g[:, 1] * f[:, 0]
    R = np.empty((len(p0), 3, 3))
    R[:, 0] = 2.0 * cw * cross_row(f)
    R[:, 1] = 2.0 * ch * cross_row(e)
    R[:, 2] = cross_row(g)
    R[:, 2, 2] += cef
    consts = np.column_stack((2.0 * cef, 2.0 * cgf / ch[:, 0], rects[:, 0], rects[:, 2]))
    return R, consts, rects


class _Workspace:
    """Preallocated buffers for mapping ``K`` points through ``C`` cells (and, for maps, the images).

    Reusing them matters: the map's temporaries are a few hundred kB each, and
    fresh allocations of that size come from the OS with page faults (measured:
    the same arithmetic 3-4x slower). One workspace per thread and size.
    """

    def __init__(self, cells: int, k: int, dtype: type = np.float64) -> None:
        self.M = np.empty((cells, 3, k), dtype)
        self.x = np.empty((cells, k), dtype)
        self.y = np.empty((cells, k), dtype)
        self.dist = np.empty((cells, k), dtype)
        self.tmp = np.empty((cells, k), dtype)
        self.sq = np.empty((cells, k), dtype)
        self.bad = np.empty((cells, k), bool)
        self.bad2 = np.empty((cells, k), bool)
        self.best = np.empty(k, np.intp)
        self.col = np.arange(k)
        self.xs = np.empty(k, dtype)
        self.ys = np.empty(k, dtype)


class _MapWorkspace(_Workspace):
    """A :class:`_Workspace` for one output size and map step, with the image-sized buffers."""

    def __init__(self, width: int, height: int, step: int, cells: int) -> None:
        P, (nh, nw) = _samples(width, height, step)
        # float32 arithmetic for the map (stored as float32 anyway): rounding ~1e-4 px at 640x480
        self.P = P.astype(np.float32)
        super().__init__(cells, self.P.shape[1], np.float32)
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


def _apply(R: np.ndarray, consts: np.ndarray, rects: np.ndarray, P: np.ndarray, ws: _Workspace | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """Map homogeneous output points P (3, K) through the piecewise inverse bilinear map -> input (x, y).

    ``R``, ``consts``, ``rects`` from :func:`cell_inverse_bilinear` (zoom folded into ``R``).
    Every cell's inverse maps every point; each point keeps the cell whose input
    rectangle is nearest (L1) to where that cell's inverse sends it (distance 0 =
    the point is inside the cell's output quad). A cell with no real inverse at a
    point (negative discriminant, or a denominator <= 0: far beyond the quad,
    where the bilinear map folds) is never chosen there; a point with no inverse
    in any cell maps to -inf. Results are views into ``ws`` when given.
    """
    C, K = len(R), P.shape[1]
    ws = ws or _Workspace(C, K, P.dtype)
    M, x, y, dist, tmp, sq, bad = ws.M, ws.x, ws.y, ws.dist, ws.tmp, ws.sq, ws.bad
    dt = M.dtype
    np.matmul(R.astype(dt, copy=False), P, out=M)
    a, b, t = M[:, 0], M[:, 1], M[:, 2]
    c2, kappa, x0, y0 = (consts[:, i:i + 1].astype(dt) for i in range(4))
    np.multiply(t, t, out=sq)
    np.multiply(b, kappa, out=tmp)
    np.subtract(sq, tmp, out=sq)
    with np.errstate(invalid="ignore"):
        np.sqrt(sq, out=sq)  # NaN where the discriminant is negative: caught by the tests below
    np.add(t, sq, out=y)  # denominator of y
    np.subtract(c2, t, out=x)
    np.add(x, sq, out=x)  # denominator of x
    eps = 1e-6 * np.abs(c2)  # c2 = 2 cross(e, f) > 0 (twice the cell's area scale); the denominators are ~c2
    # usual case, checked with two reductions: every cell invertible at every point (NaN fails the test)
    any_bad = not (np.all(x.min(axis=1) > eps[:, 0]) and np.all(y.min(axis=1) > eps[:, 0]))
    if any_bad:
        np.greater(x, eps, out=bad)
        np.logical_and(bad, np.greater(y, eps, out=ws.bad2), out=bad)
        np.logical_not(bad, out=bad)
        np.putmask(x, bad, 1.0)
        np.putmask(y, bad, 1.0)
    np.divide(a, x, out=x)
    np.add(x, x0, out=x)
    np.divide(b, y, out=y)
    np.subtract(y0, y, out=y)
    if C == 1:
        xs, ys = x[0], y[0]
    else:
        r = rects.astype(dt)
        np.subtract(r[:, 0:1], x, out=dist)
        np.subtract(x, r[:, 1:2], out=tmp)
        np.maximum(dist, tmp, out=dist)
        np.maximum(dist, 0.0, out=dist)
        np.subtract(r[:, 2:3], y, out=tmp)
        np.add(dist, np.maximum(tmp, 0.0, out=tmp), out=dist)  # + max(y0 - y, 0) + max(y - y1, 0):
        np.subtract(y, r[:, 3:4], out=tmp)
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


def _coefficients(mesh: MeshWarp, framing_scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`cell_inverse_bilinear` with the zoom folded in (output pixel -> unzoomed output is affine)."""
    R, consts, rects = cell_inverse_bilinear(mesh)
    return R @ zoom_matrix(mesh.width, mesh.height, framing_scale), consts, rects


def map_points(mesh: MeshWarp, points: np.ndarray, framing_scale: float = 1.0) -> np.ndarray:
    """Exact inverse map: input-image positions (M, 2) shown at output ``points`` (M, 2)."""
    R, consts, rects = _coefficients(mesh, framing_scale)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    P = np.vstack((pts.T, np.ones(len(pts))))
    x, y = _apply(R, consts, rects, P)
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
    R, consts, rects = _coefficients(mesh, framing_scale)
    x, y = _apply(R, consts, rects, ws.P, ws)
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


def render_covered(image: np.ndarray, depth: np.ndarray, mesh: MeshWarp, framing_scale: float = 1.0,
                   step: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`render` plus what the border fill needs (docs/method.md 5.4): the output pixels with no
    source (bool (H, W)) and, when there are any, ``depth`` rendered the same way (nearest; 0 where
    uncovered)."""
    if image.shape[:2] != (mesh.height, mesh.width):
        raise ValueError(f"image is {image.shape[1]}x{image.shape[0]} but the mesh is for "
                         f"{mesh.width}x{mesh.height}")
    inv_map, ws = _full_map(mesh, framing_scale, step)
    uncovered = ~valid_mask(inv_map, mesh.width, mesh.height)
    d = _remap(depth, inv_map, 0, cv2.INTER_NEAREST, None, None) if uncovered.any() else None
    return _remap(image, inv_map, 0, cv2.INTER_LINEAR, None, ws), uncovered, d


def sample_map(mesh: MeshWarp, framing_scale: float = 1.0, step: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The inverse map at every ``step``-th output pixel: (output positions (gh, gw, 2), input
    positions (gh, gw, 2)), the samples inside the output only (what the renderer upsamples,
    without its padding)."""
    gx, gy = mesh.grid
    ws = _map_workspace(mesh.width, mesh.height, int(step), gx * gy)
    low = _lowres_map(mesh, framing_scale, ws)
    q = ws.P[:2].T.reshape(low.shape)
    cols = (q[0, :, 0] >= 0) & (q[0, :, 0] <= mesh.width - 1)
    rows = (q[:, 0, 1] >= 0) & (q[:, 0, 1] <= mesh.height - 1)
    return q[rows][:, cols].astype(np.float64), low[rows][:, cols].astype(np.float64)


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

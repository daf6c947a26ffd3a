"""The piecewise inverse bilinear map of a :class:`MeshWarp`: output pixel -> input pixel, docs/method.md (13b).

The renderer uses the same cell model as the fit (:mod:`.warp`): each cell maps
its input rectangle to its output quad *bilinearly*, so an input pixel goes
exactly where the fit put it (B X, docs/method.md (13a)). The inverse map (output
pixel -> input pixel) is therefore the inverse of a bilinear map, solved per
output point in closed form (a quadratic per cell, docs/method.md (13b)) and
vectorised over cells and points. The previous renderer used one homography
per cell (quad -> rectangle): it agrees with the bilinear cell only at the 4
corners, and showed control points up to 0.9 px away from where the fit put them
(7scenes, 0.5-3 degree + 1-5 cm corrections; now < 0.001 px).

Every cell's inverse maps every point; each point keeps the cell whose input
rectangle is nearest (L1) to where that cell's inverse sends it (distance 0 =
the point is inside the cell's output quad). Output pixels outside the warped
mesh thus use the nearest cell's analytic continuation and land outside the
source image. A bilinear map is affine along each cell edge, so the outer edges
of the mesh stay straight and the covered part of the output is exactly the
polygon of the mesh's outer output vertices (what :func:`.framing.border_free_zoom`
assumes). Neighbouring cells parametrise a shared inner edge identically (affinely
between its two vertices), so the map is continuous across inner edges with no
tangential slip.

Zoom ("framing scale" s >= 1): output pixel q shows what the unzoomed output
shows at c + (q - c) / s, with c the image centre ((W-1)/2, (H-1)/2).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from .warp import MeshWarp, grid_geometry


def zoom_matrix(width: int, height: int, framing_scale: float) -> np.ndarray:
    """3x3 map from zoomed output pixels to unzoomed ones (zoom about the image centre)."""
    if not (np.isfinite(framing_scale) and framing_scale > 0):
        raise ValueError(f"framing_scale must be finite and > 0, got {framing_scale}")
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    k = 1.0 / framing_scale
    return np.array([[k, 0.0, cx * (1 - k)], [0.0, k, cy * (1 - k)], [0.0, 0.0, 1.0]])


def cell_inverse_bilinear(d: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients of each cell's inverse bilinear map (output quad -> input rectangle), docs/method.md (13b),
    for the output vertices ``d`` (gy+1, gx+1, 2) of a width x height mesh.

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
    gy, gx = d.shape[0] - 1, d.shape[1] - 1
    p0 = d[:-1, :-1].reshape(-1, 2)
    p1 = d[:-1, 1:].reshape(-1, 2)
    p2 = d[1:, 1:].reshape(-1, 2)
    p3 = d[1:, :-1].reshape(-1, 2)
    e = p1 - p0
    f = p3 - p0
    g = p0 - p1 + p2 - p3
    rects = _cell_rects(width, height, gx, gy)
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


@lru_cache(maxsize=16)
def _cell_rects(width: int, height: int, gx: int, gy: int) -> np.ndarray:
    """The input cells' rectangles (C, 4) ``[x0, x1, y0, y1]`` in row-major order, read-only and cached."""
    geo = grid_geometry(width, height, gx, gy)
    x0, y0 = np.meshgrid(geo.xs[:-1], geo.ys[:-1])
    x1, y1 = np.meshgrid(geo.xs[1:], geo.ys[1:])
    rects = np.column_stack((x0.ravel(), x1.ravel(), y0.ravel(), y1.ravel()))
    rects.setflags(write=False)
    return rects


class Workspace:
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
        self.near = np.empty(k, dtype)
        self.closer = np.empty(k, bool)
        self.mask = np.empty(k, dtype)  # integer views of these two: bit masks
        self.bits = np.empty(k, dtype)
        self.xs = np.empty(k, dtype)
        self.ys = np.empty(k, dtype)


def apply_inverse(R: np.ndarray, consts: np.ndarray, rects: np.ndarray, P: np.ndarray, ws: Workspace | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """Map homogeneous output points P (3, K) through the piecewise inverse bilinear map -> input (x, y).

    ``R``, ``consts``, ``rects`` from :func:`coefficients` (zoom folded into ``R``).
    Every cell's inverse maps every point; each point keeps the cell whose input
    rectangle is nearest (L1) to where that cell's inverse sends it (distance 0 =
    the point is inside the cell's output quad). A cell with no real inverse at a
    point (negative discriminant, or a denominator <= 0: far beyond the quad,
    where the bilinear map folds) is never chosen there; a point with no inverse
    in any cell maps to -inf. Results are views into ``ws`` when given.
    """
    C, K = len(R), P.shape[1]
    ws = ws or Workspace(C, K, P.dtype)
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
        # the nearest cell per point, the first of equals (argmin's choice): a running minimum, each
        # point's x, y replaced through bit masks (argmin's strided reduction and a masked copy are 4x slower)
        xs, ys, near, closer = ws.xs, ws.ys, ws.near, ws.closer
        bits = np.dtype(f"i{dt.itemsize}")
        mask, tmp = ws.mask.view(bits), ws.bits.view(bits)
        np.copyto(xs, x[0])
        np.copyto(ys, y[0])
        np.copyto(near, dist[0])
        for c in range(1, C):
            np.less(dist[c], near, out=closer)
            np.negative(closer.view(np.int8), out=mask, casting="unsafe")  # all bits set where closer
            for got, new in ((xs, x[c]), (ys, y[c])):
                got, new = got.view(bits), new.view(bits)
                np.bitwise_xor(got, new, out=tmp)
                np.bitwise_and(tmp, mask, out=tmp)
                np.bitwise_xor(got, tmp, out=got)
            if c < C - 1:
                np.minimum(near, dist[c], out=near)
    if any_bad:
        lost = bad.all(axis=0)
        if C == 1:
            xs, ys = xs.copy(), ys.copy()
        xs[lost] = -np.inf
        ys[lost] = -np.inf
    return xs, ys


def coefficients(mesh: MeshWarp, framing_scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`cell_inverse_bilinear` with the zoom folded in (output pixel -> unzoomed output is affine).

    The last few are kept (read-only), keyed by the mesh's output vertices and the zoom: a frame's
    render, its border-fill estimate and its edge points ask for the same ones."""
    d = np.asarray(mesh.dst, np.float64)
    return _zoomed(d.tobytes(), d.shape, mesh.width, mesh.height, float(framing_scale))


@lru_cache(maxsize=8)
def _zoomed(dst: bytes, shape: tuple[int, ...], width: int, height: int, framing_scale: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`coefficients` of the output vertices ``dst`` (float64 bytes of ``shape``), cached."""
    R, consts, rects = cell_inverse_bilinear(np.frombuffer(dst).reshape(shape), width, height)
    out = (R @ zoom_matrix(width, height, framing_scale), consts, rects)
    for a in out:
        a.setflags(write=False)
    return out


def map_points(mesh: MeshWarp, points: np.ndarray, framing_scale: float = 1.0) -> np.ndarray:
    """Exact inverse map: input-image positions (M, 2) shown at output ``points`` (M, 2)."""
    R, consts, rects = coefficients(mesh, framing_scale)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    P = np.vstack((pts.T, np.ones(len(pts))))
    x, y = apply_inverse(R, consts, rects, P)
    return np.column_stack((x, y))

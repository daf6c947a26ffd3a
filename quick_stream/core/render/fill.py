"""Border fill: output pixels a frame's own mesh leaves uncovered, taken from its neighbours (docs/method.md 5.4).

A stabilised frame shows the virtual camera's view, and where the virtual camera looks past
the real frame's edge (a shake peak) the mesh leaves a band uncovered. Cropping that band
away costs every frame around the peak its zoom; the neighbouring frames, shaken the other
way, saw what is missing. With the camera poses the motion stage integrated (the correction's
``camera``, g_c) and depth, each missing pixel is a 3D point whose image in a neighbour is
known exactly:

    X_v = d(q) K^-1 Z^-1 q,      X_s = g_c(s)^-1 g_c(t) g_s(t) X_v,      q_s = pi(K_s X_s)     (14)

with q the zoomed output pixel, Z the zoom about the centre (:func:`.inverse_bilinear.zoom_matrix`),
d(q) the depth of the frame's own nearest covered output pixel, looked up on every 4th pixel
(the surface continued past the edge) and g_s(t) the correction (virtual camera relative to
the real one). Neighbours are tried nearest first (the smallest camera motion, so the least parallax error from d), past
and future alike, and only within one pose chain (a path restart breaks the chain). What no
neighbour saw stays uncovered; the caller then zooms in (:func:`raise_for`).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Iterable

import cv2
import numpy as np

from .framing import scale_from_mask
from .inverse_bilinear import map_points, zoom_matrix
from .mapping import map_samples, sample_positions
from .uncovered import DepthAt, lookup, patches
from .warp import MeshWarp


@dataclass
class FillSource:
    """A frame the border fill can read: its input colour, intrinsics and camera pose in ``chain``."""

    seq: int
    chain: int
    camera: np.ndarray  # g_c (4, 4)
    image: np.ndarray  # BGR input frame
    K: np.ndarray  # (3, 3)

    @cached_property
    def camera_inv(self) -> np.ndarray:
        """g_c^-1, for (14): computed once, the source serves up to 2 ``fill_frames`` frames."""
        return np.linalg.inv(self.camera)


def nearest_depth(depth: np.ndarray, at: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray | None:
    """``depth`` with every pixel that has none (<= 0) given its nearest known pixel's; None when no
    pixel has depth. ``at`` (rows, cols): only those pixels' values, (N,)."""
    known = depth > 0
    if not known.any():
        return None
    # distance to the nearest zero of src: zeros are the known pixels, labelled 1, 2, ... in raster
    # order (DIST_LABEL_PIXEL: tests/unit/test_uncovered.py::test_opencv_labels_the_known_pixels_in_raster_order)
    _, labels = cv2.distanceTransformWithLabels(np.logical_not(known).view(np.uint8), cv2.DIST_L2, 3,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    value = np.concatenate(([0.0], depth[known].astype(np.float64)))
    return np.take(value, labels if at is None else labels[at])


def ordered_sources(seq: int, chain: int, sources: Iterable[FillSource], reach: int) -> list[FillSource]:
    """The sources of ``chain`` within ``reach`` frames of ``seq`` (itself excluded), nearest first,
    the earlier of two equally near first, each frame once."""
    near = {s.seq: s for s in sources if s.chain == chain and s.seq != seq and abs(s.seq - seq) <= reach}
    return sorted(near.values(), key=lambda s: (abs(s.seq - seq), s.seq))


def project(src: FillSource, virtual: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, inside) in ``src`` of virtual-camera points (3, n), (14): pixel coordinates and
    whether each lands in front of the source camera and inside its image."""
    T = src.camera_inv @ virtual
    P = T[:3, :3] @ points + T[:3, 3:4]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = src.K[0, 0] * P[0] / P[2] + src.K[0, 2]
        v = src.K[1, 1] * P[1] / P[2] + src.K[1, 2]
    sh, sw = src.image.shape[:2]
    return u, v, (P[2] > 0) & (u >= 0) & (u <= sw - 1) & (v >= 0) & (v <= sh - 1)


FEATHER_PX = 4  # the fill fades into the frame's own pixels over this many pixels
DEPTH_STEP = 4  # a hole's depth is its nearest known depth on every DEPTH_STEP-th pixel


def border_pixels(uncovered: np.ndarray, feather: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``uncovered`` pixels and the covered ones within ``feather`` px of them, row-major: (ys, xs,
    distance), the distance to the nearest uncovered pixel as ``cv2.distanceTransform`` (DIST_L2,
    3x3) measures it over the whole frame (0 on the uncovered pixels). Measured on the rectangles
    :func:`.uncovered.patches` puts around the uncovered pixels, ``feather + 2`` px wide: within
    ``feather`` of a pixel, the nearest uncovered pixel and the shortest step path to it are in its
    rectangle (the distance can differ from the whole frame's in its last bit: OpenCV sums the steps
    in float, and two paths of one length round apart)."""
    if feather <= 0:
        ys, xs = np.nonzero(uncovered)
        return ys, xs, np.zeros(ys.size, np.float32)
    parts = []
    for t0, t1, a, b, c0, c1 in patches(uncovered, feather + 2):
        hole = uncovered[a:b, c0:c1]
        dist = cv2.distanceTransform(np.logical_not(hole).view(np.uint8), cv2.DIST_L2, 3)[t0 - a:t1 - a].ravel()
        at = np.flatnonzero(dist <= feather)  # the hole (distance 0) and its ring: others are >= 0.955 from it
        y, x = np.divmod(at, c1 - c0)
        parts.append((y + t0, x + c0, np.take(dist, at)))
    if not parts:
        return np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0, np.float32)
    ys, xs, dist = (np.concatenate(p) for p in zip(*parts))
    flat = ys * uncovered.shape[1] + xs
    if np.any(np.diff(flat) < 0):  # two rectangles side by side in one strip
        order = np.argsort(flat, kind="stable")
        ys, xs, dist = ys[order], xs[order], dist[order]
    return ys, xs, dist


def fill_border(out: np.ndarray, uncovered: np.ndarray, depth: DepthAt, K: np.ndarray, zoom: float,
                virtual: np.ndarray, sources: list[FillSource], feather: int = FEATHER_PX) -> np.ndarray:
    """Fill ``out``'s ``uncovered`` pixels from ``sources`` (in the order given), (14); returns what is left.

    ``out`` (H, W, 3), C-contiguous, is changed in place. ``depth(ys, xs)``: the output's own depth (0 = none) at
    output pixels (:func:`.uncovered.depth_lookup`), from which each uncovered pixel takes its
    nearest; ``virtual`` = g_c(t) g_s(t), the virtual camera's pose in the sources' chain; ``K`` the
    frame's intrinsics (the virtual camera's too). The seam is hidden twice: each source's pixels
    are offset by its mean colour difference to the frame over the covered pixels within
    ``feather`` px of the hole (exposure), and the fill fades into those pixels over that distance.
    Only the pixels within ``feather`` of the hole are touched (:func:`border_pixels`).
    """
    if not out.flags.c_contiguous:
        raise ValueError("fill_border: out must be C-contiguous (it is changed in place)")
    left = uncovered.copy()
    if not left.any() or not sources:
        return left
    h, w = left.shape
    ys, xs, dist = border_pixels(uncovered, feather)
    flat = ys * w + xs
    d = depth(ys, xs).astype(np.float64)
    blank = np.flatnonzero(d <= 0)
    every = slice(None, None, DEPTH_STEP)  # the hole's depth: its nearest known on a coarse grid
    coarse = nearest_depth(depth(every, every).reshape(-(-h // DEPTH_STEP), -(-w // DEPTH_STEP)),
                           (ys[blank] // DEPTH_STEP, xs[blank] // DEPTH_STEP))
    if coarse is None:
        return left
    d[blank] = coarse
    q = zoom_matrix(w, h, zoom) @ np.vstack([xs, ys, np.ones(xs.size)])
    rays = np.linalg.inv(K) @ q * d  # virtual-camera points (3, n)
    which, uv = first_seen(rays, virtual, sources)
    counts = np.bincount(which + 1, minlength=len(sources) + 1)
    if counts[0] == which.size:
        return left
    # the points some source sees, grouped by source (each group in raster order): the others keep their pixel
    seen = np.argsort(which, kind="stable")[counts[0]:]
    flat, uv, dist = np.take(flat, seen), np.take(uv, seen, axis=0), np.take(dist, seen)
    hole = np.take(uncovered.reshape(-1), flat)
    pixels = out.reshape(-1, out.shape[2])
    own = np.take(pixels, flat, axis=0).astype(np.float32)
    vals = np.empty_like(own)
    end = 0
    for i in np.flatnonzero(counts[1:]):
        mine = slice(end, end + counts[i + 1])
        end = mine.stop
        vals[mine] = lookup(sources[i].image, uv[mine], cv2.INTER_LINEAR, cv2.BORDER_REPLICATE)
        ring = np.flatnonzero(~hole[mine])
        if ring.size >= 16:  # exposure: the source's mean colour difference to the frame
            vals[mine] += np.mean(np.take(own[mine], ring, axis=0) - np.take(vals[mine], ring, axis=0), axis=0)
    alpha = np.where(hole, 1.0, 1.0 - dist / (feather + 1.0) if feather > 0 else 0.0)[:, None]
    pixels[flat] = np.clip(alpha * vals + (1.0 - alpha) * own + 0.5, 0, 255).astype(out.dtype)
    left.reshape(-1)[flat[hole]] = False
    return left


def raise_for(left: np.ndarray, zoom: float) -> float:
    """The zoom that crops the uncovered pixels ``left`` (a mask of the output at ``zoom``) away:
    the largest centred rectangle free of them becomes the frame."""
    s = scale_from_mask(left)
    return zoom / s if s > 0 else float("inf")


def first_seen(points: np.ndarray, virtual: np.ndarray, sources: list[FillSource]) -> tuple[np.ndarray, np.ndarray]:
    """For virtual-camera points (3, n), (14): the index of the first of ``sources`` that sees each inside
    its image (-1: none does) and where it sees it, (n, 2) float32 pixel coordinates (0 where none)."""
    n = points.shape[1]
    which, uv = np.full(n, -1), np.zeros((n, 2), np.float32)
    todo = np.arange(n)
    for i, src in enumerate(sources):
        u, v, ok = project(src, virtual, np.take(points, todo, axis=1))
        if not ok.any():
            continue
        got = todo[ok]
        which[got] = i
        uv[got, 0], uv[got, 1] = u[ok], v[ok]
        todo = todo[~ok]
        if todo.size == 0:
            break
    return which, uv


def covered_zoom(mesh: MeshWarp, depth: np.ndarray, K: np.ndarray, zoom: float, virtual: np.ndarray | None,
                 sources: list[FillSource], step: int = 4, samples: np.ndarray | None = None) -> float:
    """The smallest zoom >= ``zoom`` at which the frame's mesh plus the fill from ``sources`` leave no
    border, estimated before anything is rendered (docs/method.md 5.4) on every ``step``-th output
    pixel and along the output's edges, where a border starts (a sample stands for its step x step
    block). ``virtual`` None: the mesh alone. ``samples``: :func:`.mapping.map_samples` of the mesh at
    ``zoom`` and ``step``, when already computed (the renderer reuses them)."""
    h, w = depth.shape
    low = map_samples(mesh, zoom, step) if samples is None else samples
    rows, cols, q = _inner_samples(w, h, step)
    src = low[rows, cols]  # (gh, gw, 2): the map at the samples inside the output
    ring = _edge_points(w, h, step)
    at = map_points(mesh, ring, zoom)
    inner = cv2.inRange(src, (0.0, 0.0), (w - 1.0, h - 1.0)).ravel() != 0
    edge = (at[:, 0] >= 0) & (at[:, 0] <= w - 1) & (at[:, 1] >= 0) & (at[:, 1] <= h - 1)
    if inner.all() and edge.all():
        return zoom
    ql = np.concatenate([q.reshape(-1, 2)[~inner], ring[~edge]])  # the output positions left uncovered
    if virtual is not None and sources:
        # the depth each sample shows (nearest; 0 outside the source)
        shown = cv2.remap(depth, np.ascontiguousarray(src), None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)
        grid = nearest_depth(np.where(inner.reshape(shown.shape), shown, 0.0))
        if grid is not None:
            # each uncovered sample takes the depth of the grid cell nearest to it (the grid's own
            # uncovered cells already carry their nearest covered cell's)
            gh, gw = grid.shape
            x0, y0 = q[0, 0]
            ci = np.clip(np.rint((ql[:, 0] - x0) / step), 0, gw - 1).astype(np.intp)
            ri = np.clip(np.rint((ql[:, 1] - y0) / step), 0, gh - 1).astype(np.intp)
            rays = np.linalg.inv(K) @ zoom_matrix(w, h, zoom) @ np.vstack([ql.T, np.ones(len(ql))]) * grid[ri, ci]
            ql = ql[first_seen(rays, virtual, sources)[0] < 0]
    if not len(ql):
        return zoom
    a, b = (w - 1) / 2.0, (h - 1) / 2.0
    dx = np.maximum(np.abs(ql[:, 0] - a) - step / 2.0, 0.0) / a
    dy = np.maximum(np.abs(ql[:, 1] - b) - step / 2.0, 0.0) / b
    s = float(np.min(np.maximum(dx, dy)))
    return zoom / s if s > 0 else float("inf")


@lru_cache(maxsize=4)
def _inner_samples(w: int, h: int, step: int) -> tuple[slice, slice, np.ndarray]:
    """The rows and columns of :func:`.mapping.map_samples` inside a w x h output, and their output
    positions (gh, gw, 2), read-only and cached."""
    xs, ys = sample_positions(w, h, step)
    cols = np.flatnonzero((xs >= 0) & (xs <= w - 1))
    rows = np.flatnonzero((ys >= 0) & (ys <= h - 1))
    q = np.stack(np.meshgrid(xs[cols], ys[rows]), axis=-1)
    q.setflags(write=False)
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1), q


@lru_cache(maxsize=4)
def _edge_points(w: int, h: int, step: int) -> np.ndarray:
    """Output positions every ``step`` px along the four edges of a w x h output (corners included): (n, 2),
    read-only and cached."""
    xs = np.unique(np.append(np.arange(0, w, step, dtype=np.float64), w - 1))
    ys = np.unique(np.append(np.arange(0, h, step, dtype=np.float64), h - 1))
    out = np.concatenate([np.column_stack([xs, np.zeros_like(xs)]), np.column_stack([xs, np.full_like(xs, h - 1)]),
                          np.column_stack([np.zeros_like(ys), ys]), np.column_stack([np.full_like(ys, w - 1), ys])])
    out.setflags(write=False)
    return out

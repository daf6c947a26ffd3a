"""Rendering a :class:`MeshWarp` with one ``cv2.remap``: docs/method.md 5.2.

The map is the mesh's piecewise inverse bilinear map (:mod:`.inverse_bilinear`, docs/method.md
(13b)); output pixels with no source come out as ``border`` (BORDER_CONSTANT), and exactly
those the border fill needs are found around the samples that leave the source (:mod:`.uncovered`).

Speed: the map is evaluated at every ``step``-th pixel (plus one sample of
padding on each side, so no output pixel is extrapolated), upsampled with one
``cv2.resize`` (INTER_LINEAR), converted to fixed point and used by one remap.
Within a cell the inverse map is smooth; across an inner cell edge it is
continuous with a kink, which the interpolation smooths over one step.
Measured against the exact map (step 1) on 7scenes frames with 0.5-3 degree +
1-5 cm corrections: see docs/method.md section 5 for the numbers. The samples
are computed once per frame and zoom (:func:`map_samples`): the border fill's
zoom estimate and the render share them.
"""
from __future__ import annotations

import threading
from functools import lru_cache

import cv2
import numpy as np

from .inverse_bilinear import Workspace, apply_inverse, coefficients
from .uncovered import DepthAt, depth_lookup, uncovered_pixels
from .warp import MeshWarp

# Map values are clipped to +-_CLIP_FACTOR * max(W, H) (far outside the source
# either way) so the 16-bit fixed-point conversion never overflows.
_CLIP_FACTOR = 4


class _MapWorkspace(Workspace):
    """A :class:`.inverse_bilinear.Workspace` for one output size and map step, with the image-sized buffers."""

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


@lru_cache(maxsize=8)
def sample_positions(width: int, height: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Output x (nw,) and y (nh,) of the low-resolution samples, read-only and cached.

    Sample j sits at full-resolution position step * (j - 1) + (step - 1) / 2, so
    cv2.resize by exactly ``step`` puts output pixel x at upsampled column x + step.
    """
    xs = step * (np.arange(-(-width // step) + 2) - 1) + (step - 1) / 2.0
    ys = step * (np.arange(-(-height // step) + 2) - 1) + (step - 1) / 2.0
    for a in (xs, ys):
        a.setflags(write=False)
    return xs, ys


@lru_cache(maxsize=8)
def _samples(width: int, height: int, step: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Homogeneous low-resolution sample positions (3, K) and the low-res shape (nh, nw), cached."""
    xs, ys = sample_positions(width, height, step)
    gx, gy = np.meshgrid(xs, ys)
    P = np.vstack((gx.ravel(), gy.ravel(), np.ones(gx.size)))
    P.setflags(write=False)
    return P, (ys.size, xs.size)


def _lowres_map(mesh: MeshWarp, framing_scale: float, ws: _MapWorkspace) -> np.ndarray:
    """The inverse map at the low-resolution samples, (nh, nw, 2) float32 (a view of ``ws.low``)."""
    R, consts, rects = coefficients(mesh, framing_scale)
    x, y = apply_inverse(R, consts, rects, ws.P, ws)
    lim = _CLIP_FACTOR * max(mesh.width, mesh.height)
    nh, nw = ws.low.shape[:2]
    for v in (x, y):  # clipped in place (a contiguous workspace row), then interleaved
        np.minimum(v, lim, out=v)
        np.maximum(v, -lim, out=v)
    return cv2.merge((x.reshape(nh, nw), y.reshape(nh, nw)), ws.low)


def map_samples(mesh: MeshWarp, framing_scale: float = 1.0, step: int = 4) -> np.ndarray:
    """The inverse map at the renderer's low-resolution samples (nh, nw, 2) float32, sample j at output
    position step (j - 1) + (step - 1) / 2 (one sample of padding each side): what :func:`render`
    upsamples, computed once for the border fill's estimate and the render (``samples=``)."""
    gx, gy = mesh.grid
    return _lowres_map(mesh, framing_scale, _map_workspace(mesh.width, mesh.height, _step(step), gx * gy)).copy()


def rezoom_samples(samples: np.ndarray, width: int, height: int, zoom_from: float, zoom_to: float,
                   step: int = 4) -> np.ndarray | None:
    """:func:`map_samples` at ``zoom_to`` from those at ``zoom_from`` (<= ``zoom_to``), without the mesh:
    zooming in about the centre c shows at q what ``zoom_from`` showed at c + (q - c) zoom_from / zoom_to,
    a point inside the sample grid, read bilinearly from its 2 x 2 samples (float32, as the map is). The
    render upsamples the samples the same way, so this adds an error of the same kind (docs/method.md
    5.2); None when ``zoom_to`` < ``zoom_from`` (the points would leave the grid)."""
    r = float(zoom_from) / float(zoom_to)
    if not 0.0 < r <= 1.0:
        return None
    xs, ys = sample_positions(width, height, _step(step))

    def reads(pos: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
        u = (c + (pos - c) * r - pos[0]) / step  # fractional sample index, in [0, len - 1]
        i0 = np.clip(np.floor(u).astype(np.intp), 0, len(pos) - 2)
        return i0, (u - i0).astype(np.float32)

    def lerp(a: np.ndarray, i0: np.ndarray, f: np.ndarray, axis: int) -> np.ndarray:
        lo, hi = np.take(a, i0, axis=axis), np.take(a, i0 + 1, axis=axis)  # (np.take: 7x a fancy index here)
        hi -= lo
        hi *= f[:, None, None] if axis == 0 else f[None, :, None]
        hi += lo
        return hi

    ix, fx = reads(xs, (width - 1) / 2.0)
    iy, fy = reads(ys, (height - 1) / 2.0)
    return lerp(lerp(np.asarray(samples, np.float32), ix, fx, 1), iy, fy, 0)


def _step(step: int) -> int:
    if int(step) != step or step < 1:
        raise ValueError(f"map step must be an integer >= 1, got {step}")
    return int(step)


def _full_map(mesh: MeshWarp, framing_scale: float, step: int, samples: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, _MapWorkspace]:
    """Full-resolution inverse map as a view into this thread's workspace, the low-resolution samples
    it was upsampled from (``samples`` when given: :func:`map_samples` of the same mesh, zoom and
    step) and the workspace."""
    step = _step(step)
    w, h = mesh.width, mesh.height
    gx, gy = mesh.grid
    ws = _map_workspace(w, h, step, gx * gy)
    low = _lowres_map(mesh, framing_scale, ws) if samples is None else samples
    if step == 1:
        return low[1:h + 1, 1:w + 1], low, ws
    cv2.resize(low, ws.up.shape[1::-1], dst=ws.up, interpolation=cv2.INTER_LINEAR)
    return ws.up[step:step + h, step:step + w], low, ws


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
           step: int = 4, interpolation: int = cv2.INTER_LINEAR, out: np.ndarray | None = None,
           samples: np.ndarray | None = None) -> np.ndarray:
    """The stabilised frame: ``image`` warped by ``mesh`` and zoomed by ``framing_scale`` about the centre.

    ``image`` is any image of the mesh's size (BGR, grey, depth with INTER_NEAREST, ...);
    pixels with no source are ``border`` (black by default). ``out`` (same shape and
    type as ``image``) receives the result when given; ``samples``: :func:`map_samples` of the
    same mesh, zoom and step, when already computed.
    """
    _check_size(image, mesh)
    inv_map, _, ws = _full_map(mesh, framing_scale, step, samples)
    return _remap(image, inv_map, border, interpolation, out, ws)


def _check_size(image: np.ndarray, mesh: MeshWarp) -> None:
    if image.shape[:2] != (mesh.height, mesh.width):
        raise ValueError(f"image is {image.shape[1]}x{image.shape[0]} but the mesh is for "
                         f"{mesh.width}x{mesh.height}")


def render_covered(image: np.ndarray, depth: np.ndarray, mesh: MeshWarp, framing_scale: float = 1.0,
                   step: int = 4, samples: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray | None, DepthAt | None]:
    """:func:`render` (black border) plus what the border fill needs (docs/method.md 5.4): the output
    pixels with no source (bool (H, W), :func:`.uncovered.uncovered_pixels`) and ``depth`` rendered
    the same way (nearest; 0 where uncovered) at the pixels asked for (:func:`.uncovered.depth_lookup`,
    valid until the next render on this thread); both None when every pixel has a source."""
    _check_size(image, mesh)
    inv_map, low, ws = _full_map(mesh, framing_scale, step, samples)
    out = _remap(image, inv_map, 0, cv2.INTER_LINEAR, None, ws)
    uncovered = uncovered_pixels(low, inv_map, _step(step))
    if uncovered is None:
        return out, None, None
    return out, uncovered, depth_lookup(depth, inv_map)


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

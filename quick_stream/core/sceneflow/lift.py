"""The optical flow at a grid of pixels, lifted to 3D with both depth maps and masked (docs/method.md (1)).

Each mask shrinks the candidate set before the next, dearer one runs, so every step works on the
samples still in play only: the depth of frame t and its edges at the grid pixels, the forward
flow there (read from DIS's coarse field), the image border, the backward flow at the pixels the
forward flow reached, the Lucas-Kanade refinement, the depth of frame t+1 and the velocity outliers.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import cv2
import numpy as np

from ..frame import RGBDFrame
from ..robust import median
from .pairs import SceneFlowResult, quantized_flow
from .params import SceneFlowParams

Refine = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


def depth_edge_at(depth: np.ndarray, index: np.ndarray, neighbours: np.ndarray, rel: float) -> np.ndarray:
    """True where the pixel at flat ``index`` differs in depth from one of its 4-neighbours (flat indices
    ``neighbours``, (4, N)) by more than ``rel`` (relative).

    Only the requested pixels are tested (the full-image mask is never built).
    """
    flat = depth.ravel()
    d = flat[index]
    edge = np.zeros(index.shape, bool)
    for j in neighbours:
        n = flat[j]
        edge |= np.abs(n - d) > rel * np.minimum(n, d)
    return edge


def edge_threshold(depth: np.ndarray, index: np.ndarray, right: np.ndarray, p: SceneFlowParams) -> float:
    """The relative depth jump that marks a depth edge in this frame, docs/method.md (1b): ``depth_edge``, or
    ``depth_edge_k`` times the frame's relative depth noise where that is more. The noise is read at the
    candidate pixels (flat ``index``) against their right neighbours (``right``): 1.4826 x the median of
    |z_right - z| / z over sqrt(2) (two noisy pixels), the few true edges among them being outliers."""
    flat = depth.ravel()
    d, n = flat[index], flat[right]
    ok = (d > 0) & (n > 0)
    if np.count_nonzero(ok) < 16 or p.depth_edge_k <= 0:
        return p.depth_edge
    noise = 1.4826 * median(np.abs(n[ok] - d[ok]) / d[ok]) / np.sqrt(2.0)
    return max(p.depth_edge, p.depth_edge_k * float(noise))


def sample_depth(depth: np.ndarray, u: np.ndarray, v: np.ndarray, rel: float) -> np.ndarray:
    """Bilinear depth at sub-pixel (u, v) where the 4 neighbours are valid and agree within ``rel``.

    Returns 0 where the neighbours straddle a depth edge or an invalid pixel
    (docs/method.md (1): no blending across depth edges).
    """
    h, w = depth.shape
    u0 = np.minimum(np.maximum(np.floor(u).astype(np.intp), 0), w - 2)
    v0 = np.minimum(np.maximum(np.floor(v).astype(np.intp), 0), h - 2)
    a = u - u0
    b = v - v0
    flat = depth.ravel()
    i = v0 * w + u0
    d00 = flat[i]
    d01 = flat[i + 1]
    d10 = flat[i + w]
    d11 = flat[i + w + 1]
    dmin = np.minimum(np.minimum(d00, d01), np.minimum(d10, d11))
    dmax = np.maximum(np.maximum(d00, d01), np.maximum(d10, d11))
    ok = (dmin > 0) & (dmax - dmin <= rel * dmin)
    z = (1 - b) * ((1 - a) * d00 + a * d01) + b * ((1 - a) * d10 + a * d11)
    return np.where(ok, z, 0.0)


@dataclass(frozen=True)
class CandidateGrid:
    """Candidate pixels (u, v) on a regular grid, their flat indices ``v * w + u`` and those of their
    4-neighbours (4, N): right, left, down, up, the pixel itself across the image border."""

    u: np.ndarray
    v: np.ndarray
    index: np.ndarray
    neighbours: np.ndarray


@lru_cache(maxsize=8)
def candidate_grid(h: int, w: int, step: int) -> CandidateGrid:
    """The :class:`CandidateGrid` of every ``step``-th pixel of an ``h`` x ``w`` image, read-only and cached."""
    off = step // 2
    vv, uu = np.mgrid[off:h:step, off:w:step]
    uu, vv = uu.ravel(), vv.ravel()
    i = vv * w + uu
    nb = np.stack([np.where(uu < w - 1, i + 1, i), np.where(uu > 0, i - 1, i),
                   np.where(vv < h - 1, i + w, i), np.where(vv > 0, i - w, i)])
    for a in (uu, vv, i, nb):
        a.setflags(write=False)
    return CandidateGrid(uu, vv, i, nb)


def sample_flow(flow: np.ndarray, u: np.ndarray, v: np.ndarray, width: int,
                height: int) -> tuple[np.ndarray, np.ndarray]:
    """Flow (du, dv) of a ``width`` x ``height`` image at its sub-pixel positions (u, v), in its pixels,
    from a (H, W, 2) field computed on the image resized to W x H: bilinear at the field's position
    of each pixel centre (``(u + 0.5) W / width - 0.5``, edges replicated, as ``cv2.resize`` places
    them), scaled by ``width / W`` and ``height / H`` (DIS, resizing its own field, scales by 2**F:
    the same where the size is a multiple of 2**F)."""
    if u.size == 0:  # nothing survived the masks (e.g. no valid depth): cv2.remap refuses empty maps
        return np.zeros(0), np.zeros(0)
    sx, sy = flow.shape[1] / width, flow.shape[0] / height
    mx = ((u + 0.5) * sx - 0.5).astype(np.float32).reshape(1, -1)
    my = ((v + 0.5) * sy - 0.5).astype(np.float32).reshape(1, -1)
    out = cv2.remap(flow, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0].astype(np.float64)
    return out[:, 0] / sx, out[:, 1] / sy


def _inside(u: np.ndarray, v: np.ndarray, w: int, h: int, b: float) -> np.ndarray:
    """Whether (u, v) is at least ``b`` px inside a ``w`` x ``h`` image."""
    return (u >= b) & (u <= w - 1 - b) & (v >= b) & (v <= h - 1 - b)


def _evenly(sel: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` of the indices ``sel``, evenly spaced (all of them when there are no more)."""
    if sel.size <= n:
        return sel
    return sel[np.linspace(0, sel.size - 1, n).round().astype(np.intp)]


def lift_flow(f0: RGBDFrame, f1: RGBDFrame, fwd: np.ndarray, bwd: np.ndarray | None, p: SceneFlowParams,
              refine: Refine | None = None) -> SceneFlowResult:
    """Lift optical flow to 3D and apply the masks (docs/method.md (1)).

    ``fwd`` and ``bwd`` are the forward and backward flow fields (``bwd`` None: no
    forward-backward check), each computed on the images resized to its own size
    (:func:`sample_flow`). Candidates are pixels on a regular grid (about twice ``max_points`` of
    them); each mask shrinks the candidate set before the next, dearer one runs. ``refine``
    (u0, v0, u1, v1) -> (u1, v1, kept), e.g. :func:`~quick_stream.core.sceneflow.lk.refine_lk`,
    corrects the flow of the samples that passed the image masks (at most ``lk_budget`` x
    ``max_points`` of them, evenly spaced), before the second frame's depth is read.
    """
    h, w = f0.depth.shape
    counts: dict[str, int] = {}
    step = max(p.grid_step, int(np.sqrt(h * w / (2.0 * p.max_points))))
    grid = candidate_grid(h, w, step)
    counts["sampled"] = grid.u.size
    z0 = f0.depth.ravel()[grid.index]
    sel = np.flatnonzero((z0 >= p.min_depth) & (z0 <= p.max_depth))
    counts["invalid_depth"] = grid.u.size - sel.size
    rel = edge_threshold(f0.depth, grid.index[sel], grid.neighbours[0, sel], p) if p.depth_edge > 0 else 0.05
    if p.depth_edge > 0:
        edge = depth_edge_at(f0.depth, grid.index[sel], grid.neighbours[:, sel], rel)
        counts["depth_edge"] = int(np.count_nonzero(edge))
        sel = sel[~edge]
    uu, vv, z0 = grid.u[sel], grid.v[sel], z0[sel].astype(np.float64)
    du, dv = sample_flow(fwd, uu, vv, w, h)
    u1 = uu + du
    v1 = vv + dv
    ok = _inside(u1, v1, w, h, p.border_px)
    counts["out_of_image"] = int(ok.size - np.count_nonzero(ok))
    sel = np.flatnonzero(ok)
    if bwd is not None:
        bu, bv = sample_flow(bwd, u1[sel], v1[sel], w, h)
        ex, ey = du[sel] + bu, dv[sel] + bv
        lim2 = np.maximum(p.fb_threshold_px ** 2, (p.fb_rel * p.fb_rel) * (du[sel] ** 2 + dv[sel] ** 2))  # (1a)
        good = ex * ex + ey * ey <= lim2
        counts["fb_inconsistent"] = int(sel.size - np.count_nonzero(good))
        sel = sel[good]
    if refine is not None and p.lk_budget > 0:  # no more than the kept samples need (docs/method.md (1))
        n = sel.size
        sel = _evenly(sel, int(p.lk_budget * p.max_points))
        counts["lk_thinned"] = n - sel.size
    uu, vv, z0, u1, v1 = uu[sel], vv[sel], z0[sel], u1[sel], v1[sel]
    if refine is not None:
        u1, v1, kept = refine(uu, vv, u1, v1)
        kept &= _inside(u1, v1, w, h, p.border_px)
        counts["lk_rejected"] = int(kept.size - np.count_nonzero(kept))
        uu, vv, z0, u1, v1 = uu[kept], vv[kept], z0[kept], u1[kept], v1[kept]
    z1 = sample_depth(f1.depth, u1, v1, rel)
    sel = np.flatnonzero((z1 >= p.min_depth) & (z1 <= p.max_depth))
    counts["invalid_depth_next"] = int(z1.size - sel.size)
    K0, K1 = f0.intrinsics, f1.intrinsics
    if sel.size >= 3:  # the outlier test on the unquantized samples; the kept ones go on the wire
        sel = sel[_velocity_inliers(uu[sel], vv[sel], z0[sel], u1[sel], v1[sel], z1[sel], f0, f1, p, counts)]
    sel = _evenly(sel, p.max_points)
    counts["kept"] = int(sel.size)
    return quantized_flow(f0.seq, f1.seq, np.column_stack((uu[sel], vv[sel])), z0[sel],
                          np.column_stack((u1[sel], v1[sel])), z1[sel], K0, K1, counts)


def _velocity_inliers(u0: np.ndarray, v0: np.ndarray, z0: np.ndarray, u1: np.ndarray, v1: np.ndarray,
                      z1: np.ndarray, f0: RGBDFrame, f1: RGBDFrame, p: SceneFlowParams,
                      counts: dict[str, int]) -> np.ndarray:
    """Mask of the pairs whose speed |v| (docs/method.md (1)) is within ``outlier_k`` robust deviations
    (and ``outlier_floor_m``) of the median speed; counts the others as ``velocity_outlier``."""
    K0, K1 = f0.intrinsics, f1.intrinsics
    dx = (u1 - K1.cx) * (z1 / K1.fx) - (u0 - K0.cx) * (z0 / K0.fx)
    dy = (v1 - K1.cy) * (z1 / K1.fy) - (v0 - K0.cy) * (z0 / K0.fy)
    dz = z1 - z0
    speed = np.sqrt(dx * dx + dy * dy + dz * dz)
    dev = np.abs(speed - median(speed))
    good = dev <= max(p.outlier_k * (1.4826 * median(dev)), p.outlier_floor_m)
    counts["velocity_outlier"] = int(good.size - np.count_nonzero(good))
    return good

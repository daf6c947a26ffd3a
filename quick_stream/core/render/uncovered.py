"""The output pixels a render leaves without a source, found without full-resolution passes (docs/method.md 5.2).

The renderer's full-resolution map is its low-resolution samples upsampled bilinearly
(``cv2.resize``), so each output pixel's source position is a convex combination of the
positions of the (at most 2 x 2) samples around it. Where those all lie inside the source image
(by a margin far above float32 rounding), so does the pixel's: only the pixels near a sample
that does not need the exact test (:func:`uncovered_pixels`). Those are a band along the border,
usually a few thousand of the 307 200 pixels of a 640x480 frame, covered by a few thin
rectangles (:func:`patches`); the border fill works on the same rectangles and reads the output's
depth only where it needs it (:func:`depth_lookup`).
"""
from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

SAFE_MARGIN = 1e-2  # px: a sample this far inside the source keeps its pixels inside (rounding is ~1e-4 px)
PATCH_ROWS = 32  # output rows per strip of :func:`patches`
SAMPLE_ROWS = 16  # map sample rows (64 px at step 4) per strip when :func:`uncovered_pixels` cuts the samples
MERGE_GAP = 32  # columns: runs of marked columns closer than this share a patch
_LOOKUP_COLS = 4096  # cv2.remap takes maps under 32767 columns: lookups go in rows of this many points

# the output's depth at output pixels (ys, xs): index arrays (-> (N,)) or slices (-> (rows * cols,), row-major)
DepthAt = Callable[[np.ndarray | slice, np.ndarray | slice], np.ndarray]


def bounds(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """The bounding box ``(y0, y1, x0, x1)`` (ends excluded) of the True pixels of ``mask``, None when there is none."""
    words = _words(mask)
    rows = np.flatnonzero(words.any(axis=1))
    if rows.size == 0:
        return None
    marked = np.bitwise_or.reduce(words[rows[0]:rows[-1] + 1], axis=0)
    cols = np.flatnonzero(marked.view(bool)[:mask.shape[1]] if words is not mask else marked)
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _words(mask: np.ndarray) -> np.ndarray:
    """A bool mask's rows as 8-byte words (8 pixels a word: reductions 8x shorter), or the mask itself
    when its rows are not whole words."""
    if mask.flags.c_contiguous and mask.shape[1] % 8 == 0:
        return mask.view(np.uint64)
    return mask


def patches(mask: np.ndarray, margin: int, rows: int = PATCH_ROWS) -> list[tuple[int, int, int, int, int, int]]:
    """Rectangles around the True pixels of ``mask`` (H, W), each ``(t0, t1, a, b, c0, c1)``: rows
    ``t0:t1`` and the rectangle ``a:b, c0:c1`` around them, such that every pixel within ``margin``
    (in x and y) of a True pixel is in the rows ``t0:t1`` of exactly one rectangle, which also holds
    every True pixel that near it and the box between them (all within the image).

    One rectangle, the bounding box widened by ``margin``, when that is small (a band along one
    edge); otherwise the rows are cut into strips of ``rows``: per strip, ``t0:t1`` its rows within
    ``margin`` of a True pixel, ``a:b`` those widened by ``margin``, and ``c0:c1`` a run of columns
    holding True pixels in rows ``a:b`` widened by ``margin`` (runs further apart than
    ``max(2 margin + 1, MERGE_GAP)`` columns are separate rectangles). A band along several edges
    (what a render leaves uncovered) gives a few thin rectangles.
    """
    h, w = mask.shape
    box = bounds(mask)
    if box is None:
        return []
    a, b, c0, c1 = max(box[0] - margin, 0), min(box[1] + margin, h), max(box[2] - margin, 0), min(box[3] + margin, w)
    if (b - a) * (c1 - c0) <= h * w // 8 or b - a <= rows + 2 * margin:
        return [(a, b, a, b, c0, c1)]
    marked = np.flatnonzero(_words(mask).any(axis=1))
    gap = max(2 * margin + 1, MERGE_GAP)
    out = []
    for r0 in range(a // rows * rows, b, rows):
        r1 = min(r0 + rows, h)
        lo, hi = np.searchsorted(marked, (r0 - margin, r1 + margin)).tolist()  # True rows within margin of the strip
        if lo == hi:
            continue
        t0, t1 = max(r0, int(marked[lo]) - margin), min(r1, int(marked[hi - 1]) + margin + 1)
        ra, rb = max(t0 - margin, 0), min(t1 + margin, h)
        cols = np.flatnonzero(mask[ra:rb].any(axis=0))
        cut = np.flatnonzero(np.diff(cols) > gap)
        starts, ends = [cols[0], *cols[cut + 1].tolist()], [*cols[cut].tolist(), cols[-1]]
        out += [(t0, t1, ra, rb, max(int(s) - margin, 0), min(int(e) + 1 + margin, w)) for s, e in zip(starts, ends)]
    return out


def uncovered_pixels(samples: np.ndarray, inv_map: np.ndarray, step: int) -> np.ndarray | None:
    """Bool (H, W): the output pixels whose source position in ``inv_map`` (H, W, 2) lies outside the
    source image [0, W-1] x [0, H-1] (the complement of :func:`.mapping.valid_mask`, exactly), None
    when there is none. ``samples`` (nh, nw, 2): the low-resolution map ``inv_map`` was upsampled
    from, sample j (x or y) at output position step (j - 1) + (step - 1) / 2; only the pixels
    around the samples that are not safely inside are tested (:func:`patches` of them)."""
    h, w = inv_map.shape[:2]
    m = SAFE_MARGIN
    unsafe = cv2.inRange(samples, (m, m), (w - 1 - m, h - 1 - m)) == 0
    out = None
    for i0, i1, _, _, j0, j1 in patches(unsafe, 0, SAMPLE_ROWS):
        # pixel x reads the samples (x + step + 0.5) / step - 0.5 rounded down and the next one:
        # samples j0 ..< j1 are read by the pixels step (j0 - 2) ..< step j1
        ya, yb, xa, xb = max(step * (i0 - 2), 0), min(step * i1, h), max(step * (j0 - 2), 0), min(step * j1, w)
        if ya >= yb or xa >= xb:
            continue
        valid = cv2.inRange(inv_map[ya:yb, xa:xb], (0.0, 0.0), (w - 1.0, h - 1.0))
        if cv2.countNonZero(valid) < valid.size:
            out = np.zeros((h, w), bool) if out is None else out
            np.equal(valid, 0, out=out[ya:yb, xa:xb])  # exact wherever written: overlaps agree
    return out


def lookup(image: np.ndarray, points: np.ndarray, interpolation: int, border_mode: int = cv2.BORDER_CONSTANT
           ) -> np.ndarray:
    """``image`` sampled at ``points`` (N, 2) float32 source positions: (N,) or (N, channels), as
    ``cv2.remap`` samples each output pixel (any number of points: remap's maps must stay under
    32767 columns)."""
    n = len(points)
    if n == 0:
        return np.zeros((0, *image.shape[2:]), image.dtype)
    if n <= _LOOKUP_COLS:
        grid = np.ascontiguousarray(points, np.float32).reshape(1, n, 2)
    else:
        grid = np.empty((-(-n // _LOOKUP_COLS) * _LOOKUP_COLS, 2), np.float32)
        grid[:n] = points
        grid[n:] = 0.0
        grid = grid.reshape(-1, _LOOKUP_COLS, 2)
    out = cv2.remap(image, grid, None, interpolation, borderMode=border_mode, borderValue=0)
    return out.reshape(-1, *image.shape[2:])[:n]


def depth_lookup(depth: np.ndarray, inv_map: np.ndarray) -> DepthAt:
    """The output's depth as the renderer would draw ``depth`` with ``inv_map`` (nearest, 0 where no
    source), at the output pixels asked for only. Reads ``inv_map`` when called: a view of the
    render workspace stays valid until the next render on its thread."""
    pairs = inv_map.view(np.complex64)[..., 0]  # each (x, y) one 8-byte item: gathered in one copy

    def at(ys: np.ndarray | slice, xs: np.ndarray | slice) -> np.ndarray:
        return lookup(depth, pairs[ys, xs].reshape(-1).view(np.float32).reshape(-1, 2), cv2.INTER_NEAREST)
    return at

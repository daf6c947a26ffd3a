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


def _marked_rows(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The indices of the rows of a bool ``mask`` holding a True pixel, and the mask's rows as 8-byte
    words (8 pixels a word: reductions 8x shorter) or the mask itself when its rows are not whole words."""
    words = mask.view(np.uint64) if mask.flags.c_contiguous and mask.shape[1] % 8 == 0 else mask
    return np.flatnonzero(words.any(axis=1)), words


def _columns(words: np.ndarray, width: int) -> np.ndarray:
    """A row of ``_marked_rows``'s words (or of the mask) or-reduced: bool (width,), the columns marked."""
    return words.view(np.uint8).view(bool)[..., :width] if words.dtype == np.uint64 else words


def _box(rows: np.ndarray, words: np.ndarray, width: int) -> tuple[int, int, int, int] | None:
    """The bounding box ``(y0, y1, x0, x1)`` (ends excluded) of a mask's True pixels from its marked ``rows``
    and ``words`` (:func:`_marked_rows`), None when there is none."""
    if rows.size == 0:
        return None
    cols = np.flatnonzero(_columns(np.bitwise_or.reduce(words[rows[0]:rows[-1] + 1], axis=0), width))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


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
    (what a render leaves uncovered) gives a few thin rectangles. The strips are worked out together
    (one reduction over their rows, the runs from one pass over the strips' columns).
    """
    h, w = mask.shape
    marked, words = _marked_rows(mask)
    box = _box(marked, words, w)
    if box is None:
        return []
    a, b, c0, c1 = max(box[0] - margin, 0), min(box[1] + margin, h), max(box[2] - margin, 0), min(box[3] + margin, w)
    if (b - a) * (c1 - c0) <= h * w // 8 or b - a <= rows + 2 * margin:
        return [(a, b, a, b, c0, c1)]
    r0 = np.arange(a // rows * rows, b, rows)
    r1 = np.minimum(r0 + rows, h)
    lo, hi = np.searchsorted(marked, r0 - margin), np.searchsorted(marked, r1 + margin)  # True rows near each strip
    near = hi > lo
    r0, r1, lo, hi = r0[near], r1[near], lo[near], hi[near]
    t0 = np.maximum(r0, marked[lo] - margin)
    t1 = np.minimum(r1, marked[hi - 1] + margin + 1)
    ra, rb = np.maximum(t0 - margin, 0), np.minimum(t1 + margin, h)
    # the columns marked in rows ra:rb of each strip: one reduction over [ra0, rb0, ra1, rb1, ...], every other
    # result (the ranges may overlap); the strips whose rows reach the mask's end (the last few: rb never
    # falls from one strip to the next) are reduced to the end one by one
    inner = rb < h
    occ = [np.bitwise_or.reduceat(words, np.column_stack((ra[inner], rb[inner])).ravel(), axis=0)[0::2]]
    occ += [np.bitwise_or.reduce(words[x:], axis=0, keepdims=True) for x in ra[~inner].tolist()]
    occ = _columns(np.concatenate(occ) if len(occ) > 1 else occ[0], w)
    f = np.flatnonzero(occ)
    strip, col = np.divmod(f, occ.shape[1])
    first = np.ones(f.size, bool)  # a run starts at a strip's first marked column and after a wider gap
    first[1:] = (strip[1:] != strip[:-1]) | (np.diff(col) > max(2 * margin + 1, MERGE_GAP))
    starts = np.flatnonzero(first)
    ends = np.append(starts[1:] - 1, f.size - 1)
    i = strip[starts]
    return list(zip(t0[i].tolist(), t1[i].tolist(), ra[i].tolist(), rb[i].tolist(),
                    np.maximum(col[starts] - margin, 0).tolist(), np.minimum(col[ends] + 1 + margin, w).tolist()))


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

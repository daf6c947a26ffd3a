"""The compact layout of ``flow`` messages (format version 2; docs/wire-format.md, ``flow``).

A flow message held five float32 arrays per pair (points, displacements, weights, pixels,
pixels_next: 44 bytes a pair, 132 kB for 3000 pairs), most of it derivable: the sampled
pixels lie on the scene flow's regular grid, the weights are all 1, and points and
displacements follow from the pixels, the two depths and the intrinsics. The compact
layout carries what they follow from, and the decoder lifts them with the very function the
scene flow uses (:func:`quick_stream.core.sceneflow.lift_pairs`), so they come out bit for bit:

- ``grid``: the samples as bits of a regular grid (``x0``, ``y0``, ``step``, ``cols``, ``rows``,
  ``mask``: bit ``j * cols + i``, least significant first, is pixel (x0 + i step, y0 + j step)),
  in raster order;
- ``depth``: each sample's depth in frame t (metres, float32: the points' z);
- ``offset`` with ``offset_exp`` k: ``pixels_next = pixels + offset * 2^-k`` (int16 x 2);
- ``depth_change`` with ``depth_change_exp`` k': depth in frame t+1 ``= depth + depth_change * 2^-k'``;
- ``weights``: nil when every weight is 1.

The arrays are zstd frames of the byte-shuffled little-endian array, as zstd depth is. A flow
the layout does not reproduce exactly (samples off a grid, flow not in int16 fixed point, as
in a flow made by hand) is sent with the five float32 arrays of version 1 (``layout: "full"``).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import zstandard

from ...core.sceneflow import SceneFlowResult, lift_pairs
from .codec import Reader, byte_planes, encode_array, from_byte_planes

MAX_GRID_CELLS = 1 << 24  # grid cells a mask may cover (a 4096 x 4096 image sampled at every pixel)
MAX_EXP = 64  # |k| of the fixed-point steps 2^-k
_ZSTD_LEVEL = 3
_ZSTD_MAX_WINDOW = 1 << 27


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint8)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit for bit (``-0.0`` is not ``0.0``, NaN is itself)."""
    a, b = np.ascontiguousarray(a, np.float64), np.ascontiguousarray(b, np.float64)
    return a.shape == b.shape and bool(np.array_equal(_bits(a), _bits(b)))


def pack_array(a: np.ndarray, dtype: str) -> dict[str, Any]:
    """``{enc: "zstd", dtype, shape, data}``: a zstd frame of the byte-shuffled array."""
    d = encode_array(a, dtype)
    d["data"] = zstandard.ZstdCompressor(level=_ZSTD_LEVEL, write_content_size=True).compress(
        byte_planes(np.frombuffer(d["data"], dtype)))
    d["enc"] = "zstd"
    return d


def read_packed(r: Reader, name: str, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    """A :func:`pack_array` field of exactly ``shape``; every problem a WireError naming the field."""
    a = r.map(name)
    enc = a.str("enc")
    if enc != "zstd":
        raise a.error("enc", f"expected 'zstd', got {enc!r}")
    dt = a.str("dtype")
    if dt != dtype:
        raise a.error("dtype", f"expected dtype {dtype!r}, got {dt!r}")
    got = a.list("shape")
    if got != list(shape):
        raise a.error("shape", f"expected shape {list(shape)}, got {got!r}")
    size = np.dtype(dtype).itemsize
    want = math.prod(shape) * size
    data = a.bytes("data")
    try:
        params = zstandard.get_frame_parameters(data)
        if params.content_size != want:
            raise a.error("data", f"zstd content size {params.content_size} does not match dtype {dtype} x shape "
                                  f"{list(shape)} = {want} bytes")
        raw = zstandard.ZstdDecompressor(max_window_size=_ZSTD_MAX_WINDOW).decompress(data, max_output_size=want)
    except zstandard.ZstdError as e:
        raise a.error("data", f"zstd decompression failed: {e}") from None
    if len(raw) != want:
        raise a.error("data", f"decompressed {len(raw)} bytes, expected {want}")
    return from_byte_planes(raw, dtype, shape)


# --- encoding -----------------------------------------------------------------------------------

def _grid(pixels: np.ndarray) -> dict[str, Any] | None:
    """The grid bit mask of integer pixels in strictly increasing raster order; None if they are not."""
    n = len(pixels)
    if n == 0:
        return {"x0": 0, "y0": 0, "step": 1, "cols": 0, "rows": 0, "mask": b""}
    if not np.all(np.isfinite(pixels)) or not np.all(pixels == np.rint(pixels)) or pixels.min() < 0 \
            or pixels.max() >= 2**31:
        return None
    p = pixels.astype(np.int64)
    x0, y0 = int(p[:, 0].min()), int(p[:, 1].min())
    rel = p - (x0, y0)
    step = int(np.gcd.reduce(rel.ravel())) or 1
    cols, rows = int(rel[:, 0].max()) // step + 1, int(rel[:, 1].max()) // step + 1
    if cols * rows > MAX_GRID_CELLS:
        return None
    idx = (rel[:, 1] // step) * cols + rel[:, 0] // step
    if n > 1 and not np.all(np.diff(idx) > 0):
        return None
    bits = np.zeros(cols * rows, np.uint8)
    bits[idx] = 1
    return {"x0": x0, "y0": y0, "step": step, "cols": cols, "rows": rows,
            "mask": np.packbits(bits, bitorder="little").tobytes()}


def _fixed(values: np.ndarray) -> tuple[int, np.ndarray] | None:
    """(k, int16 q) with ``values == q * 2^-k`` exactly, for the smallest such k; None if none."""
    if values.size == 0:
        return 0, np.zeros(values.shape, np.int16)
    if not np.all(np.isfinite(values)):
        return None
    nz = values[values != 0]
    if nz.size == 0:
        return 0, np.zeros(values.shape, np.int16)
    # the fractional bits of each value: v = m 2^e with 53 mantissa bits, the lowest set one counts
    m, e = np.frexp(np.abs(nz))
    mant = (m * 2.0 ** 53).astype(np.int64)
    tz = np.log2(mant & -mant).astype(np.int64)
    k = max(int(np.max(53 - e - tz)), math.ceil(math.log2(float(np.max(np.abs(nz))) / 32767)))
    if not -MAX_EXP <= k <= MAX_EXP:
        return None
    q = values * 2.0 ** k
    if np.max(np.abs(q)) > 32767 or not np.all(q == np.rint(q)):
        return None
    return k, q.astype(np.int16)


def expand(pixels: np.ndarray, depth: np.ndarray, offset: np.ndarray, k: int, dz: np.ndarray, kd: int,
           K0, K1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, displacements, pixels_next) of the compact fields (the decoder's arithmetic)."""
    pixels_next = pixels + offset.astype(np.float64) * 2.0 ** -k
    depth_next = depth + dz.astype(np.float64) * 2.0 ** -kd
    points, displacements = lift_pairs(pixels, depth, pixels_next, depth_next, K0, K1)
    return points, displacements, pixels_next


def compact_fields(flow: SceneFlowResult) -> dict[str, Any] | None:
    """The compact layout's fields of ``flow`` when they give every array back bit for bit, else None."""
    grid = _grid(flow.pixels)
    if grid is None:
        return None
    pixels = flow.pixels.astype(np.float64)
    depth = flow.points[:, 2].astype(np.float64)
    if not _same(depth, depth.astype(np.float32)):
        return None
    off = _fixed(flow.pixels_next - pixels)
    dz = _fixed(flow.displacements[:, 2].astype(np.float64))
    if off is None or dz is None:
        return None
    (k, q), (kd, qd) = off, dz
    with np.errstate(all="ignore"):
        points, displacements, pixels_next = expand(pixels, depth, q, k, qd, kd, flow.intrinsics,
                                                    flow.intrinsics_next)
    weights = np.asarray(flow.weights, np.float64)
    ones = _same(weights, np.ones(len(weights)))
    if not (_same(points, flow.points) and _same(displacements, flow.displacements)
            and _same(pixels_next, flow.pixels_next)):
        return None
    if not ones and not _same(weights, weights.astype(np.float32)):
        return None
    n = len(flow.points)
    return {"n": n, "grid": grid, "depth": pack_array(depth, "<f4"), "offset": pack_array(q, "<i2"),
            "offset_exp": int(k), "depth_change": pack_array(qd, "<i2"), "depth_change_exp": int(kd),
            "weights": None if ones else pack_array(weights, "<f4")}


# --- decoding -----------------------------------------------------------------------------------

def _grid_pixels(r: Reader, n: int) -> np.ndarray:
    g = r.map("grid")
    x0, y0 = g.int("x0", min=0), g.int("y0", min=0)
    step, cols, rows = g.int("step", min=1), g.int("cols", min=0), g.int("rows", min=0)
    for name, v in (("x0", x0), ("y0", y0), ("step", step), ("cols", cols), ("rows", rows)):
        if v >= 2**31:
            raise g.error(name, f"must be < 2^31, got {v}")
    cells = cols * rows
    if cells > MAX_GRID_CELLS:
        raise g.error("cols", f"{cols} x {rows} grid cells exceed the limit {MAX_GRID_CELLS}")
    mask = g.bytes("mask")
    if len(mask) != (cells + 7) // 8:
        raise g.error("mask", f"{len(mask)} bytes for {cells} cells (expected {(cells + 7) // 8})")
    bits = np.unpackbits(np.frombuffer(mask, np.uint8), bitorder="little")
    if bits[cells:].any():
        raise g.error("mask", "bits set past the last cell")
    idx = np.flatnonzero(bits[:cells])
    if len(idx) != n:
        raise g.error("mask", f"{len(idx)} samples in the mask but n is {n}")
    px = np.empty((n, 2))
    px[:, 0] = x0 + (idx % max(cols, 1)) * step
    px[:, 1] = y0 + (idx // max(cols, 1)) * step
    if n and px.max() >= 2**31:
        raise g.error("step", "grid pixels beyond 2^31")
    return px


def _exp(r: Reader, name: str) -> int:
    k = r.int(name)
    if not -MAX_EXP <= k <= MAX_EXP:
        raise r.error(name, f"must be in [-{MAX_EXP}, {MAX_EXP}], got {k}")
    return k


def decode_compact(r: Reader, max_points: int, K0, K1) -> dict[str, np.ndarray]:
    """The five arrays of a compact ``flow`` message (WireError for anything malformed)."""
    n = r.int("n", min=0)
    if n > max_points:
        raise r.error("n", f"{n} pairs exceed the limit {max_points}")
    pixels = _grid_pixels(r, n)
    depth = read_packed(r, "depth", "<f4", (n,)).astype(np.float64)
    if not np.all(np.isfinite(depth)):
        raise r.error("depth", "non-finite value")
    offset = read_packed(r, "offset", "<i2", (n, 2))
    dz = read_packed(r, "depth_change", "<i2", (n,))
    k, kd = _exp(r, "offset_exp"), _exp(r, "depth_change_exp")
    weights = np.ones(n)
    if r.has("weights"):
        weights = read_packed(r, "weights", "<f4", (n,)).astype(np.float64)
        if not np.all(np.isfinite(weights)):
            raise r.error("weights", "non-finite value")
    with np.errstate(all="ignore"):
        points, displacements, pixels_next = expand(pixels, depth, offset, k, dz, kd, K0, K1)
    for name, a in (("points", points), ("displacements", displacements), ("pixels_next", pixels_next)):
        if not np.all(np.isfinite(a)):
            raise r.error(name, "non-finite value (the compact fields overflow float32)")
    return {"points": points, "displacements": displacements, "weights": weights, "pixels": pixels,
            "pixels_next": pixels_next}


__all__ = ["compact_fields", "decode_compact", "expand", "pack_array", "read_packed"]

"""Image and depth codecs of the wire format: colour as JPEG or raw, depth as raw or zstd-compressed
quantized ``uint16`` (docs/wire-format.md). Sizes are checked from headers before anything is decoded
(``MAX_IMAGE_SIDE`` and ``MAX_IMAGE_PIXELS``, a service's ``--max-frame-side`` and ``--max-frame-pixels``)."""
from __future__ import annotations

import math
import os
from typing import Any

import cv2
import numpy as np
import zstandard

from ...core.frame import dequantize_depth, quantize_depth
from .codec import (MAX_DEPTH_SCALE, MIN_DEPTH_SCALE, Reader, WireError, byte_planes, encode_array, from_byte_planes,
                    read_shape)

MAX_IMAGE_SIDE = 4096  # images larger in either dimension are refused from their header, before decoding
# Images with more pixels are refused from their header too: what a process holds for one frame grows with its
# pixels (measured in docs/wire-format.md), so this bounds a frame's memory.
MAX_PIXELS_ENV = "QUICK_STREAM_MAX_FRAME_PIXELS"  # also the default of every service's --max-frame-pixels


def _env_pixels(default: int) -> int:
    value = os.environ.get(MAX_PIXELS_ENV, "").strip()
    if not value:
        return default
    if not value.isdigit() or not 256 <= int(value) <= 16384**2:
        raise ValueError(f"${MAX_PIXELS_ENV} must be a pixel count in 256..{16384**2}, got {value!r}")
    return int(value)


MAX_IMAGE_PIXELS = _env_pixels(1920 * 1200)

_ZSTD_LEVEL = 1
_ZSTD_MAX_WINDOW = 1 << 27
# A check decompresses a depth stream up to this size whole (and hands it on, Reader.depth_raw), a
# larger one in 1 MiB pieces: a 16384x16384 map's check costs 1 MiB, not 512
KEEP_RAW_BYTES = 16 << 20


def set_max_image_side(side: int) -> None:
    """Change the largest image side this process accepts (a service's ``--max-frame-side``): a
    640x480 stream has no use for an 8192x8192 frame, whose decode alone costs ~200 MB."""
    global MAX_IMAGE_SIDE
    if not 16 <= int(side) <= 16384:
        raise ValueError(f"max frame side must be in 16..16384, got {side}")
    MAX_IMAGE_SIDE = int(side)


def set_max_image_pixels(pixels: int) -> None:
    """Change the most pixels an image may have in this process (a service's ``--max-frame-pixels``):
    the bound on what one frame costs in memory, whatever its shape within ``MAX_IMAGE_SIDE``."""
    global MAX_IMAGE_PIXELS
    if not 256 <= int(pixels) <= 16384**2:
        raise ValueError(f"max frame pixels must be in 256..{16384**2}, got {pixels}")
    MAX_IMAGE_PIXELS = int(pixels)


# --- images -----------------------------------------------------------------------------------

def encode_image(img: np.ndarray, encoding: str = "jpeg", quality: int = 90) -> dict[str, Any]:
    """Colour image (HxWx3 uint8 BGR) as ``{enc: jpeg|raw, shape, data[, quality, dtype]}``."""
    if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise WireError(f"colour must be HxWx3 uint8 BGR, got {getattr(img, 'shape', type(img))}", field="color")
    if encoding == "raw":
        d = encode_array(img, "|u1")
        d["enc"] = "raw"
        return d
    if encoding != "jpeg":
        raise WireError(f"colour encoding must be 'jpeg' or 'raw', got {encoding!r}", field="color.enc")
    if not 1 <= int(quality) <= 100:
        raise WireError(f"JPEG quality must be in [1, 100], got {quality}", field="color.quality")
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise WireError("JPEG encoding failed", field="color")
    return {"enc": "jpeg", "quality": int(quality), "shape": list(img.shape), "data": buf.tobytes()}


def decode_image(r: Reader, name: str) -> tuple[np.ndarray, str, np.ndarray | None]:
    """Decode a colour image field; returns (HxWx3 uint8 BGR, encoding, luma): a JPEG decodes as
    ``r.color`` asks (:data:`~.codec.COLOR_MODES`), luma being its own Y channel (HxW uint8) or None."""
    m = r.map(name)
    enc = m.str("enc")
    if enc == "raw":
        img = r.array(name, "|u1", 3, (3,), max_elems=3 * min(MAX_IMAGE_SIDE**2, MAX_IMAGE_PIXELS))
        _check_side(m, img.shape)
        return img, enc, None
    if enc != "jpeg":
        raise m.error("enc", f"unknown image encoding {enc!r} (expected 'jpeg' or 'raw')")
    shape = read_shape(m, 3)
    if shape[2] != 3:
        raise m.error("shape", f"expected H x W x 3, got {shape}")
    _check_side(m, shape)
    if "data" not in m.d and "ref" in m.d:
        ref = m.d["ref"]
        which = f"record {ref}" if type(ref) is int else "a record"
        raise m.error("data", f"missing: the recording stored this JPEG apart, as {which} of its Foxglove image "
                              "channel, and that record was not found (a damaged recording; docs/recording.md)")
    data = m.bytes("data")
    size = jpeg_size(data)
    if size is None:
        raise m.error("data", "not a JPEG image (no SOF header)")
    if size != (shape[1], shape[0]):
        raise m.error("data", f"JPEG is {size[0]}x{size[1]} but shape says {shape[1]}x{shape[0]}")
    if not r.pixels:
        return np.broadcast_to(np.uint8(0), shape), enc, None
    buf = np.frombuffer(data, np.uint8)
    want_bgr, want_luma = r.color != "luma", r.color != "bgr"
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR) if want_bgr else np.broadcast_to(np.uint8(0), shape)
        luma = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if want_luma else None
    except cv2.error as e:
        raise m.error("data", f"JPEG failed to decode: {e}") from None
    if img is None or img.shape != shape or want_luma and (luma is None or luma.shape != shape[:2]):
        raise m.error("data", "JPEG failed to decode")
    return img, enc, luma


def _check_side(r: Reader, shape: tuple[int, ...]) -> None:
    if not (0 < shape[0] <= MAX_IMAGE_SIDE and 0 < shape[1] <= MAX_IMAGE_SIDE):
        raise r.error("shape", f"image size {shape[1]}x{shape[0]} outside 1..{MAX_IMAGE_SIDE}")
    if shape[0] * shape[1] > MAX_IMAGE_PIXELS:
        raise r.error("shape", f"image size {shape[1]}x{shape[0]} has {shape[0] * shape[1]} pixels, above the "
                               f"limit of {MAX_IMAGE_PIXELS} (--max-frame-pixels, ${MAX_PIXELS_ENV})")


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's SOF marker, without decoding; None if not found."""
    if data[:2] != b"\xff\xd8":
        return None
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD9)):
            i += 2
            continue
        seglen = int.from_bytes(data[i + 2:i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > n:
                return None
            h = int.from_bytes(data[i + 5:i + 7], "big")
            w = int.from_bytes(data[i + 7:i + 9], "big")
            return w, h
        if seglen < 2:
            return None
        i += 2 + seglen
    return None


# --- depth ------------------------------------------------------------------------------------

def encode_depth(depth: np.ndarray, encoding: str = "raw", scale: float = 1000.0) -> dict[str, Any]:
    """Depth (metres) as ``{enc: raw|zstd, dtype <u2, shape, scale, data}``."""
    if not isinstance(depth, np.ndarray) or depth.ndim != 2:
        raise WireError(f"depth must be HxW, got {getattr(depth, 'shape', type(depth))}", field="depth")
    if not (math.isfinite(scale) and MIN_DEPTH_SCALE <= scale <= MAX_DEPTH_SCALE):
        raise WireError(f"depth scale must be in [{MIN_DEPTH_SCALE:g}, {MAX_DEPTH_SCALE:g}] units/m, got {scale}",
                        field="depth.scale")
    q = quantize_depth(depth, scale)
    d = encode_array(q, "<u2")
    if encoding == "zstd":
        d["data"] = zstandard.ZstdCompressor(level=_ZSTD_LEVEL, write_content_size=True).compress(
            byte_planes(q.astype("<u2", copy=False)))
    elif encoding != "raw":
        raise WireError(f"depth encoding must be 'raw' or 'zstd', got {encoding!r}", field="depth.enc")
    d.update(enc=encoding, scale=float(scale))
    return d


def decode_depth(r: Reader, name: str) -> tuple[np.ndarray, str, float]:
    """Decode a depth field; returns (HxW float32 metres, encoding, scale)."""
    m = r.map(name)
    enc = m.str("enc")
    scale = m.float("scale", positive=True)
    if not MIN_DEPTH_SCALE <= scale <= MAX_DEPTH_SCALE:
        raise m.error("scale", f"depth scale {scale:g} units/m is outside [{MIN_DEPTH_SCALE:g}, {MAX_DEPTH_SCALE:g}]")
    if enc == "raw":
        q = r.array(name, "<u2", 2, max_elems=min(MAX_IMAGE_SIDE**2, MAX_IMAGE_PIXELS))
        _check_side(m, q.shape)
        if not r.pixels:
            return np.broadcast_to(np.float32(0), q.shape), enc, scale
        return dequantize_depth(q, scale), enc, scale
    if enc != "zstd":
        raise m.error("enc", f"unknown depth encoding {enc!r} (expected 'raw' or 'zstd')")
    dt = m.str("dtype")
    if dt != "<u2":
        raise m.error("dtype", f"expected dtype '<u2', got {dt!r}")
    shape = read_shape(m, 2)
    _check_side(m, shape)
    data = m.bytes("data")
    want = shape[0] * shape[1] * 2
    try:
        params = zstandard.get_frame_parameters(data)
        if params.content_size != want:
            raise m.error("data", f"zstd content size {params.content_size} does not match "
                                  f"dtype <u2 x shape {shape} = {want} bytes")
        if not r.pixels:  # checked all the same (a damaged frame must not take a queue's slot)
            if not r.streams:  # an exact replay's recorded bytes: each receiver checks them
                return np.broadcast_to(np.float32(0), shape), enc, scale
            if want <= KEEP_RAW_BYTES:  # whole, kept for a decode of the same bytes (Reader.depth_raw)
                raw = _decompress(data, want)
                got = len(raw)
                r.depth_raw = raw if got == want else None
            else:  # in 1 MiB pieces
                got = _zstd_length(data)
            if got != want:
                raise m.error("data", f"decompressed {got} bytes, expected {want}")
            return np.broadcast_to(np.float32(0), shape), enc, scale
        raw = r.depth_raw if r.depth_raw is not None and len(r.depth_raw) == want else _decompress(data, want)
    except zstandard.ZstdError as e:
        raise m.error("data", f"zstd decompression failed: {e}") from None
    if len(raw) != want:
        raise m.error("data", f"decompressed {len(raw)} bytes, expected {want}")
    return dequantize_depth(from_byte_planes(raw, "<u2", shape), scale), enc, scale


def _decompress(data: bytes, want: int) -> bytes:
    """The zstd frame ``data`` decompressed whole (at most ``want`` bytes); ``ZstdError`` if it does not decompress."""
    return zstandard.ZstdDecompressor(max_window_size=_ZSTD_MAX_WINDOW).decompress(data, max_output_size=want)


def _zstd_length(data: bytes) -> int:
    """How many bytes the zstd frame ``data`` decompresses to, without holding them (1 MiB pieces: a
    check of a 16384x16384 depth map costs 1 MiB, not 512); ``ZstdError`` if it does not decompress."""
    n = 0
    for piece in zstandard.ZstdDecompressor(max_window_size=_ZSTD_MAX_WINDOW).read_to_iter(
            data, read_size=1 << 20, write_size=1 << 20):
        n += len(piece)
    return n

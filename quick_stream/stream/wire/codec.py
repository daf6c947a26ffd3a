"""Envelope, version check, errors and the array/image codecs of the msgpack wire format.

Every message is one msgpack map whose envelope is ``v`` (format version),
``type``, ``stream`` and ``seq`` (see docs/wire-format.md). Decoding never lets
anything but :class:`WireError` escape: :func:`unpack` bounds the input size and
msgpack's length limits before unpacking, and :class:`Reader` checks every field's
presence, msgpack type, finiteness and (for arrays) byte length against dtype x shape.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import msgpack
import numpy as np
import zstandard

from ...core.frame import dequantize_depth, quantize_depth  # noqa: F401 - re-exported

FORMAT_VERSION = 1  # the version of every message type but those in VERSIONS
VERSIONS = {"flow": 2}  # types whose newest version is another (flow 2: the compact layout)
MIN_DEPTH_SCALE, MAX_DEPTH_SCALE = 1.0, 1e6  # raw depth units per metre (mm = 1000, TUM = 5000)
MESSAGE_TYPES = ("frame", "flow", "motion", "correction", "stabilized", "stats", "end")
DEFAULT_MAX_BYTES = 64 * 1024 * 1024
MAX_IMAGE_SIDE = 4096  # images larger in either dimension are refused from their header, before decoding


def set_max_image_side(side: int) -> None:
    """Change the largest image side this process accepts (a service's ``--max-frame-side``): a
    640x480 stream has no use for an 8192x8192 frame, whose decode alone costs ~200 MB."""
    global MAX_IMAGE_SIDE
    if not 16 <= int(side) <= 16384:
        raise ValueError(f"max frame side must be in 16..16384, got {side}")
    MAX_IMAGE_SIDE = int(side)
MAX_LIST_LEN = 100_000  # msgpack arrays (lists); bulk data travels as bin, not lists
MAX_MAP_LEN = 10_000
MAX_STR_LEN = 1024 * 1024

_ZSTD_LEVEL = 1
_ZSTD_MAX_WINDOW = 1 << 27


class WireError(ValueError):
    """A message could not be encoded or decoded; the message names the problem.

    ``stream``, ``seq`` and ``field`` are set when known (``field`` is a dotted path
    such as ``depth.data``).
    """

    def __init__(self, problem: str, *, stream: str | None = None, seq: int | None = None,
                 field: str | None = None, type: str | None = None) -> None:
        self.problem, self.stream, self.seq, self.field, self.type = problem, stream, seq, field, type
        where = []
        if type is not None:
            where.append(f"type {type!r}")
        if stream is not None:
            where.append(f"stream {stream!r}")
        if seq is not None:
            where.append(f"seq {seq}")
        if field is not None:
            where.append(f"field {field!r}")
        super().__init__(f"wire: {problem}" + (f" [{', '.join(where)}]" if where else ""))


def version_of(type: str) -> int:
    """The newest format version of message ``type`` (docs/wire-format.md, Versioning)."""
    return VERSIONS.get(type, FORMAT_VERSION)


def pack(fields: dict[str, Any], type: str, stream: str, seq: int, version: int | None = None) -> bytes:
    """The message bytes: envelope plus ``fields`` (already msgpack-native values); ``version``
    (default the type's newest, :func:`version_of`) goes in ``v``."""
    if type not in MESSAGE_TYPES:
        raise WireError(f"unknown message type {type!r}", stream=stream, seq=seq)
    if not isinstance(stream, str) or not stream:
        raise WireError(f"stream id must be a non-empty str, got {stream!r}", seq=seq, field="stream")
    if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or seq < 0:
        raise WireError(f"seq must be an int >= 0, got {seq!r}", stream=stream, field="seq")
    msg = {"v": version_of(type) if version is None else int(version), "type": type, "stream": stream, "seq": int(seq)}
    msg.update(fields)
    return msgpack.packb(msg, use_bin_type=True)


def unpack(data: bytes, max_bytes: int = DEFAULT_MAX_BYTES) -> Reader:
    """Size-check, unpack and check the envelope; a :class:`Reader` over the whole map."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(f"expected bytes, got {type(data).__name__}")
    n = len(data)
    if n > max_bytes:
        raise WireError(f"message of {n} bytes exceeds max_bytes={max_bytes}")
    if n == 0:
        raise WireError("empty message (not msgpack)")
    try:
        unpacker = msgpack.Unpacker(
            raw=False, strict_map_key=True, use_list=True, max_buffer_size=max(n, 1),
            max_bin_len=max_bytes, max_str_len=min(MAX_STR_LEN, max_bytes),
            max_array_len=MAX_LIST_LEN, max_map_len=MAX_MAP_LEN, max_ext_len=0,
        )
        unpacker.feed(data)
        obj = unpacker.unpack()
    except msgpack.OutOfData:
        raise WireError(f"truncated message ({n} bytes end inside a msgpack object)") from None
    except Exception as e:  # noqa: BLE001 - FormatError, StackError, ValueError (limits), TypeError (unhashable key)...
        raise WireError(f"not valid msgpack: {type(e).__name__}: {e}") from None
    if unpacker.tell() != n:
        raise WireError(f"trailing bytes after the message ({n - unpacker.tell()} of {n})")
    if not isinstance(obj, dict):
        raise WireError(f"message is not a msgpack map but {type(obj).__name__}")
    stream = obj.get("stream") if isinstance(obj.get("stream"), str) else None
    seq = obj.get("seq") if _is_int(obj.get("seq")) else None
    mtype = obj.get("type") if isinstance(obj.get("type"), str) else None
    if "v" not in obj:
        raise WireError(f"missing format version (expected v={FORMAT_VERSION})",
                        stream=stream, seq=seq, field="v", type=mtype)
    v = obj["v"]
    newest = version_of(mtype) if mtype in MESSAGE_TYPES else FORMAT_VERSION
    if not _is_int(v) or not 1 <= v <= newest:
        expected = f"{FORMAT_VERSION}" if newest == FORMAT_VERSION else f"1 to {newest}"
        raise WireError(f"unsupported format version{f' of a {mtype!r} message' if newest != FORMAT_VERSION else ''}: "
                        f"expected {expected}, found {v!r}", stream=stream, seq=seq, field="v", type=mtype)
    r = Reader(obj, stream=stream, seq=seq, type=mtype, version=v)
    r.type = r.str("type")
    if r.type not in MESSAGE_TYPES:
        raise r.error("type", f"unknown message type {r.type!r} (known: {', '.join(MESSAGE_TYPES)})")
    r.stream = r.str("stream")
    r.seq = r.int("seq", min=0)
    return r


_ENVELOPE_BYTES = 256


def peek(data: bytes) -> tuple[str, int] | None:
    """The envelope ``(type, seq)`` of a message without unpacking the rest (the envelope is packed
    first, :func:`pack`); None if ``data`` does not start like one. For bookkeeping on arrival
    only: the message itself is still checked by :func:`decode` when it is used."""
    try:
        head = bytes(data[:_ENVELOPE_BYTES])  # v, type, stream (<= 64 chars) and seq fit in it
        u = msgpack.Unpacker(raw=False, max_buffer_size=_ENVELOPE_BYTES, max_bin_len=0, max_str_len=_ENVELOPE_BYTES,
                             max_array_len=0, max_map_len=0)
        u.feed(head)
        env = {}
        for _ in range(min(u.read_map_header(), 4)):
            k = u.unpack()
            env[k] = u.unpack()
    except Exception:  # noqa: BLE001 - anything malformed: not a message we can count
        return None
    seq, mtype = env.get("seq"), env.get("type")
    return (mtype, seq) if isinstance(mtype, str) and _is_int(seq) and seq >= 0 else None


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


_MISSING = object()


@dataclass
class Reader:
    """Typed access to one msgpack map; every failure is a :class:`WireError` naming the field."""

    d: dict
    stream: str | None = None
    seq: int | None = None
    prefix: str = ""
    type: str | None = None
    pixels: bool = True  # False: check every field, but leave images and depth maps undecoded (:func:`check`)
    version: int = FORMAT_VERSION  # the message's format version (``v``)

    def error(self, name: str, problem: str) -> WireError:
        return WireError(problem, stream=self.stream, seq=self.seq, field=self.prefix + name, type=self.type)

    def has(self, name: str) -> bool:
        return self.d.get(name) is not None

    def get(self, name: str, optional: bool = False) -> Any:
        val = self.d.get(name, _MISSING)
        if val is _MISSING or (val is None and not optional):
            if optional:
                return None
            raise self.error(name, "missing field" if val is _MISSING else "field is nil")
        return val

    def _typed(self, name: str, kinds: tuple, what: str, optional: bool) -> Any:
        val = self.get(name, optional)
        if val is None:
            return None
        if isinstance(val, bool) and bool not in kinds or not isinstance(val, kinds):
            raise self.error(name, f"expected {what}, got {type(val).__name__}")
        return val

    def int(self, name: str, min: int | None = None, optional: bool = False) -> int | None:
        val = self._typed(name, (int,), "int", optional)
        if val is not None and min is not None and val < min:
            raise self.error(name, f"must be >= {min}, got {val}")
        return val

    def float(self, name: str, finite: bool = True, positive: bool = False,
              optional: bool = False) -> float | None:
        val = self._typed(name, (int, float), "float", optional)
        if val is None:
            return None
        val = float(val)
        if finite and not math.isfinite(val):
            raise self.error(name, f"non-finite value {val}")
        if positive and not val > 0:
            raise self.error(name, f"must be > 0, got {val}")
        return val

    def bool(self, name: str) -> bool:
        return self._typed(name, (bool,), "bool", False)

    def str(self, name: str, optional: bool = False) -> str | None:
        return self._typed(name, (str,), "str", optional)

    def bytes(self, name: str) -> bytes:
        return self._typed(name, (bytes,), "bin", False)

    def list(self, name: str, optional: bool = False) -> list | None:
        return self._typed(name, (list,), "array", optional)

    def map(self, name: str, optional: bool = False) -> Reader | None:
        val = self._typed(name, (dict,), "map", optional)
        if val is None:
            return None
        return Reader(val, self.stream, self.seq, f"{self.prefix}{name}.", self.type, self.pixels, self.version)

    def floats(self, name: str, n: int | None = None, finite: bool = True,
               optional: bool = False) -> np.ndarray | None:
        """A msgpack array of numbers as float64 (length ``n`` if given)."""
        vals = self.list(name, optional)
        if vals is None:
            return None
        if n is not None and len(vals) != n:
            raise self.error(name, f"expected {n} numbers, got {len(vals)}")
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in vals):
            raise self.error(name, "expected an array of numbers")
        try:
            arr = np.array(vals, dtype=np.float64)
        except OverflowError:
            raise self.error(name, "number out of float64 range") from None
        if finite and not np.all(np.isfinite(arr)):
            raise self.error(name, "non-finite value")
        return arr

    def array(self, name: str, dtype: str, ndim: int, trailing: tuple[int, ...] = (),
              finite: bool = False, max_elems: int | None = None) -> np.ndarray:
        """A raw array ``{dtype, shape, data}``; dtype must be exactly ``dtype`` (e.g. ``<f4``)."""
        a = self.map(name)
        dt = a.str("dtype")
        if dt != dtype:
            raise a.error("dtype", f"expected dtype {dtype!r}, got {dt!r}")
        shape = _shape(a, ndim)
        if trailing and shape[ndim - len(trailing):] != trailing:
            raise a.error("shape", f"expected shape (..., {', '.join(map(str, trailing))}), got {shape}")
        count = math.prod(shape)
        if max_elems is not None and count > max_elems:
            raise a.error("shape", f"{count} elements exceed the limit {max_elems}")
        data = a.bytes("data")
        want = count * np.dtype(dtype).itemsize
        if len(data) != want:
            raise a.error("data", f"{len(data)} bytes do not match dtype {dtype} x shape {shape} = {want} bytes")
        arr = np.frombuffer(data, dtype=dtype).reshape(shape).copy()
        if finite and arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise a.error("data", "non-finite value")
        return arr


def _shape(r: Reader, ndim: int) -> tuple[int, ...]:
    shape = r.list("shape")
    if len(shape) != ndim or not all(_is_int(s) and 0 <= s < 2**31 for s in shape):
        raise r.error("shape", f"expected {ndim} ints in [0, 2^31), got {shape!r}")
    return tuple(shape)


def encode_array(arr: np.ndarray, dtype: str) -> dict[str, Any]:
    """``{dtype, shape, data}`` with the array cast to ``dtype`` (little-endian, C order)."""
    a = np.ascontiguousarray(np.asarray(arr), dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def float_list(name: str, values: Any, n: int | None = None) -> list[float]:
    """Encode a small float vector/matrix (row-major) as a msgpack array of float64; must be finite."""
    a = np.asarray(values, dtype=np.float64).ravel()
    if n is not None and a.size != n:
        raise WireError(f"expected {n} values, got {a.size}", field=name)
    if not np.all(np.isfinite(a)):
        raise WireError("non-finite value", field=name)
    return [float(x) for x in a]


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


def decode_image(r: Reader, name: str) -> tuple[np.ndarray, str]:
    """Decode a colour image field; returns (HxWx3 uint8 BGR, encoding)."""
    m = r.map(name)
    enc = m.str("enc")
    if enc == "raw":
        img = r.array(name, "|u1", 3, (3,), max_elems=3 * MAX_IMAGE_SIDE**2)
        _check_side(m, img.shape)
        return img, enc
    if enc != "jpeg":
        raise m.error("enc", f"unknown image encoding {enc!r} (expected 'jpeg' or 'raw')")
    shape = _shape(m, 3)
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
        return np.broadcast_to(np.uint8(0), shape), enc
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    except cv2.error as e:
        raise m.error("data", f"JPEG failed to decode: {e}") from None
    if img is None or img.shape != shape:
        raise m.error("data", "JPEG failed to decode")
    return img, enc


def _check_side(r: Reader, shape: tuple[int, ...]) -> None:
    if not (0 < shape[0] <= MAX_IMAGE_SIDE and 0 < shape[1] <= MAX_IMAGE_SIDE):
        raise r.error("shape", f"image size {shape[1]}x{shape[0]} outside 1..{MAX_IMAGE_SIDE}")


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
        shuffled = np.ascontiguousarray(q.astype("<u2").view(np.uint8).reshape(-1, 2).T).tobytes()
        d["data"] = zstandard.ZstdCompressor(level=_ZSTD_LEVEL, write_content_size=True).compress(shuffled)
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
        q = r.array(name, "<u2", 2, max_elems=MAX_IMAGE_SIDE**2)
        _check_side(m, q.shape)
        if not r.pixels:
            return np.broadcast_to(np.float32(0), q.shape), enc, scale
        return dequantize_depth(q, scale), enc, scale
    if enc != "zstd":
        raise m.error("enc", f"unknown depth encoding {enc!r} (expected 'raw' or 'zstd')")
    dt = m.str("dtype")
    if dt != "<u2":
        raise m.error("dtype", f"expected dtype '<u2', got {dt!r}")
    shape = _shape(m, 2)
    _check_side(m, shape)
    data = m.bytes("data")
    want = shape[0] * shape[1] * 2
    try:
        params = zstandard.get_frame_parameters(data)
        if params.content_size != want:
            raise m.error("data", f"zstd content size {params.content_size} does not match "
                                  f"dtype <u2 x shape {shape} = {want} bytes")
        if not r.pixels:
            return np.broadcast_to(np.float32(0), shape), enc, scale
        raw = zstandard.ZstdDecompressor(max_window_size=_ZSTD_MAX_WINDOW).decompress(data, max_output_size=want)
    except zstandard.ZstdError as e:
        raise m.error("data", f"zstd decompression failed: {e}") from None
    if len(raw) != want:
        raise m.error("data", f"decompressed {len(raw)} bytes, expected {want}")
    planes = np.frombuffer(raw, np.uint8).reshape(2, -1)
    q = np.empty((planes.shape[1], 2), np.uint8)
    q[:, 0], q[:, 1] = planes[0], planes[1]  # un-shuffle (a transposed copy is ~8x slower)
    q = q.view("<u2").reshape(shape)
    return dequantize_depth(q, scale), enc, scale

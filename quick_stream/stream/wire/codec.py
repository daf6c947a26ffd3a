"""Envelope, version check, errors and the array codec of the msgpack wire format (images and
depth: :mod:`.pixels`).

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

from ...core.frame import dequantize_depth, quantize_depth  # noqa: F401 - re-exported

FORMAT_VERSION = 1  # the version of every message type but those in VERSIONS
VERSIONS = {"flow": 2}  # types whose newest version is another (flow 2: the compact layout)
MIN_DEPTH_SCALE, MAX_DEPTH_SCALE = 1.0, 1e6  # raw depth units per metre (mm = 1000, TUM = 5000)
MESSAGE_TYPES = ("frame", "flow", "motion", "correction", "stabilized", "stats", "end")
DEFAULT_MAX_BYTES = 64 * 1024 * 1024


MAX_LIST_LEN = 100_000  # msgpack arrays (lists); bulk data travels as bin, not lists
MAX_SEQ_LIST = 10_000  # frame seqs one message names (the frames a flow stage shed; a flow spans at most 300)
MAX_MAP_LEN = 10_000
# What a frame's JPEG colour decodes to: "bgr" the colour only; "bgr+luma" the colour and the JPEG's
# own grey (its Y channel, RGBDFrame.luma, what the optical flow reads); "luma" the grey only, the
# colour left a zero-filled read-only view of its declared shape (the flow service's decode: the
# JPEG's grey alone costs about 60 % of its colour). A raw colour decodes to the colour and no luma
# in every mode.
COLOR_MODES = ("bgr", "bgr+luma", "luma")
MAX_STR_LEN = 1024 * 1024



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
    color: str = "bgr"  # what a JPEG colour image decodes to (:data:`COLOR_MODES`)
    # with pixels False: False leaves the compressed depth stream unchecked too (an exact replay's
    # capture sends recorded bytes, which every receiver checks; :func:`~.pixels.decode_depth`)
    streams: bool = True
    # the depth's decompressed zstd stream: set by a check (pixels False), which decompresses it whole
    # anyway; handed to a decode of the same bytes, it is not decompressed again (:mod:`.pixels`)
    depth_raw: bytes | None = None

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

    def seqs(self, name: str, below: int, optional: bool = True) -> tuple[int, ...]:
        """A msgpack array of frame seqs, each in [0, ``below``), at most :data:`MAX_SEQ_LIST` (the
        frames an ``end``, a flow or a correction names as shed); () when absent."""
        vals = self.list(name, optional)
        if vals is None:
            return ()
        if len(vals) > MAX_SEQ_LIST or not all(_is_int(x) and 0 <= x < below for x in vals):
            raise self.error(name, f"expected at most {MAX_SEQ_LIST} frame seqs in [0, {below}), got "
                             f"{vals[:5]!r}{'...' if len(vals) > 5 else ''} ({len(vals)} values)")
        return tuple(vals)

    def map(self, name: str, optional: bool = False) -> Reader | None:
        val = self._typed(name, (dict,), "map", optional)
        if val is None:
            return None
        return Reader(val, self.stream, self.seq, f"{self.prefix}{name}.", self.type, self.pixels, self.version,
                      self.color)

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
        shape = read_shape(a, ndim)
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


def read_shape(r: Reader, ndim: int) -> tuple[int, ...]:
    shape = r.list("shape")
    if len(shape) != ndim or not all(_is_int(s) and 0 <= s < 2**31 for s in shape):
        raise r.error("shape", f"expected {ndim} ints in [0, 2^31), got {shape!r}")
    return tuple(shape)


def encode_array(arr: np.ndarray, dtype: str) -> dict[str, Any]:
    """``{dtype, shape, data}`` with the array cast to ``dtype`` (little-endian, C order)."""
    a = np.ascontiguousarray(np.asarray(arr), dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def byte_planes(arr: np.ndarray) -> bytes:
    """The array's bytes (C order) regrouped by byte position: every element's first byte, then every
    second byte, ... (the "byte shuffle" before zstd: the high bytes of depth and of small values
    compress far better together). One ``cv2.split`` of the elements as channels (a transposed copy
    is 2-3x slower)."""
    a = np.ascontiguousarray(arr)
    size = a.dtype.itemsize
    if size == 1 or a.size == 0:
        return a.tobytes()
    return b"".join(cv2.split(a.view(np.uint8).reshape(-1, 1, size)))


def from_byte_planes(raw: bytes, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    """The array of ``dtype`` and ``shape`` whose :func:`byte_planes` are ``raw`` (exactly its size), a new
    writable array. One ``cv2.merge`` of the planes as channels (a transposed copy is 50x slower)."""
    dt = np.dtype(dtype)
    planes = np.frombuffer(raw, np.uint8).reshape(dt.itemsize, -1)
    if dt.itemsize == 1 or planes.shape[1] == 0:
        return planes.view(dt).reshape(shape).copy()
    return cv2.merge([p.reshape(-1, 1) for p in planes]).view(dt).reshape(shape)


def seq_list(name: str, seqs: Any, below: int, stream: str | None = None, seq: int | None = None) -> list[int] | None:
    """Frame seqs for the wire, each in [0, ``below``) (:meth:`Reader.seqs`); None when there are none
    (the field is then left out)."""
    out = [int(x) for x in seqs]
    if len(out) > MAX_SEQ_LIST or not all(0 <= x < below for x in out):
        raise WireError(f"expected at most {MAX_SEQ_LIST} frame seqs in [0, {below}), got {out[:5]} "
                        f"({len(out)} values)", field=name, stream=stream, seq=seq)
    return out or None


def float_list(name: str, values: Any, n: int | None = None) -> list[float]:
    """Encode a small float vector/matrix (row-major) as a msgpack array of float64; must be finite."""
    a = np.asarray(values, dtype=np.float64).ravel()
    if n is not None and a.size != n:
        raise WireError(f"expected {n} values, got {a.size}", field=name)
    if not np.all(np.isfinite(a)):
        raise WireError("non-finite value", field=name)
    return [float(x) for x in a]

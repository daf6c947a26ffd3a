"""Encode/decode of each wire message type (format version 1; docs/wire-format.md).

``encode_<type>(obj, stream, ...) -> bytes`` per type, :func:`encode` dispatching on
the object's class, and :func:`decode` returning a :class:`Decoded` (type, object,
envelope, wire-only extras). :func:`decode` raises only :class:`~.codec.WireError`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...core.frame import RGBDFrame
from ...core.motion import MotionEstimate
from ...core.path.planner import Correction
from ...core.sceneflow import SceneFlowResult
from . import ranges
from .codec import COLOR_MODES, DEFAULT_MAX_BYTES, Reader, WireError, float_list, pack, seq_list, unpack
from .estimates import (_decode_correction, _decode_flow, _decode_motion, encode_correction, encode_flow,
                        encode_motion)
from .fields import Decoded, intrinsics_fields, read_intrinsics, text
from .pixels import decode_depth, decode_image, encode_depth, encode_image


@dataclass
class StabilizedImage:
    """One rendered output frame: BGR uint8 image, the framing zoom used and any flags."""

    seq: int
    timestamp_ns: int
    image: np.ndarray
    zoom: float = 1.0
    flags: list[str] = field(default_factory=list)


@dataclass
class Stats:
    """Per-service health/stats: flat dict of numbers, strings, bools or nil."""

    service: str
    values: dict[str, Any] = field(default_factory=dict)


@dataclass
class EndOfStream:
    """The stream ended (source exhausted or stopped); ``seq`` is its last frame's seq (-1: none).

    Sent in order on the same key as the stage's data, so a receiver sees it after the
    last data message; each stage forwards it once it has flushed what it held."""

    seq: int
    reason: str = ""
    shed: tuple[int, ...] = ()  # frames after the last flow that the flow stage shed (docs/wire-format.md)


# --- frame --------------------------------------------------------------------------------------

def encode_frame(frame: RGBDFrame, stream: str, *, color: str = "jpeg", quality: int = 90,
                 depth: str = "raw", depth_scale: float = 1000.0, pub_ns: int | None = None) -> bytes:
    """An RGBDFrame as a ``frame`` message; colour ``jpeg``/``raw``, depth ``raw``/``zstd``;
    ``pub_ns``: wall-clock time the capture published it (latency accounting)."""
    f = {
        "pub_ns": None if pub_ns is None else int(pub_ns),
        "t_ns": int(frame.timestamp_ns),
        "intrinsics": intrinsics_fields(frame.intrinsics),
        "color": encode_image(frame.color, color, quality),
        "depth": encode_depth(frame.depth, depth, depth_scale),
        "pose": None if frame.pose is None else float_list("pose", frame.pose, 16),
        "origin": text("origin", frame.origin),
        "capture": _capture(frame.capture) if frame.capture else None,
    }
    return pack(f, "frame", stream, frame.seq)


_CAPTURE_TYPES = (int, float, str)


def _capture(meta: dict) -> dict:
    out = {}
    for k, v in meta.items():
        if isinstance(v, np.generic):
            v = v.item()
        if not isinstance(k, str) or isinstance(v, bool) or not isinstance(v, _CAPTURE_TYPES):
            raise WireError(f"capture metadata must be str -> int/float/str, got {k!r}: {type(v).__name__}",
                            field=f"capture.{k}")
        out[k] = v
    return out


def restamp_frame(data: bytes, stream: str, pub_ns: int, seq: int | None = None) -> bytes:
    """A recorded ``frame`` message re-addressed to ``stream`` with a new ``pub_ns`` (and ``seq``, if
    given); everything else (the compressed images included) byte for byte as recorded (exact replay)."""
    r = unpack(data)
    if r.type != "frame":
        raise r.error("type", f"expected a 'frame' message, got {r.type!r}")
    fields = {k: v for k, v in r.d.items() if k not in ("v", "type", "stream", "seq")}
    fields["pub_ns"] = int(pub_ns)
    return pack(fields, "frame", stream, r.seq if seq is None else seq)


def _decode_frame(r: Reader) -> Decoded:
    k = read_intrinsics(r, "intrinsics")
    t_ns = ranges.time_ns(r, "t_ns", r.int("t_ns"))
    color, cenc, luma = decode_image(r, "color")
    depth, denc, scale = decode_depth(r, "depth")
    if color.shape[:2] != (k.height, k.width):
        raise r.error("color", f"image is {color.shape[1]}x{color.shape[0]} but intrinsics say {k.width}x{k.height}")
    if depth.shape != (k.height, k.width):
        raise r.error("depth", f"depth is {depth.shape[1]}x{depth.shape[0]} but intrinsics say {k.width}x{k.height}")
    pose = r.floats("pose", 16, optional=True)
    pose = None if pose is None else ranges.transform(r, "pose", pose.reshape(4, 4), affine=False)
    capture = {}
    if r.has("capture"):
        cr = r.map("capture")
        for key_, v in cr.d.items():
            if not isinstance(key_, str) or isinstance(v, bool) or not isinstance(v, _CAPTURE_TYPES):
                raise cr.error(str(key_), f"expected int/float/str, got {type(v).__name__}")
            capture[key_] = v
    frame = RGBDFrame(color, depth, k, t_ns, r.seq, pose,
                      r.str("origin", optional=True) or "", capture=capture, luma=luma)
    return Decoded("frame", frame, r.stream, r.seq, color_encoding=cenc, depth_encoding=denc, depth_scale=scale,
                   pub_ns=ranges.time_ns(r, "pub_ns", r.int("pub_ns", optional=True)),
                   depth_raw=None if r.pixels else r.depth_raw)


# --- stabilized ---------------------------------------------------------------------------------

def encode_stabilized(s: StabilizedImage, stream: str, *, color: str = "jpeg", quality: int = 90,
                      src_pub_ns: int | None = None, ready_pub_ns: int | None = None,
                      image: dict[str, Any] | None = None) -> bytes:
    """A StabilizedImage as a ``stabilized`` message (image ``jpeg``/``raw``; ``image``: its image already
    encoded by :func:`encode_image`, which ``color`` and ``quality`` then do not change).

    Latency accounting (optional): ``src_pub_ns`` is when the capture published the source
    frame, ``ready_pub_ns`` when it published the frame that closed this frame's segment
    (so the wait for the segment is ready - src, and the processing is now - ready)."""
    if not (np.isfinite(s.zoom) and s.zoom > 0):
        raise WireError(f"zoom must be finite and > 0, got {s.zoom}", field="zoom", stream=stream, seq=s.seq)
    f = {"t_ns": int(s.timestamp_ns), "image": encode_image(s.image, color, quality) if image is None else image,
         "zoom": float(s.zoom),
         "flags": [text("flags", x) for x in s.flags],
         "src_pub_ns": None if src_pub_ns is None else int(src_pub_ns),
         "ready_pub_ns": None if ready_pub_ns is None else int(ready_pub_ns)}
    return pack(f, "stabilized", stream, s.seq)


def _decode_stabilized(r: Reader) -> Decoded:
    img, enc, _ = decode_image(r, "image")
    flags = r.list("flags")
    if not all(isinstance(x, str) for x in flags):
        raise r.error("flags", "expected an array of str")
    s = StabilizedImage(r.seq, ranges.time_ns(r, "t_ns", r.int("t_ns")), img,
                        ranges.zoom(r, "zoom", r.float("zoom", positive=True)), flags)
    src, ready = (ranges.time_ns(r, k, r.int(k, optional=True)) for k in ("src_pub_ns", "ready_pub_ns"))
    return Decoded("stabilized", s, r.stream, r.seq, encoding=enc, src_pub_ns=src, ready_pub_ns=ready)


# --- stats --------------------------------------------------------------------------------------

_STAT_TYPES = (int, float, str, bool, type(None))


def encode_stats(s: Stats, stream: str, seq: int) -> bytes:
    """A Stats as a ``stats`` message; ``seq`` counts this service's stats messages."""
    vals = {}
    for k, v in s.values.items():
        if isinstance(v, np.generic):
            v = v.item()
        if not isinstance(k, str) or not isinstance(v, _STAT_TYPES):
            raise WireError(f"stats values must be str -> number/str/bool/nil, got {k!r}: {type(v).__name__}",
                            field=f"values.{k}", stream=stream, seq=seq)
        vals[k] = v
    return pack({"service": text("service", s.service), "values": vals}, "stats", stream, seq)


def _decode_stats(r: Reader) -> Decoded:
    vr = r.map("values")
    for k, v in vr.d.items():
        if not isinstance(k, str) or not isinstance(v, _STAT_TYPES):
            raise vr.error(str(k), f"expected number/str/bool/nil, got {type(v).__name__}")
    return Decoded("stats", Stats(r.str("service"), dict(vr.d)), r.stream, r.seq)


# --- end of stream ------------------------------------------------------------------------------

def encode_end(e: EndOfStream, stream: str) -> bytes:
    """An EndOfStream as an ``end`` message (envelope seq = last frame's seq, 0 when none; ``shed``
    left out when there are none)."""
    f: dict[str, Any] = {"last_seq": int(e.seq), "reason": text("reason", e.reason)}
    if (named := seq_list("shed", e.shed, int(e.seq) + 1, stream, max(int(e.seq), 0))) is not None:
        f["shed"] = named
    return pack(f, "end", stream, max(int(e.seq), 0))


def _decode_end(r: Reader) -> Decoded:
    last = r.int("last_seq", min=-1)
    return Decoded("end", EndOfStream(last, r.str("reason"), r.seqs("shed", last + 1)), r.stream, r.seq)


# --- dispatch -----------------------------------------------------------------------------------

_DECODERS = {
    "frame": _decode_frame, "flow": _decode_flow, "motion": _decode_motion,
    "correction": _decode_correction, "stabilized": _decode_stabilized, "stats": _decode_stats,
    "end": _decode_end,
}


_ENCODERS = (
    (RGBDFrame, encode_frame), (SceneFlowResult, encode_flow), (MotionEstimate, encode_motion),
    (Correction, encode_correction), (StabilizedImage, encode_stabilized), (Stats, encode_stats),
    (EndOfStream, encode_end),
)


def encode(obj: Any, stream: str, **kw: Any) -> bytes:
    """Encode any message object (type from its class); ``kw`` goes to the per-type encoder."""
    for cls, encoder in _ENCODERS:
        if isinstance(obj, cls):
            return encoder(obj, stream, **kw)
    raise WireError(f"no wire message type for {type(obj).__name__}")


def decode(data: bytes, max_bytes: int = DEFAULT_MAX_BYTES, pixels: bool = True, color: str = "bgr",
           streams: bool = True, depth_raw: bytes | None = None) -> Decoded:
    """Decode one message; raises :class:`WireError` (and nothing else) for any malformed input.
    ``pixels=False`` checks every field the same way but leaves images and depth maps undecoded
    (zero-filled read-only views of the declared shape): :func:`check`; with ``streams=False`` too
    the depth's compressed stream is not decompressed to check it either (an exact replay's
    capture: the recorded bytes go out as they are, and every receiver checks them). ``color``: what
    a frame's JPEG colour decodes to, its BGR pixels and/or its own grey (:data:`~.codec.COLOR_MODES`;
    the scene flow reads the grey, so every decode that feeds it asks for it). ``depth_raw``: the
    depth's decompressed stream a check of these very bytes kept (:attr:`Decoded.depth_raw`), taken
    instead of decompressing it again."""
    if color not in COLOR_MODES:
        raise ValueError(f"color must be one of {COLOR_MODES}, got {color!r}")
    r = None
    try:
        r = unpack(data, max_bytes)
        r.pixels, r.color, r.streams, r.depth_raw = pixels, color, streams, depth_raw
        return _DECODERS[r.type](r)
    except WireError:
        raise
    except Exception as e:  # noqa: BLE001 - safety net: no other exception type may escape
        raise WireError(f"malformed message: {type(e).__name__}: {e}",
                        stream=getattr(r, "stream", None), seq=getattr(r, "seq", None)) from None


# Which message types each stage's key carries (an end marker closes any data stage's stream).
STAGE_TYPES = {"frame": ("frame", "end"), "flow": ("flow", "end"), "motion": ("motion", "end"),
               "correction": ("correction", "end"), "stabilized": ("stabilized", "end"), "stats": ("stats",)}


def check(data: bytes, stream: str | None = None, stage: str | None = None,
          max_bytes: int = DEFAULT_MAX_BYTES) -> Decoded:
    """Validate a message before any bookkeeping reads it (arrival ledgers, restart cursors, inbox
    skips): every field as :func:`decode` checks it, without decoding pixels (a frame costs ~0.1 ms),
    plus the envelope's ``stream`` and type against the key it came on. Raises :class:`WireError`
    naming the problem."""
    d = decode(data, max_bytes, pixels=False)
    if stream is not None and d.stream != stream:
        raise WireError(f"message of stream {d.stream!r} on the key of stream {stream!r}", stream=d.stream, seq=d.seq,
                        field="stream", type=d.type)
    if stage is not None and d.type not in STAGE_TYPES.get(stage, ()):
        raise WireError(f"{d.type} message on the {stage} key", stream=d.stream, seq=d.seq, field="type", type=d.type)
    return d

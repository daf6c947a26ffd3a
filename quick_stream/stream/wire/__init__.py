"""Versioned msgpack wire format of the quick-stream services (docs/wire-format.md).

>>> data = encode_frame(frame, "cam0", color="jpeg", depth="zstd")
>>> msg = decode(data)            # Decoded(type="frame", obj=RGBDFrame, stream, seq, extra)

Every decoding failure is a :class:`WireError` (a ``ValueError``) naming the problem and,
where known, the stream, seq and field.
"""
from .codec import (
    COLOR_MODES,
    DEFAULT_MAX_BYTES,
    FORMAT_VERSION,
    MESSAGE_TYPES,
    WireError,
    dequantize_depth,
    quantize_depth,
)
from .messages import (
    Decoded,
    EndOfStream,
    StabilizedImage,
    Stats,
    check,
    decode,
    encode,
    encode_correction,
    encode_end,
    encode_flow,
    encode_frame,
    encode_motion,
    encode_stabilized,
    encode_stats,
)
from .pixels import encode_image

__all__ = [
    "COLOR_MODES", "DEFAULT_MAX_BYTES", "FORMAT_VERSION", "MESSAGE_TYPES", "Decoded", "EndOfStream", "StabilizedImage",
    "Stats", "WireError", "check", "decode", "dequantize_depth", "encode", "encode_correction", "encode_end",
    "encode_flow", "encode_frame", "encode_image", "encode_motion", "encode_stabilized", "encode_stats",
    "quantize_depth",
]

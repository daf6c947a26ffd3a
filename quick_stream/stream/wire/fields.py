"""What the wire's message modules share: :class:`Decoded` (a decoded message) and the field helpers
(intrinsics, strings) of docs/wire-format.md."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ...core.frame import FrameError, Intrinsics
from ...core.release_tags import Tag
from . import ranges
from .codec import FORMAT_VERSION, Reader, WireError


@dataclass
class Decoded:
    """A decoded message: ``type``, the object, its envelope, and the fields of its message the object
    has no attribute for (docs/wire-format.md), each set by its type's decoder (the others keep
    their defaults): a ``frame``'s encodings, depth scale and ``pub_ns``; a ``flow``'s ``shed``; a
    ``correction``'s release ``tag``; a ``stabilized`` image's encoding and latency stamps.
    ``payload``: the message as received, kept by a service loop whose input decodes lazily."""

    type: str
    obj: Any
    stream: str
    seq: int
    version: int = FORMAT_VERSION
    color_encoding: str | None = None  # frame
    depth_encoding: str | None = None  # frame
    depth_scale: float | None = None  # frame: depth units per metre
    pub_ns: int | None = None  # frame: when the capture published it (None: not stamped)
    shed: tuple[int, ...] = ()  # flow: frames before this pair that the flow stage shed
    tag: Tag | None = None  # correction: its release tag (wire field ``batch``; None: a sender without tags)
    encoding: str | None = None  # stabilized: the image's encoding
    src_pub_ns: int | None = None  # stabilized: when its input frame was published
    ready_pub_ns: int | None = None  # stabilized: when the frame that made it renderable was published
    payload: bytes | None = None  # the message's bytes (a lazy input's frame, decoded when rendered)
    depth_raw: bytes | None = None  # frame, checked (pixels=False): its depth stream decompressed, for its decode


def intrinsics_fields(k: Intrinsics) -> dict[str, Any]:
    return {"fx": float(k.fx), "fy": float(k.fy), "cx": float(k.cx), "cy": float(k.cy),
            "width": int(k.width), "height": int(k.height)}


def read_intrinsics(r: Reader, name: str) -> Intrinsics:
    m = r.map(name)
    k = Intrinsics(m.float("fx", positive=True), m.float("fy", positive=True), m.float("cx"), m.float("cy"),
                   m.int("width", min=1), m.int("height", min=1))
    try:
        k.validate()
    except FrameError as e:
        raise r.error(name, str(e)) from None
    return ranges.intrinsics(r, name, k)


def text(name: str, s: Any) -> str:
    if not isinstance(s, str):
        raise WireError(f"expected str, got {type(s).__name__}", field=name)
    return s

"""What the wire's message modules share: :class:`Decoded` (a decoded message) and the field helpers
(intrinsics, strings) of docs/wire-format.md."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ...core.frame import FrameError, Intrinsics
from . import ranges
from .codec import FORMAT_VERSION, Reader, WireError


@dataclass
class Decoded:
    """A decoded message: ``type``, the object, its envelope and wire-only ``extra`` fields.

    ``extra`` holds what the object has no attribute for: ``zoom`` (correction),
    ``color_encoding``/``depth_encoding``/``depth_scale`` (frame), ``encoding`` (stabilized).
    """

    type: str
    obj: Any
    stream: str
    seq: int
    version: int = FORMAT_VERSION
    extra: dict[str, Any] = field(default_factory=dict)


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

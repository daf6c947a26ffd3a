"""RGB-D frame type shared by every source and stage.

One frame = colour (BGR uint8, HxWx3) + depth (metres, float32, HxW, 0 = invalid)
+ pinhole intrinsics + capture timestamp (ns) + sequence number. Sources that
cannot produce a usable frame yield a :class:`BadFrame` in its place, so a
stream keeps its sequence numbering and downstream stages can flag the gap
instead of crashing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np


class FrameError(ValueError):
    """A frame (or one of its fields) is unusable; the message names which."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """The 3x3 camera matrix."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]
        )

    def scaled(self, sx: float, sy: float | None = None) -> "Intrinsics":
        """Intrinsics of the same camera after resizing the image by (sx, sy)."""
        sy = sx if sy is None else sy
        return Intrinsics(
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            int(round(self.width * sx)),
            int(round(self.height * sy)),
        )

    def validate(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in vals):
            raise FrameError(f"intrinsics: non-finite value in {self}")
        if self.fx <= 0 or self.fy <= 0:
            raise FrameError(f"intrinsics: focal length must be > 0, got fx={self.fx} fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise FrameError(f"intrinsics: image size must be > 0, got {self.width}x{self.height}")


@dataclass
class RGBDFrame:
    """One RGB-D frame.

    ``pose`` is the ground-truth camera-to-world transform (4x4) when the source
    knows it, else None. ``origin`` names where the frame came from (a file, a
    device, ``synthetic``) so errors can point at it. ``notes`` lists non-fatal
    problems the source repaired (e.g. non-finite depth set to invalid). ``luma`` (HxW uint8):
    the colour's grey as its codec stored it (a JPEG's own Y channel), set by a decoder that
    decoded it; the optical flow reads it instead of converting ``color`` (:meth:`grey`).
    """

    color: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics
    timestamp_ns: int
    seq: int
    pose: np.ndarray | None = None
    origin: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)
    capture: dict[str, int | float | str] = field(default_factory=dict)
    luma: np.ndarray | None = None

    def grey(self) -> np.ndarray:
        """The grey image the optical flow reads (docs/method.md section 1): ``luma`` when the decoder
        gave it, else ``color`` converted (``cv2.COLOR_BGR2GRAY``)."""
        if self.luma is not None:
            return self.luma
        return cv2.cvtColor(self.color, cv2.COLOR_BGR2GRAY)

    @property
    def label(self) -> str:
        """Short human-readable name of this frame for error messages."""
        return frame_label(self.seq, self.origin)

    def validate(self) -> "RGBDFrame":
        """Check types, shapes and values; raise :class:`FrameError` naming the field.

        Non-finite or negative depth values are set to 0 (invalid) and recorded in
        ``notes``; a frame whose depth is entirely invalid is rejected, since no
        motion can be measured from it.
        """
        c, d = self.color, self.depth
        try:
            self.intrinsics.validate()
        except FrameError as e:
            raise FrameError(f"{self.label}: {e}") from None
        if not isinstance(c, np.ndarray) or c.dtype != np.uint8 or c.ndim != 3 or c.shape[2] != 3:
            raise FrameError(
                f"{self.label}: colour must be HxWx3 uint8 BGR, got "
                f"{getattr(c, 'shape', type(c))} {getattr(c, 'dtype', '')}"
            )
        lu = self.luma
        if lu is not None and not (isinstance(lu, np.ndarray) and lu.dtype == np.uint8 and lu.shape == c.shape[:2]):
            raise FrameError(f"{self.label}: luma must be {c.shape[0]}x{c.shape[1]} uint8 (the colour's size), got "
                             f"{getattr(lu, 'shape', type(lu))} {getattr(lu, 'dtype', '')}")
        if not isinstance(d, np.ndarray) or d.ndim != 2:
            raise FrameError(f"{self.label}: depth must be HxW, got {getattr(d, 'shape', type(d))}")
        if d.shape != c.shape[:2]:
            raise FrameError(
                f"{self.label}: depth size {d.shape[1]}x{d.shape[0]} does not match "
                f"colour size {c.shape[1]}x{c.shape[0]}"
            )
        if (self.intrinsics.width, self.intrinsics.height) != (c.shape[1], c.shape[0]):
            raise FrameError(
                f"{self.label}: intrinsics are for {self.intrinsics.width}x{self.intrinsics.height} "
                f"but the image is {c.shape[1]}x{c.shape[0]}"
            )
        if d.dtype != np.float32:
            if not np.issubdtype(d.dtype, np.floating):
                raise FrameError(f"{self.label}: depth must be float metres, got dtype {d.dtype}")
            d = d.astype(np.float32)
        lo, hi = (d.min(), d.max()) if d.size else (0.0, 0.0)
        if not (lo >= 0 and np.isfinite(hi)):  # some value is NaN (min and max are then NaN), inf or negative
            bad = ~np.isfinite(d) | (d < 0)
            nbad = int(np.count_nonzero(bad))
            d = np.where(bad, np.float32(0), d)
            self.notes = self.notes + (f"depth: {nbad} non-finite or negative values set to invalid",)
            hi = d.max() if d.size else 0.0
        self.depth = d
        if not hi > 0:
            raise FrameError(f"{self.label}: depth has no valid pixel (all zero or invalid)")
        return self

    def with_(self, **changes) -> "RGBDFrame":
        """A copy with ``changes``; a new ``color`` drops the old colour's ``luma`` unless given too."""
        if "color" in changes:
            changes.setdefault("luma", None)
        return replace(self, **changes)


@dataclass(frozen=True)
class BadFrame:
    """Placeholder for a frame a source could not deliver (unreadable file, bad data).

    It keeps the stream's sequence number and timestamp so downstream stages mark
    the motions touching it invalid instead of silently bridging the gap.
    """

    seq: int
    timestamp_ns: int
    origin: str
    error: str

    @property
    def label(self) -> str:
        return frame_label(self.seq, self.origin)


def frame_label(seq: int, origin: str) -> str:
    """A frame's short name in messages: ``frame SEQ (ORIGIN)``, the origin when known."""
    return f"frame {seq}" + (f" ({origin})" if origin else "")


def quantize_depth(depth: np.ndarray, scale: float = 1000.0) -> np.ndarray:
    """Metres -> uint16 units of 1/scale m: depth x scale (exact in float64 for float32 depth) rounded
    half to even; non-finite, <= 0 or out-of-range values become 0 (invalid)."""
    d = np.multiply(depth, scale, dtype=np.float64)
    # OpenCV's conversion rounds half to even (as np.rint) and saturates: -inf and anything rounding
    # below 0 give 0, as they must; what rounds above 65535 saturates and is zeroed below, and so is
    # NaN (OpenCV 4 cast it to 0, OpenCV 5.1 to 65535) (two thirds of the time of rint, a range mask
    # and a masked copy)
    if d.size == 0:
        return np.zeros(d.shape, np.uint16)
    out = cv2.multiply(d.reshape(1, -1), 1.0, dtype=cv2.CV_16U).reshape(d.shape)
    high = ~(d < 65535.5)  # rounds to 65536 or more (inf too), or NaN
    if high.any():
        out[high] = 0
    return out


def dequantize_depth(q: np.ndarray, scale: float = 1000.0) -> np.ndarray:
    """uint16 units -> float32 metres (0 stays 0 = invalid): one float32 division, into one new array."""
    out = np.empty(np.shape(q), np.float32)
    return np.divide(q, np.float32(scale), out=out, dtype=np.float32)

"""Border-free cropping: how much of a stabilised clip survives one static crop that removes every border.

``cropping`` (:mod:`quick_stream.quality.metrics`) measures the zoom of each output frame against its
input; a stabiliser that leaves black borders (no zoom) scores 1 there although a viewer still
sees the borders. This module measures the borders themselves, from the output frames alone:

Uncovered region. Per output frame, the near-black pixels (every channel <= ``level``) that are
connected (4-connectivity) to the frame's border: what a warp leaves where no input pixel
landed. A flood fill from the border, so dark scene content inside the frame (a black object, a
shadow not touching the border) is not counted.

Border-free scale. The largest rectangle centred on the frame centre, of the frame's aspect
ratio, that contains no uncovered pixel, as a fraction of the frame's size (1: no border). Pixel
(x, y) covers [x, x+1] x [y, y+1]; a rectangle of scale s spans W/2 +- s W/2 by H/2 +- s H/2,
so it excludes the pixel when s <= max(2 dx / W, 2 dy / H), with dx, dy the distances from the
centre to the pixel's nearer edges (0 for a pixel on a centre line). The frame's scale is the
minimum of that over its uncovered pixels; a black band of k columns on one side gives
1 - 2k / W.

Sequence. One static crop for the whole clip: the border-free scale of the sequence is the
minimum over its frames; ``border-free cropping`` = cropping x that scale (so a clip with no
border scores its cropping unchanged, and a failed sequence, whose cropping is 0, scores 0).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import cv2
import numpy as np

from ..core.render.framing import scale_from_mask

DEFAULT_LEVEL = 10  # like MetricParams.black_level: a pixel is near-black when every channel is <= this


def uncovered_mask(frame: np.ndarray, level: int = DEFAULT_LEVEL) -> np.ndarray:
    """Boolean (H, W) mask: near-black pixels (all channels <= ``level``) connected to the frame border."""
    if frame.ndim == 2:
        dark = frame <= level
    elif frame.ndim == 3:
        dark = np.all(frame <= level, axis=2)
    else:
        raise ValueError(f"expected an (H, W) or (H, W, C) image, got shape {frame.shape}")
    if not dark.any():
        return dark
    n, labels = cv2.connectedComponents(dark.astype(np.uint8), connectivity=4)
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    touching = np.unique(edge[edge > 0])
    if touching.size == 0:
        return np.zeros_like(dark)
    return np.isin(labels, touching)


def border_free_scale(frame: np.ndarray, level: int = DEFAULT_LEVEL) -> float:
    """Border-free scale of one output frame (module docstring)."""
    return scale_from_mask(uncovered_mask(frame, level))


def border_free_cropping(cropping: float, scale: float) -> float:
    """Cropping of the clip once its borders are cropped away by one static centred crop of ``scale``."""
    return float(cropping) * float(scale)


@dataclass
class BorderFreeAccumulator:
    """Streaming sequence value: ``add`` each output frame, then read ``scale`` (minimum over frames)."""

    level: int = DEFAULT_LEVEL
    scale: float = 1.0
    frames: int = 0
    frames_with_border: int = 0
    worst_frame: int = -1  # index of the frame that sets ``scale`` (-1: no border anywhere)

    def add(self, frame: np.ndarray) -> float:
        s = border_free_scale(frame, self.level)
        if s < 1.0:
            self.frames_with_border += 1
        if s < self.scale:
            self.scale, self.worst_frame = s, self.frames
        self.frames += 1
        return s

    def as_dict(self) -> dict:
        return {"border_free_scale": self.scale, "frames_with_border": self.frames_with_border,
                "border_worst_frame": self.worst_frame, "border_level": self.level}


def sequence_border_free_scale(frames: Iterable[np.ndarray], level: int = DEFAULT_LEVEL) -> float:
    """Minimum border-free scale over ``frames`` (one static crop that removes every border)."""
    acc = BorderFreeAccumulator(level)
    for f in frames:
        acc.add(f)
    return acc.scale

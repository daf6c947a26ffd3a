"""Border-free cropping: how much of a stabilised clip survives one static crop that removes every border.

``cropping`` (:mod:`quick_stream.quality.metrics`) measures the zoom of each output frame against its
input; a stabiliser that leaves black borders (no zoom) scores 1 there although a viewer still
sees the borders. This module measures the borders themselves, in the output frames:

Uncovered region. Per output frame, the near-black pixels (every channel <= ``level``) that are
connected (4-connectivity) to the frame's border: what a warp leaves where no input pixel
landed. A flood fill from the border, so dark scene content inside the frame (a black object, a
shadow not touching the border) is not counted.

Dark content at the border. A scene can itself be near-black where it meets the frame's edge (a
black monitor at the image edge: the unstabilised input of TUM fr1/rpy would score 0.07 by the
rule above). So only what the stabiliser left uncovered counts: a near-black output pixel is
uncovered only if the input frame does not show near-black content there. Given the input frame
and the output -> input homography H the metrics fitted for the frame
(``MetricsAccumulator.last_homography``: centred full-resolution coordinates, fitted from output
to input keypoints), the input's near-black mask is warped into the output by H (nearest
neighbour; output pixels that H maps outside the input are not content), dilated by ``margin``
px (default 3) for the error of the fitted H, and those pixels are taken out of the near-black
mask before the flood fill from the border. A border band next to dark content can so lose up to
``margin`` px along the content, and only there; elsewhere on the band its scale is exact. A frame
for which no homography could be fitted (too few matches, a degenerate fit, an output blacker
than the metrics' limit) keeps the plain rule above and is counted (``border_frames_unaligned``);
without an input frame (:func:`border_free_scale` on an output alone) the plain rule applies.

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
DEFAULT_MARGIN = 3  # px the input's dark content is grown by in the output, for the error of the fitted homography


def near_black(frame: np.ndarray, level: int = DEFAULT_LEVEL) -> np.ndarray:
    """Boolean (H, W) mask of the pixels whose every channel is <= ``level``."""
    if frame.ndim == 2:
        return frame <= level
    if frame.ndim == 3:
        return np.all(frame <= level, axis=2)
    raise ValueError(f"expected an (H, W) or (H, W, C) image, got shape {frame.shape}")


def content_mask(input_frame: np.ndarray, homography: np.ndarray, shape: tuple[int, ...],
                 level: int = DEFAULT_LEVEL, margin: int = DEFAULT_MARGIN) -> np.ndarray:
    """Boolean mask of the output (``shape``) pixels that show near-black content of ``input_frame``.

    ``homography`` maps output to input in centred coordinates (pixel index minus ((W-1)/2, (H-1)/2)
    of each image, as the metrics fit it); output pixels it maps outside the input are not content;
    the mask is dilated by ``margin`` px (module docstring).
    """
    dark = near_black(input_frame, level).astype(np.uint8)
    h_out, w_out = shape[:2]
    if not dark.any():
        return np.zeros((h_out, w_out), bool)
    h_in, w_in = dark.shape
    to_input = np.array([[1, 0, (w_in - 1) / 2], [0, 1, (h_in - 1) / 2], [0, 0, 1]], float)
    from_output = np.array([[1, 0, -(w_out - 1) / 2], [0, 1, -(h_out - 1) / 2], [0, 0, 1]], float)
    m = to_input @ np.asarray(homography, float) @ from_output  # output pixel -> input pixel
    warped = cv2.warpPerspective(dark, m, (w_out, h_out), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if margin > 0:
        warped = cv2.dilate(warped, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1)))
    return warped.astype(bool)


def uncovered_mask(frame: np.ndarray, level: int = DEFAULT_LEVEL, content: np.ndarray | None = None) -> np.ndarray:
    """Boolean (H, W) mask: near-black pixels (all channels <= ``level``) connected to the frame border,
    leaving out the pixels of ``content`` (dark scene content, :func:`content_mask`) before the flood fill."""
    dark = near_black(frame, level)
    if content is not None:
        dark &= ~content
    if not dark.any():
        return dark
    n, labels = cv2.connectedComponents(dark.astype(np.uint8), connectivity=4)
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    touching = np.unique(edge[edge > 0])
    if touching.size == 0:
        return np.zeros_like(dark)
    return np.isin(labels, touching)


def border_free_scale(frame: np.ndarray, level: int = DEFAULT_LEVEL, content: np.ndarray | None = None) -> float:
    """Border-free scale of one output frame (module docstring), ``content`` left out of the border."""
    return scale_from_mask(uncovered_mask(frame, level, content))


def border_free_cropping(cropping: float, scale: float) -> float:
    """Cropping of the clip once its borders are cropped away by one static centred crop of ``scale``."""
    return float(cropping) * float(scale)


@dataclass
class BorderFreeAccumulator:
    """Streaming sequence value: ``add`` each output frame (with its input frame and the metrics'
    output -> input homography when known), then read ``scale`` (minimum over frames)."""

    level: int = DEFAULT_LEVEL
    margin: int = DEFAULT_MARGIN
    scale: float = 1.0
    frames: int = 0
    frames_with_border: int = 0
    frames_unaligned: int = 0  # frames given an input but no homography: scored by the plain rule
    worst_frame: int = -1  # index of the frame that sets ``scale`` (-1: no border anywhere)

    def add(self, frame: np.ndarray, input_frame: np.ndarray | None = None,
            homography: np.ndarray | None = None) -> float:
        mask = uncovered_mask(frame, self.level)
        if input_frame is not None and homography is None:
            self.frames_unaligned += 1
        elif input_frame is not None and mask.any():
            content = content_mask(input_frame, homography, frame.shape, self.level, self.margin)
            mask = uncovered_mask(frame, self.level, content)
        s = scale_from_mask(mask)
        if s < 1.0:
            self.frames_with_border += 1
        if s < self.scale:
            self.scale, self.worst_frame = s, self.frames
        self.frames += 1
        return s

    def as_dict(self) -> dict:
        return {"border_free_scale": self.scale, "frames_with_border": self.frames_with_border,
                "border_worst_frame": self.worst_frame, "border_level": self.level,
                "border_margin_px": self.margin, "border_frames_unaligned": self.frames_unaligned}


def sequence_border_free_scale(frames: Iterable[np.ndarray], level: int = DEFAULT_LEVEL) -> float:
    """Minimum border-free scale over ``frames`` (one static crop that removes every border)."""
    acc = BorderFreeAccumulator(level)
    for f in frames:
        acc.add(f)
    return acc.scale

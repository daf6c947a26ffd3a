"""Each frame's grey images for the optical flow, made once per frame although a frame is in two pairs.

DIS computes its flow at the finest pyramid level of its preset (``F``: 2 for ultrafast, the image
reduced 4x with ``INTER_AREA``) and then resizes that flow to its input's size. Here each frame is
reduced once, DIS runs at ``F = 0`` on the reduced images (the same patches, bit for bit) and the
flow is read from the coarse field only where the scene flow needs it
(:func:`~quick_stream.core.sceneflow.lift.sample_flow`): DIS no longer reduces both images at every
pair nor resizes its result to full resolution. An image DIS would not treat that way (too small:
DIS then picks its scales itself) goes to DIS as it is (:func:`dis_input`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..frame import RGBDFrame
from .params import DIS_PRESETS, SceneFlowParams


@dataclass(frozen=True)
class DisInput:
    """A grey image as DIS is to get it, and the finest pyramid level DIS is to compute at on it."""

    image: np.ndarray
    finest: int


@dataclass(frozen=True)
class FrameImages:
    """One frame's grey images: ``grey`` at full resolution (Lucas-Kanade), ``dis`` and ``dis_fb`` the
    DIS inputs of the forward and backward flow (None without the backward check), ``contrast``
    the grey-level std at the flow scale."""

    grey: np.ndarray
    dis: DisInput
    dis_fb: DisInput | None
    contrast: float


class Dis:
    """A DIS optical flow of one preset, computing at each input's :class:`DisInput` level, its patches
    ``stride`` px apart (0: the preset's own)."""

    def __init__(self, preset: str, stride: int = 0) -> None:
        self._dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
        if stride:
            self._dis.setPatchStride(stride)
        self.finest = self._dis.getFinestScale()
        self.patch = self._dis.getPatchSize()

    def calc(self, i0: DisInput, i1: DisInput) -> np.ndarray:
        """The flow field from ``i0`` to ``i1`` (at ``i0.image``'s size)."""
        self._dis.setFinestScale(i0.finest)
        self._dis.setPatchSize(self.patch)  # DIS changes both when it picks its scales for a small image
        return self._dis.calc(i0.image, i1.image, None)

    def _coarsest(self, h: int, w: int) -> int:
        """DIS's coarsest pyramid level for an ``h`` x ``w`` input (its own formula)."""
        return min(int(math.log(max(h, w) / (4.0 * self.patch)) / math.log(2.0) + 0.5),
                   int(math.log(min(h, w) / self.patch) / math.log(2.0)))

    def dis_input(self, grey: np.ndarray) -> DisInput:
        """``grey`` reduced to the preset's finest level (``INTER_AREA``, size // 2**F, as DIS reduces it)
        when DIS then computes the same levels from it, else ``grey`` as it is at the preset's level."""
        h, w = grey.shape
        f = self.finest
        coarsest = self._coarsest(h, w)
        if f == 0 or coarsest < f or self._coarsest(h >> f, w >> f) != coarsest - f:
            return DisInput(grey, f)
        return DisInput(cv2.resize(grey, (w >> f, h >> f), interpolation=cv2.INTER_AREA), 0)


def _scaled(grey: np.ndarray, scale: float) -> np.ndarray:
    """``grey`` resized by ``scale`` (the flow scale, the backward check's scale)."""
    if scale == 1.0:
        return grey
    return cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


class ImageCache:
    """:class:`FrameImages` of the last two frames, keyed by seq; the colour array is kept with them
    so a hit is the very same image (identity, not a reused id)."""

    def __init__(self, params: SceneFlowParams, dis: Dis, dis_fb: Dis) -> None:
        self.params = params
        self.dis, self.dis_fb = dis, dis_fb
        self._cache: dict[int, tuple[np.ndarray, FrameImages]] = {}

    def get(self, frame: RGBDFrame) -> FrameImages:
        """``frame``'s images, made on its first use."""
        hit = self._cache.get(frame.seq)
        if hit is not None and hit[0] is frame.color:
            return hit[1]
        p = self.params
        grey = frame.grey()
        scale = p.flow_scale_for(*grey.shape)
        flow_grey = _scaled(grey, scale)
        fb = self.dis_fb.dis_input(_scaled(grey, p.fb_scale * scale)) if p.fb_check else None
        images = FrameImages(grey, self.dis.dis_input(flow_grey), fb, float(cv2.meanStdDev(flow_grey)[1][0, 0]))
        self._cache.pop(frame.seq, None)
        if len(self._cache) >= 2:
            del self._cache[next(iter(self._cache))]
        self._cache[frame.seq] = (frame.color, images)
        return images

""":class:`SceneFlow`: the scene flow of consecutive frames of one stream (docs/method.md (1))."""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from ..frame import RGBDFrame
from .images import Dis, ImageCache
from .lift import Refine, lift_flow
from .lk import refine_lk
from .pairs import SceneFlowResult
from .params import SceneFlowParams


class SceneFlow:
    """Computes :class:`~quick_stream.core.sceneflow.SceneFlowResult` for consecutive frames.

    Keeps the last two frames' grey images (:class:`~quick_stream.core.sceneflow.images.ImageCache`)
    so a stream makes each frame's once. Not thread-safe (one instance per stream).
    """

    def __init__(self, params: SceneFlowParams | None = None) -> None:
        self.params = params or SceneFlowParams()
        self.params.validate()
        self._loose = replace(self.params, refine="none", fb_threshold_px=self.params.loose_fb_px)
        self._dis = Dis(self.params.preset, self.params.dis_stride)
        self._dis_fb = Dis("ultrafast", self.params.dis_stride)
        self._images = ImageCache(self.params, self._dis, self._dis_fb)

    def optical_flow(self, f0: RGBDFrame, f1: RGBDFrame) -> tuple[np.ndarray, np.ndarray | None]:
        """Forward DIS flow field and, with fb_check, the backward one, each at its preset's finest pyramid
        level of the images at flow_scale (and fb_scale x flow_scale): what :func:`~.lift.lift_flow` reads."""
        i0, i1 = self._images.get(f0), self._images.get(f1)
        fwd = self._dis.calc(i0.dis, i1.dis)
        bwd = self._dis_fb.calc(i1.dis_fb, i0.dis_fb) if self.params.fb_check else None
        return fwd, bwd

    def compute(self, f0: RGBDFrame, f1: RGBDFrame) -> SceneFlowResult:
        """Scene flow from frame ``f0`` (time t) to ``f1`` (time t+1).

        A frame without enough image contrast for optical flow (black, saturated,
        blank) gives an empty result whose ``problem`` names it. A flow that keeps fewer than
        ``loose_below`` pairs is lifted again loose (docs/method.md (1c)); taken, its ``counts`` has
        ``loose`` 1.
        """
        for f in (f0, f1):
            std = self._images.get(f).contrast
            if std < self.params.min_contrast:
                return SceneFlowResult.empty(
                    f0, f1, f"{f.label}: too little image contrast for optical flow (grey std {std:.2f})"
                )
        fwd, bwd = self.optical_flow(f0, f1)
        flow = lift_flow(f0, f1, fwd, bwd, self.params, self.refiner(f0, f1))
        p = self.params
        if len(flow) < max(p.loose_below, p.loose_try_below):  # smeared by motion blur: the same fields, lifted loose (1c)
            loose = lift_flow(f0, f1, fwd, bwd, self._loose, self.textured(f0, f1))
            need = p.loose_below if len(flow) < p.loose_below else max(p.loose_below, p.loose_gain * len(flow))
            if len(loose) >= need:  # fewer than loose_below: too few for a fit, and loose ones stray
                loose.counts["loose"] = 1
                return loose
        return flow

    def textured(self, f0: RGBDFrame, f1: RGBDFrame) -> Refine:
        """The loose lift's sample test (docs/method.md (1c)): a sample is kept, where DIS put it, when the grey
        level's standard deviation over a ``lk_window`` square is at least ``loose_min_std`` around it in both
        frames (DIS fills a flat area with its neighbours' flow, which no test of the flow itself catches)."""
        w, t = self.params.lk_window, self.params.loose_min_std
        s0, s1 = local_std(self._images.get(f0).grey, w), local_std(self._images.get(f1).grey, w)
        h, wd = s0.shape

        def at(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
            return img[np.clip(np.rint(v).astype(np.intp), 0, h - 1), np.clip(np.rint(u).astype(np.intp), 0, wd - 1)]

        def keep(u0: np.ndarray, v0: np.ndarray, u1: np.ndarray, v1: np.ndarray):
            return u1, v1, (at(s0, u0, v0) >= t) & (at(s1, u1, v1) >= t)
        return keep

    def refiner(self, f0: RGBDFrame, f1: RGBDFrame) -> Refine | None:
        """The sample-flow refinement :func:`~.lift.lift_flow` takes for this pair (None when ``refine`` is "none")."""
        if self.params.refine != "lk":
            return None
        g0, g1 = self._images.get(f0).grey, self._images.get(f1).grey

        def refine(u0: np.ndarray, v0: np.ndarray, u1: np.ndarray, v1: np.ndarray):
            return refine_lk(g0, g1, u0, v0, u1, v1, self.params)
        return refine


def local_std(grey: np.ndarray, window: int) -> np.ndarray:
    """The grey level's standard deviation over the ``window`` x ``window`` square around each pixel."""
    g = grey.astype(np.float32)
    m = cv2.boxFilter(g, -1, (window, window))
    m2 = cv2.boxFilter(g * g, -1, (window, window))
    return np.sqrt(np.maximum(m2 - m * m, 0.0))

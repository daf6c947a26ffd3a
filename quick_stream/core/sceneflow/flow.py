""":class:`SceneFlow`: the scene flow of consecutive frames of one stream (docs/method.md (1))."""
from __future__ import annotations

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
        blank) gives an empty result whose ``problem`` names it.
        """
        for f in (f0, f1):
            std = self._images.get(f).contrast
            if std < self.params.min_contrast:
                return SceneFlowResult.empty(
                    f0, f1, f"{f.label}: too little image contrast for optical flow (grey std {std:.2f})"
                )
        fwd, bwd = self.optical_flow(f0, f1)
        return lift_flow(f0, f1, fwd, bwd, self.params, self.refiner(f0, f1))

    def refiner(self, f0: RGBDFrame, f1: RGBDFrame) -> Refine | None:
        """The sample-flow refinement :func:`~.lift.lift_flow` takes for this pair (None when ``refine`` is "none")."""
        if self.params.refine != "lk":
            return None
        g0, g1 = self._images.get(f0).grey, self._images.get(f1).grey

        def refine(u0: np.ndarray, v0: np.ndarray, u1: np.ndarray, v1: np.ndarray):
            return refine_lk(g0, g1, u0, v0, u1, v1, self.params)
        return refine

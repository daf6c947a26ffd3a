"""The scene flow's parameters (:class:`SceneFlowParams`) and the DIS presets it chooses from."""
from __future__ import annotations

from dataclasses import dataclass

import cv2

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
DIS_MIN_PATCH = 8  # px: the presets' patch size (8 for each, OpenCV 5.0)


@dataclass
class SceneFlowParams:
    """Parameters of :class:`~quick_stream.core.sceneflow.SceneFlow` (each one documented where it acts)."""

    preset: str = "ultrafast"  # DIS preset: ultrafast | fast | medium
    dis_stride: int = 6  # DIS patch stride (px, finest level), any preset; 0: the preset's own (4; medium 3)
    flow_scale: float = 1.0  # compute optical flow on images resized by this factor ...
    flow_max_side: int = 640  # ... or less, so that their longer side is at most this many px (0: no limit;
    # docs/method.md 1, "Resolution"): 1280x720 flows at 0.5
    fb_check: bool = True  # forward-backward consistency test (occlusions)
    fb_scale: float = 0.75  # backward flow (used only for the test) at this image scale (docs/method.md (1a))
    fb_threshold_px: float = 1.5  # max |f_fwd(p) + f_bwd(p + f_fwd)| in full-resolution px ...
    fb_rel: float = 0.05  # ... or this share of |f_fwd(p)| where that is more: fast motion (docs/method.md (1a))
    grid_step: int = 4  # sample at most every grid_step-th pixel in x and y ...
    max_points: int = 3000  # ... coarser if needed for ~2x this many candidates; keep at most this many
    min_depth: float = 0.1  # metres; depth outside [min_depth, max_depth] is invalid
    max_depth: float = 8.0
    depth_edge: float = 0.03  # relative depth jump to a 4-neighbour that marks a depth edge ...
    depth_edge_k: float = 4.0  # ... or this many times the frame's own relative depth noise where that is
    # more (noisy stereo depth would mark every pixel an edge; docs/method.md (1b))
    border_px: float = 2.0  # flow must land this far inside the image
    outlier_k: float = 6.0  # |v| outlier if | |v| - median| > outlier_k * 1.4826 * MAD
    outlier_floor_m: float = 0.01  # ... and more than this many metres from the median
    min_contrast: float = 2.0  # grey-level std below this (black, saturated, blank): no flow
    refine: str = "lk"  # "lk": refine each kept sample's flow with Lucas-Kanade started from DIS | "none"
    lk_window: int = 9  # LK window (px, odd)
    lk_iters: int = 10  # LK iterations at most (it starts from the DIS flow)
    lk_eps_px: float = 0.03  # LK stops once an iteration moves the sample less than this (px)
    lk_max_shift_px: float = 2.0  # LK moving a sample further than this from DIS: sample dropped
    lk_budget: float = 1.25  # LK refines at most lk_budget x max_points samples, evenly spaced (0: all)
    loose_below: int = 50  # a flow keeping fewer pairs than this (the motion's min_points) is lifted again loose:
    # no LK refinement and a forward-backward limit of loose_fb_px, kept when that gives this many (motion
    # blur: LK and the tight limit drop smeared samples; docs/method.md (1c)); 0: off
    loose_fb_px: float = 4.0
    loose_try_below: int = 400  # a flow keeping fewer pairs than this is also lifted loose, and the loose one taken
    loose_gain: float = 4.0  # ... when it keeps at least loose_gain x as many pairs (and loose_below): a few
    # LK-exact pairs against many DIS ones (docs/method.md (1c)); loose_try_below <= loose_below: only the starved
    loose_min_std: float = 3.0  # ... and only samples with this much grey-level std around them in both frames
    reach_over: int = 2  # a frame whose flow has fewer than reach_min_pairs pairs (smeared, blank) is reached
    # over: the next frames' flow starts from the frame before it, for at most this many frames (0: off;
    # docs/method.md 2.4, the flow stage's FlowStage)
    reach_min_pairs: int = 8  # ... fewer pairs than this: a flow the motion could fit nothing to (its min_rotation_points)
    reach_back_pairs: int = 50  # a flow with fewer pairs than this (the motion's min_points: below it only a
    # rotation-only fit) is held one frame: if the flow out of its frame starves, that frame is the smeared one
    # and the flow from the frame before it is tried, reaching over it (0: off; docs/method.md 2.4)

    def validate(self) -> None:
        if self.preset not in DIS_PRESETS:
            raise ValueError(f"sceneflow preset must be one of {sorted(DIS_PRESETS)}, got {self.preset!r}")
        if not self.depth_edge_k >= 0:
            raise ValueError(f"sceneflow depth_edge_k must be >= 0, got {self.depth_edge_k}")
        if not 0 <= self.fb_rel < 1:
            raise ValueError(f"sceneflow fb_rel must be in [0, 1), got {self.fb_rel}")
        for name in ("flow_scale", "fb_scale"):
            val = getattr(self, name)
            if not 0.1 <= val <= 1.0:
                raise ValueError(f"sceneflow {name} must be in [0.1, 1], got {val}")
        if not (isinstance(self.flow_max_side, int) and (self.flow_max_side == 0 or self.flow_max_side >= 64)):
            raise ValueError(f"sceneflow flow_max_side must be 0 (no limit) or an integer >= 64, got {self.flow_max_side!r}")
        if not 0 <= self.dis_stride <= DIS_MIN_PATCH:  # beyond its patch size, OpenCV's DIS reads out of bounds
            raise ValueError(f"sceneflow dis_stride must be in [1, {DIS_MIN_PATCH}] px (the patch size; 0: the "
                             f"preset's own), got {self.dis_stride}")
        if self.grid_step < 1 or self.max_points < 3:
            raise ValueError("sceneflow grid_step must be >= 1 and max_points >= 3")
        if self.refine not in ("lk", "none"):
            raise ValueError(f"sceneflow refine must be 'lk' or 'none', got {self.refine!r}")
        if self.lk_window < 3 or self.lk_window % 2 == 0 or self.lk_iters < 1 or not self.lk_max_shift_px > 0:
            raise ValueError("sceneflow lk_window must be odd >= 3, lk_iters >= 1 and lk_max_shift_px > 0")
        if self.reach_over < 0 or self.reach_min_pairs < 1 or self.reach_back_pairs < 0:
            raise ValueError(f"sceneflow reach_over and reach_back_pairs must be >= 0 and reach_min_pairs >= 1, got "
                             f"{self.reach_over}, {self.reach_back_pairs}, {self.reach_min_pairs}")
        if self.loose_try_below < 0 or not self.loose_gain >= 1:
            raise ValueError(f"sceneflow loose_try_below must be >= 0 and loose_gain >= 1, got "
                             f"{self.loose_try_below}, {self.loose_gain}")
        if self.loose_below < 0 or not self.loose_fb_px > 0 or not self.loose_min_std >= 0:
            raise ValueError(f"sceneflow loose_below must be >= 0, loose_fb_px > 0 and loose_min_std >= 0, got "
                             f"{self.loose_below}, {self.loose_fb_px}, {self.loose_min_std}")
        if not 0 < self.lk_eps_px <= 1:
            raise ValueError(f"sceneflow lk_eps_px must be in (0, 1] px, got {self.lk_eps_px}")

    def flow_scale_for(self, height: int, width: int) -> float:
        """The scale optical flow runs at on a ``height`` x ``width`` frame: ``flow_scale``, lowered so that
        the longer side comes to at most ``flow_max_side`` px (docs/method.md 1, "Resolution")."""
        side = max(height, width)
        if self.flow_max_side and side * self.flow_scale > self.flow_max_side:
            return self.flow_max_side / side
        return self.flow_scale

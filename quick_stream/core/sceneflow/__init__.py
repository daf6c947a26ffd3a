"""Dense scene flow: DIS optical flow lifted to 3D with both depth maps.

docs/method.md section 1. For frames t and t+1 with depths Z_t, Z_{t+1} and
intrinsics K_t, K_{t+1}, each sampled pixel p of frame t with flow f(p) gives

    x  = K_t^-1 [p, 1] Z_t(p)                       (the point, camera-t coordinates)
    x' = K_{t+1}^-1 [p + f, 1] Z_{t+1}(p + f)       (the same point, camera-(t+1) coordinates)
    v  = x' - x                                     (its displacement)

Masks: invalid or out-of-range depth in either frame, pixels on depth edges
(depth is often misregistered to colour there), flow leaving the image,
forward-backward inconsistent flow (occlusions) and unnaturally large
velocities (robustly, relative to the median: the paper's only filter).
Depth at the sub-pixel position p + f is interpolated bilinearly only where its
four neighbours agree, never blended across a depth edge.

The result keeps the pixel positions as well as the 3D pairs, so the motion
estimator can weigh image-plane and depth errors separately.

Modules: ``params`` (:class:`SceneFlowParams`), ``flow`` (:class:`SceneFlow`, one per stream),
``images`` (each frame's grey images, made once), ``lift`` (sampling, masks, the lift),
``lk`` (the Lucas-Kanade refinement), ``pairs`` (:class:`SceneFlowResult` and the wire's
quantization, :func:`quantized_flow`, :func:`lift_pairs`).
"""
from .flow import SceneFlow
from .lift import lift_flow, sample_depth
from .pairs import SceneFlowResult, lift_pairs, quantized_flow
from .params import DIS_PRESETS, SceneFlowParams

__all__ = [
    "DIS_PRESETS", "SceneFlow", "SceneFlowParams", "SceneFlowResult", "lift_flow", "lift_pairs",
    "quantized_flow", "sample_depth",
]

"""Lucas-Kanade refinement of the sampled flow, started from DIS (docs/method.md (1))."""
from __future__ import annotations

import cv2
import numpy as np

from .params import SceneFlowParams


def refine_lk(g0: np.ndarray, g1: np.ndarray, u0: np.ndarray, v0: np.ndarray, u1: np.ndarray, v1: np.ndarray,
              p: SceneFlowParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lucas-Kanade refinement of sample flows started from DIS (docs/method.md (1)).

    DIS interpolates its flow from overlapping patches at a coarse scale, which leaves
    errors correlated across the image (they do not average out over the samples); a
    few LK iterations per sample at full resolution, started from the DIS estimate,
    remove most of them. Returns the refined (u1, v1) and a mask of samples LK kept: it
    converged and moved the sample at most ``lk_max_shift_px`` from DIS.
    """
    if u0.size == 0:
        return u1, v1, np.ones(0, bool)
    p0 = np.empty((u0.size, 1, 2), np.float32)
    p0[:, 0, 0], p0[:, 0, 1] = u0, v0
    p1 = np.empty_like(p0)
    p1[:, 0, 0], p1[:, 0, 1] = u1, v1
    out, st, _ = cv2.calcOpticalFlowPyrLK(
        g0, g1, p0, p1, winSize=(p.lk_window, p.lk_window), maxLevel=0, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, p.lk_iters, p.lk_eps_px))
    ur = out[:, 0, 0].astype(np.float64)
    vr = out[:, 0, 1].astype(np.float64)
    ok = st[:, 0].astype(bool) & np.isfinite(ur) & np.isfinite(vr)
    du, dv = ur - u1, vr - v1
    ok &= du * du + dv * dv <= p.lk_max_shift_px ** 2
    return np.where(ok, ur, u1), np.where(ok, vr, v1), ok

"""The textbook 2D stabiliser: LK feature tracks, a rigid 2D trajectory, a centred moving average.

The method of Nghia Ho's "simple video stabilization using OpenCV" as most tutorials teach it,
kept deliberately plain as a known reference point for the quality benchmark:

1. per consecutive pair (i-1, i): ``cv2.goodFeaturesToTrack`` on frame i-1 (200 corners,
   quality 0.01, min distance 30 px, block 3), tracked into frame i with
   ``cv2.calcOpticalFlowPyrLK``; the tracked pairs give ``cv2.estimateAffinePartial2D``
   (rotation, uniform scale, translation; RANSAC), reduced to (dx, dy, da) with
   da = atan2(a10, a00). A pair that cannot be fitted repeats the previous pair's motion
   (zero for the first);
2. trajectory T_i = sum of the motions up to frame i (T_0 = 0), per component;
3. smoothed S = centred moving average of T over 2 * radius + 1 frames (radius 15), the ends
   padded by repeating the first / last value;
4. frame i is warped (``cv2.warpAffine``, bilinear, black border) by the rotation-plus-translation
   (S_i - T_i) about the image origin, as the motions were estimated. No zoom: the borders stay
   black (the benchmark's border-free cropping column charges them).

Offline: the centred average needs ``radius`` future frames, so the whole clip is processed at
once (:func:`stabilize`). Every input frame gives exactly one output frame, in order.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class LKParams:
    radius: int = 15  # moving average over 2 * radius + 1 frames
    max_corners: int = 200
    quality: float = 0.01
    min_distance: float = 30.0
    block_size: int = 3


def pair_motion(prev_grey: np.ndarray, grey: np.ndarray, p: LKParams | None = None) -> tuple[float, float, float] | None:
    """(dx, dy, da) of the partial affine map from ``prev_grey`` to ``grey`` (None when it cannot be fitted)."""
    p = p or LKParams()
    pts = cv2.goodFeaturesToTrack(prev_grey, p.max_corners, p.quality, p.min_distance, blockSize=p.block_size)
    if pts is None or len(pts) < 3:
        return None
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(prev_grey, grey, pts, None)
    ok = status.reshape(-1) == 1
    if ok.sum() < 3:
        return None
    m, _ = cv2.estimateAffinePartial2D(pts[ok], nxt[ok])
    if m is None or not np.all(np.isfinite(m)):
        return None
    return float(m[0, 2]), float(m[1, 2]), math.atan2(m[1, 0], m[0, 0])


def moving_average(curve: np.ndarray, radius: int) -> np.ndarray:
    """Centred box average over 2 * radius + 1 samples, ends padded with the end values."""
    if radius <= 0:
        return curve.astype(float).copy()
    padded = np.pad(curve.astype(float), (radius, radius), mode="edge")
    kernel = np.ones(2 * radius + 1) / (2 * radius + 1)
    return np.convolve(padded, kernel, mode="valid")


def corrections(frames: list[np.ndarray], p: LKParams | None = None) -> np.ndarray:
    """(N, 3) per-frame correction (dx, dy, da) = smoothed trajectory - trajectory."""
    p = p or LKParams()
    n = len(frames)
    motions = np.zeros((max(n - 1, 0), 3))
    prev = cv2.cvtColor(frames[0], cv2.COLOR_BGR2GRAY) if n else None
    last = (0.0, 0.0, 0.0)
    for i in range(1, n):
        grey = cv2.cvtColor(frames[i], cv2.COLOR_BGR2GRAY)
        m = pair_motion(prev, grey, p)
        last = m if m is not None else last
        motions[i - 1] = last
        prev = grey
    traj = np.vstack([np.zeros((1, 3)), np.cumsum(motions, axis=0)]) if n else np.zeros((0, 3))
    smooth = np.stack([moving_average(traj[:, k], p.radius) for k in range(3)], axis=1) if n else traj
    return smooth - traj


def warp(frame: np.ndarray, dx: float, dy: float, da: float) -> np.ndarray:
    """``frame`` rotated by ``da`` about the origin and shifted by (dx, dy); uncovered pixels black."""
    c, s = math.cos(da), math.sin(da)
    m = np.array([[c, -s, dx], [s, c, dy]])
    h, w = frame.shape[:2]
    return cv2.warpAffine(frame, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def stabilize(frames: list[np.ndarray], p: LKParams | None = None) -> list[np.ndarray]:
    """Stabilised BGR frames, one per input frame, in order."""
    if not frames:
        return []
    corr = corrections(frames, p)
    return [warp(f, *c) for f, c in zip(frames, corr)]

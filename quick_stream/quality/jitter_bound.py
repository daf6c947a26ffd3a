"""The least residual jitter a border-free 2D cropping stabilizer can reach at a given cropping: docs/method.md 6.3.

A stabilizer whose output shows, at zoom z = 1 / cropping, a window of the input shifted by c_t px and
turned by theta_t can only move that window inside the frame. Its output's per-pair motion is, to first
order, z (input translation - (c_{t+1} - c_t)) px and (input angle - (theta_{t+1} - theta_t)) degrees, and
the residual jitter of 6.1 is linear in the trajectory, so the least jitter it can reach is a bounded
least-squares problem per axis (18). Each axis is given the whole room on its own (a window turned by
theta has less room to shift), which only enlarges the feasible set: the answer bounds every constant-zoom
2D stabilizer that crops, shifts and turns the input, on the scorer's own reading of the input motion
(whose measurement noise it counts as motion to remove: on a slow clip, where that noise is much of the
jitter, it is no bound). A 3D warp is not such a crop (it changes the parallax between frames) and can go
below it (docs/method.md 6.3).
Pure numpy/scipy; the scorer's per-pair input motions in, (px, deg) out.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy import sparse
from scipy.optimize import lsq_linear

from .metrics_jitter import smooth_trajectory


def turn_room_deg(width: int, height: int, cropping: float) -> float:
    """Largest turn (degrees) up to which a centred window of ``cropping`` times the frame, turned by
    any smaller angle, stays in the frame (90 when every turn does)."""
    if not 0 < cropping <= 1:
        raise ValueError(f"cropping must be in (0, 1], got {cropping}")
    W, H = (width - 1) / 2.0, (height - 1) / 2.0
    w, h = W * cropping, H * cropping

    def inside(t: float) -> bool:
        c, s = math.cos(t), math.sin(t)
        return w * c + h * s <= W + 1e-9 and w * s + h * c <= H + 1e-9

    # the corners' reach rises and falls with the turn, so the turns that fit need not be one interval:
    # walk up in half degrees to the first that does not fit, then bisect that step
    step, lo = math.radians(0.5), 0.0
    while lo + step <= math.pi / 2 and inside(lo + step):
        lo += step
    if lo + step > math.pi / 2:
        return 90.0
    hi = lo + step
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if inside(mid) else (lo, mid)
    return math.degrees(lo)


@lru_cache(maxsize=4)
def high_pass_matrix(n: int, sigma_frames: float, chunk: int = 256) -> sparse.csr_matrix:
    """(n, n) sparse matrix of 6.1's high-pass on a trajectory of n frames: identity minus its Gaussian
    smoothing (zero beyond the kernel's reach, so banded; built a block of columns at a time). Cached:
    every method of a clip is bounded on the same input (read only)."""
    eye = np.eye(n, min(chunk, n))
    blocks = []
    for j in range(0, n, chunk):
        cols = np.roll(eye, j, axis=0)[:, :min(chunk, n - j)]  # e_j .. e_{j+chunk-1}
        blocks.append(sparse.csc_matrix(cols - smooth_trajectory(cols, sigma_frames)))
    return sparse.hstack(blocks).tocsr()


def border_free_jitter_bound(input_motions: np.ndarray, cropping: float, width: int, height: int,
                             sigma_frames: float) -> tuple[float, float]:
    """(px, deg): the least jitter of a border-free output at ``cropping`` (docs/method.md (18)).

    ``input_motions`` (N, 3): the scorer's per-pair input motions (tx px, ty px, angle deg), missing
    pairs already interpolated as the scorer does. px is charged at the output's zoom 1 / cropping.
    """
    m = np.asarray(input_motions, float).reshape(-1, 3)
    if not np.all(np.isfinite(m)):
        raise ValueError("input motions must be finite (interpolate missing pairs first)")
    traj = np.vstack([np.zeros((1, 3)), np.cumsum(m, axis=0)])
    hp = high_pass_matrix(len(traj), sigma_frames)
    margin = 1.0 - cropping
    rooms = ((width - 1) / 2.0 * margin, (height - 1) / 2.0 * margin, turn_room_deg(width, height, cropping))
    left = []
    for k, room in enumerate(rooms):
        target = hp @ traj[:, k]
        if room <= 0:
            left.append(target)
            continue
        # tight tolerances: a bound must be the minimum, and any point short of it reads higher
        shift = lsq_linear(hp, target, bounds=(-room, room), method="trf", tol=1e-12, lsmr_tol=1e-12,
                           max_iter=1000).x
        left.append(hp @ (traj[:, k] - shift))
    px = math.sqrt(float(np.mean(left[0] ** 2 + left[1] ** 2))) / cropping
    deg = math.sqrt(float(np.mean(left[2] ** 2)))
    return px, deg

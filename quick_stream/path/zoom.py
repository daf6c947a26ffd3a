"""The zoom track of a segment, planned with its path (docs/method.md (14)).

The planner knows, per frame, the zoom the planned correction needs to leave no border
(:class:`~.budget.SegmentMeshes`, the renderer's mesh on the frame's points). The zoom
track is the smooth curve that stays at or above that requirement and as close to 1 as
it can: per segment

    minimise  sum_t (z_t - 1)^2 + mu * sum_t (z_{t+1} - 2 z_t + z_{t-1})^2
    subject to  r_t <= z_t <= Z

with the last two zooms of the previous segment committed, so the zoom changes with
continuous rate across keyframes. It is the smoother's problem (docs/method.md (8)) in one
dimension with target 1; the bounds enter through the same dual non-negative least squares.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from .smoother import segment_system


def plan_zooms(required: np.ndarray, committed: np.ndarray, smoothness: float, max_zoom: float,
               provisional: int = 0, provisional_weight: float = 1e-3) -> np.ndarray:
    """Zooms (N,) >= ``required`` (N,) (capped at ``max_zoom``), smooth, continuing ``committed`` (k,) (0..3).

    The last ``provisional`` frames (a window's look-ahead, planned again later) are not pulled
    towards 1: the track holds its level there, so the next window finds the zoom it may need."""
    r = np.clip(np.nan_to_num(np.asarray(required, dtype=np.float64), nan=max_zoom, posinf=max_zoom),
                1.0, max_zoom)
    c = np.asarray(committed, dtype=np.float64).reshape(-1, 1)
    N = len(r)
    w = np.ones(N)
    if provisional > 0:
        w[max(N - provisional, 0):] = provisional_weight
    system = segment_system(N, len(c), smoothness, closeness=w)
    z0 = system.unconstrained(np.ones((N, 1)), c)[:, 0]
    # Constraints as rows of C z >= d: z_t >= r_t where the unconstrained track is low, and
    # -z_t >= -Z where it would overshoot; a second pass adds rows the first one needs.
    lo = np.zeros(N, bool)
    hi = np.zeros(N, bool)
    z = z0
    for _ in range(3):
        lo |= z < r - 1e-12
        hi |= z > max_zoom + 1e-12
        if not (lo.any() or hi.any()):
            break
        rows = np.concatenate((np.flatnonzero(lo), np.flatnonzero(hi)))
        sign = np.concatenate((np.ones(lo.sum()), -np.ones(hi.sum())))
        d = np.concatenate((r[lo], -np.full(hi.sum(), max_zoom)))
        Ainv = system.solve(np.eye(N))
        AiCt = Ainv[:, rows] * sign[None]
        M = sign[:, None] * AiCt[rows]
        M[np.diag_indices_from(M)] += 1e-12 * max(float(np.trace(M)) / len(M), 1e-30)
        L = np.linalg.cholesky(M)
        y, _ = nnls(L.T, np.linalg.solve(L, d - sign * z0[rows]), maxiter=50 * len(rows))
        z = z0 + AiCt @ y
        if np.all(z >= r - 1e-9) and np.all(z <= max_zoom + 1e-9):
            break
    return np.clip(np.maximum(z, r), 1.0, max_zoom)

"""The smoothed path of one keyframe segment: close to the camera, little acceleration (docs/method.md (8)-(9)).

The stabilized camera's pose at the segment's frames is written in the chart of the
group about the pose ``B`` it had at the opening keyframe: ``P_t = B exp(p_t)``. The real
camera's pose in the same chart is ``x_t = log(B^-1 g_c(t))``. Per segment the smoother
places ``p_t`` for the segment's frames t0+1..tf by minimising (docs/method.md (8))

    J_s(p) = sum_t |p_t - x_t|^2 + lam * sum_t |p_{t+1} - 2 p_t + p_{t-1}|^2

where the second sum runs over every triple that contains a frame being placed, the
frames before t0+1 being the committed past (``p_t0 = 0`` and up to two earlier
stabilized poses re-expressed in the same chart), so a segment continues the previous
one with continuous position and velocity. The end is free: no frame beyond the
closing keyframe is needed, so the latency stays one segment.

The problem separates per twist component into one banded N x N system (the same
matrix for every component); the correction of frame t is
``g_s(t) = g_c(t)^-1 B exp(p_t)`` (composition order: docs/conventions.md), exact
whatever the size of ``p``: only the smoother's objective is written in chart
coordinates. ``lam`` sets the cutoff: a stationary sinusoid of angular frequency w
(radians per frame) passes with gain 1 / (1 + 4 lam (1 - cos w)^2) (docs/method.md (9)).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve


def smoothness_for_cutoff(cutoff_hz: float, fps: float) -> float:
    """The ``lam`` whose gain is 0.5 at ``cutoff_hz`` for video at ``fps`` (docs/method.md (9))."""
    w = 2.0 * math.pi * cutoff_hz / fps
    return 1.0 / (4.0 * (1.0 - math.cos(w)) ** 2)


def cutoff_of_smoothness(lam: float, fps: float) -> float:
    """Inverse of :func:`smoothness_for_cutoff`: the frequency (Hz) where the gain is 0.5."""
    return math.acos(1.0 - 0.5 / math.sqrt(lam)) * fps / (2.0 * math.pi)


@dataclass
class SegmentSystem:
    """The smoother's quadratic form for N frames after ``k`` committed ones (docs/method.md (8)).

    ``J_s = p^T A p - 2 p^T (x - F c) + const`` per component, with ``p`` the N placed
    values, ``c`` the k committed ones (oldest first, the opening keyframe last).
    """

    A: np.ndarray  # (N, N) symmetric positive definite
    F: np.ndarray  # (N, k) coupling to the committed past
    factor: tuple  # Cholesky factor of A (scipy.linalg.cho_factor)
    V: np.ndarray  # (N, N) maps the N step-velocity targets into the placed frames' normal equations
    w: np.ndarray  # (N,) closeness weight of each placed frame

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """A^-1 rhs for rhs (N,) or (N, m)."""
        return cho_solve(self.factor, rhs)

    def unconstrained(self, x: np.ndarray, committed: np.ndarray, velocity: np.ndarray | None = None) -> np.ndarray:
        """Minimiser of J_s for real path ``x`` (N, n), committed past (k, n) and, with a velocity
        weight, the target velocities (N, n) of the steps into the placed frames: (N, n)."""
        rhs = self.w[:, None] * x - self.F @ committed
        if velocity is not None:
            rhs = rhs + self.V @ velocity
        return self.solve(rhs)


def segment_system(n_frames: int, n_committed: int, lam: float, velocity_weight: float = 0.0,
                   closeness: np.ndarray | None = None) -> SegmentSystem:
    """Build :class:`SegmentSystem` for ``n_frames`` placed frames after ``n_committed`` (0..3) committed ones.

    ``closeness`` (N,): per-frame weight of the first term of (8) (default 1)."""
    if n_frames < 1:
        raise ValueError("a segment needs at least one frame to place")
    if not 0 <= n_committed <= 3:
        raise ValueError(f"0 to 3 committed frames expected, got {n_committed}")
    if not (math.isfinite(lam) and lam >= 0):
        raise ValueError(f"smoothness must be finite and >= 0, got {lam}")
    k, N = n_committed, n_frames
    m = k + N
    D = np.zeros((max(m - 2, 0), m))
    for i in range(m - 2):
        D[i, i:i + 3] = (1.0, -2.0, 1.0)
    Q = lam * (D.T @ D)
    D1 = np.zeros((m - 1, m))
    for i in range(m - 1):
        D1[i, i:i + 2] = (-1.0, 1.0)
    Q += velocity_weight * (D1.T @ D1)
    # the N steps into the placed frames (t0 -> t0+1 .. tf-1 -> tf); with no committed past the
    # first placed frame has no step into it: its target is unused
    V = velocity_weight * (D1[k - 1:, k:].T if k else np.hstack([np.zeros((N, 1)), D1[:, k:].T]))
    w = np.ones(N) if closeness is None else np.asarray(closeness, dtype=np.float64)
    A = Q[k:, k:] + np.diag(w)
    return SegmentSystem(A=A, F=Q[k:, :k], factor=cho_factor(A), V=V, w=w)


def chart_path(group, base: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """log(B^-1 P) for each pose (docs/method.md (8)): (m, 4, 4) -> (m, n)."""
    return group.log(np.linalg.inv(base)[None] @ np.asarray(poses, dtype=np.float64))

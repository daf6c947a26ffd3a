"""End-constraints at keyframes (docs/method.md 4.2).

* ``identity`` (the paper's): no correction at keyframes, so the stabilized path
  passes through the real, jittery keyframe poses and their jitter survives as a
  slow wobble.
* ``smoothed``: the stabilized pose at each keyframe is a causal filter of the
  keyframe poses in the group: predict S_pred = S_prev P over the segment, where
  P is the segment's intended motion (the planner passes the product of its
  low-passed camera twists) or, without one, the alpha-beta constant-velocity
  step exp(L v); innovation e = log(S_pred^-1 K_j), S_j = S_pred exp(alpha e),
  v += beta e / L. It uses no frame beyond the closing keyframe, so the latency
  stays one segment, and a steady pan or dolly passes through without lag. The
  end-constraint is the correction g_s = K_j^-1 S_j (composition order: :mod:`.optimal`).
"""
from __future__ import annotations

import numpy as np

from ..lie import LieGroup

END_MODES = ("identity", "smoothed")


class EndConstraints:
    """Correction targets at keyframes for one stream."""

    def __init__(self, group: LieGroup, mode: str = "smoothed", alpha: float = 0.4, beta: float = 0.4) -> None:
        if mode not in END_MODES:
            raise ValueError(f"end-constraint mode must be one of {END_MODES}, got {mode!r}")
        if not (0 < alpha <= 1 and 0 <= beta <= 1):
            raise ValueError(f"smoothing gains need 0 < alpha <= 1 and 0 <= beta <= 1, got {alpha}, {beta}")
        self.group, self.mode, self.alpha, self.beta = group, mode, alpha, beta
        self._S: np.ndarray | None = None  # smoothed pose at the last keyframe
        self._v = np.zeros(group.dim)  # velocity twist per frame
        self._warm = False  # velocity estimated yet (first keyframe after a reset sets it)

    def reset(self, keyframe_pose: np.ndarray) -> None:
        """Restart at a keyframe with no correction (stream start, broken path, failed segment)."""
        self._S = np.asarray(keyframe_pose, dtype=np.float64).copy()
        self._v = np.zeros(self.group.dim)
        self._warm = False

    def at_keyframe(self, keyframe_pose: np.ndarray, frames: int, motion: np.ndarray | None = None) -> np.ndarray:
        """The correction required at a keyframe reached ``frames`` frames after the previous one.

        ``motion``, when given, is the segment's intended (low-passed) camera motion; it
        replaces the constant-velocity prediction exp(L v).
        """
        K = np.asarray(keyframe_pose, dtype=np.float64)
        if self.mode == "identity" or self._S is None:
            if self._S is None:
                self.reset(K)
            else:
                self._S = K.copy()
            return np.eye(4)
        g = self.group
        if not self._warm:  # first keyframe after a reset: no correction, start the velocity
            self._v = g.log(g.inverse(self._S) @ K) / frames
            self._S = K.copy()
            self._warm = True
            return np.eye(4)
        pred = self._S @ (g.exp(frames * self._v) if motion is None else motion)
        e = g.log(g.inverse(pred) @ K)
        self._S = pred @ g.exp(self.alpha * e)
        self._v = self._v + self.beta * e / frames
        return g.inverse(K) @ self._S

"""Relative pose error (RPE) between estimated and ground-truth frame-to-frame motions.

For a frame pair (t, t+1) with ground-truth camera-to-world poses T_t, T_{t+1}
the true camera motion is G = T_t^-1 T_{t+1}; for an estimate g the error is
E = G^-1 g. Rotation error = angle of E's rotation (degrees), translation
error = |E's translation| (mm). For groups beyond SE(3) the estimate's linear
part is projected to the nearest rotation first (its non-rigid part is not a
pose error the ground truth can measure).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable

import numpy as np

from ...core.lie import so3

if TYPE_CHECKING:
    from ...core.motion_pipeline import PairRecord


def relative_pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in mm) of camera motion ``estimate`` vs ``truth``."""
    g = estimate.copy()
    g[:3, :3] = so3.nearest_rotation(g[:3, :3])
    E = np.linalg.inv(truth) @ g
    c = np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c))), float(np.linalg.norm(E[:3, 3]) * 1000.0)


@dataclass
class ErrorStats:
    """Median / mean / RMSE of per-pair rotation (deg) and translation (mm) errors."""

    n: int
    rot_median: float
    rot_mean: float
    rot_rmse: float
    trans_median: float
    trans_mean: float
    trans_rmse: float

    @classmethod
    def from_errors(cls, rot_deg: list[float] | np.ndarray, trans_mm: list[float] | np.ndarray) -> "ErrorStats":
        r = np.asarray(rot_deg, float)
        t = np.asarray(trans_mm, float)
        if r.size == 0:
            nan = float("nan")
            return cls(0, nan, nan, nan, nan, nan, nan)
        return cls(
            int(r.size),
            float(np.median(r)), float(r.mean()), float(np.sqrt(np.mean(r * r))),
            float(np.median(t)), float(t.mean()), float(np.sqrt(np.mean(t * t))),
        )

    def as_dict(self) -> dict[str, float | int]:
        return dict(self.__dict__)


def pair_error_stats(pairs: Iterable[PairRecord]) -> ErrorStats:
    """Errors of a motion run's valid motions against their ground truth (pairs without one are left out)."""
    rot, tr = [], []
    for p in pairs:
        if p.truth is not None and p.motion.valid:
            r, t = relative_pose_error(p.motion.matrix, p.truth)
            rot.append(r)
            tr.append(t)
    return ErrorStats.from_errors(rot, tr)

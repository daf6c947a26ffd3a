"""Camera motion between consecutive frames, in any of the four groups.

Conventions (also in docs/conventions.md):

* A frame's pose T_t is camera-to-world (OpenCV camera axes: x right, y down,
  z forward). A point with camera-t coordinates x has camera-(t+1) coordinates
  x' = M_t x, where M_t = T_{t+1}^-1 T_t is the *point motion* the scene flow
  measures (x' = x + v).
* The *camera motion* is g(xi_t) = M_t^-1 = T_t^-1 T_{t+1}: the pose of camera
  t+1 expressed in camera t's frame. Its twist xi_t = log(g(xi_t)) uses the
  group's chart (paper: decoupled exponential for SE(3)/SIM(3), phi for SA(3)/GA(3)),
  translation first, so xi_t[:3] is the camera's translation in camera-t axes.
* The camera path integrates on the right: g_c(0) = I, g_c(t+1) = g_c(t) g(xi_t)
  (paper, section "Video stabilization"), so g_c(t) = T_0^-1 T_t.

Estimators: ``exact`` (default, robust fit, :mod:`.exact`) and ``induced``
(the paper's mean of induced twists, :mod:`.induced`).
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ..lie import LieGroup, get_group
from ..sceneflow import SceneFlowResult
from .exact import ExactParams, irls_closed_form, refine_reprojection
from .induced import estimate_induced

ESTIMATORS = ("exact", "induced")


@dataclass
class MotionParams:
    """Which group and estimator, and when a motion counts as invalid."""

    group: str = "se3"  # se3 | sim3 | sa3 | ga3
    estimator: str = "exact"  # exact | induced
    min_points: int = 50  # fewer scene-flow pairs: motion invalid
    min_inlier_ratio: float = 0.25  # exact: fewer robust inliers than this share: invalid
    exact: ExactParams = field(default_factory=ExactParams)

    @classmethod
    def describe(cls) -> dict[str, str]:
        d = {f.name: repr(f.default) for f in fields(cls) if f.name != "exact"}
        d.update({f"exact.{k}": v for k, v in ExactParams.describe().items()})
        return d

    def validate(self) -> None:
        get_group(self.group)
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"motion estimator must be one of {ESTIMATORS}, got {self.estimator!r}")


@dataclass
class MotionEstimate:
    """Camera motion g(xi_t) from frame ``seq`` to ``seq_next`` (see module conventions).

    When ``valid`` is False, ``matrix`` is the identity and ``reason`` says why.
    """

    seq: int
    seq_next: int
    group: str
    estimator: str
    matrix: np.ndarray  # 4x4 camera motion T_t^-1 T_{t+1}
    twist: np.ndarray  # chart coordinates of ``matrix``, translation first
    valid: bool
    reason: str = ""
    n_points: int = 0
    inlier_ratio: float = 0.0
    rms_px: float = float("nan")
    zeta_bar: np.ndarray | None = None  # log(matrix^-1): the path solver's zeta_bar (design note 4)


def invalid_motion(seq: int, seq_next: int, group: str, estimator: str, reason: str) -> MotionEstimate:
    """An identity motion flagged invalid (the path holds still across it)."""
    g = get_group(group)
    return MotionEstimate(
        seq, seq_next, group, estimator, g.identity(), np.zeros(g.dim), False, reason, zeta_bar=np.zeros(g.dim)
    )


class MotionEstimator:
    """Estimates :class:`MotionEstimate` from a :class:`SceneFlowResult`."""

    def __init__(self, params: MotionParams | None = None) -> None:
        self.params = params or MotionParams()
        self.params.validate()
        self.group: LieGroup = get_group(self.params.group)

    def estimate(self, flow: SceneFlowResult) -> MotionEstimate:
        p = self.params
        n = len(flow)
        if flow.problem:
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator, flow.problem)
        if n < max(p.min_points, p.exact.min_points):
            return invalid_motion(
                flow.seq, flow.seq_next, p.group, p.estimator,
                f"only {n} usable scene-flow pairs (need {p.min_points})",
            )
        x, v, w = flow.points, flow.displacements, flow.weights
        try:
            if p.estimator == "induced":
                M = estimate_induced(self.group, x, v, w)
                inliers, rms = 1.0, float("nan")
            else:
                M, w1 = irls_closed_form(p.group, x, x + v, w, p.exact, flow.intrinsics.fx)
                ref = refine_reprojection(
                    self.group, M, x, flow.pixels_next, x[:, 2] + v[:, 2], flow.intrinsics_next.K, w1, p.exact
                )
                M, inliers, rms = ref.M, ref.inlier_ratio, ref.rms_px
            g = self.group.inverse(M)
            twist = self.group.log(g)
            zbar = self.group.log(M)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as e:
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator, f"fit failed: {e}")
        if not np.all(np.isfinite(g)):
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator, "fit is not finite")
        if inliers < p.min_inlier_ratio:
            return invalid_motion(
                flow.seq, flow.seq_next, p.group, p.estimator,
                f"only {inliers:.0%} of scene-flow pairs agree with one motion",
            )
        return MotionEstimate(
            flow.seq, flow.seq_next, p.group, p.estimator, g, twist, True,
            n_points=n, inlier_ratio=inliers, rms_px=rms, zeta_bar=zbar,
        )


def integrate_path(motions: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Camera path g_c(0) = I, g_c(t+1) = g_c(t) g(xi_t) (paper, "Video stabilization"); (N+1, 4, 4)."""
    path = np.empty((len(motions) + 1, 4, 4))
    path[0] = np.eye(4)
    for i, g in enumerate(motions):
        path[i + 1] = path[i] @ g
    return path


__all__ = [
    "ESTIMATORS", "ExactParams", "MotionEstimate", "MotionEstimator", "MotionParams",
    "integrate_path", "invalid_motion",
]

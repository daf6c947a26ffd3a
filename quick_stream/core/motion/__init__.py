"""Camera motion between consecutive frames, in any of the four groups.

Conventions (also in docs/conventions.md):

* A frame's pose T_t is camera-to-world (OpenCV camera axes: x right, y down,
  z forward). A point with camera-t coordinates x has camera-(t+1) coordinates
  x' = M_t x, where M_t = T_{t+1}^-1 T_t is the *point motion* the scene flow
  measures (x' = x + v).
* The *camera motion* is g(xi_t) = M_t^-1 = T_t^-1 T_{t+1}: the pose of camera
  t+1 expressed in camera t's frame. Its twist xi_t = log(g(xi_t)) uses the
  group's chart (docs/method.md (3e) for SE(3)/SIM(3), (3f) for SA(3)/GA(3)),
  translation first, so xi_t[:3] is the camera's translation in camera-t axes.
* The camera path integrates on the right: g_c(0) = I, g_c(t+1) = g_c(t) g(xi_t)
  (docs/method.md 4.1), so g_c(t) = T_0^-1 T_t.

Estimators: ``exact`` (default, robust fit, :mod:`.exact`) and ``induced``
(the paper's mean of induced twists, :mod:`.induced`).

Observability (``exact``, docs/method.md section 2.3): a motion is only as
determined as the spread of the points it was fitted to. When the weighted
point spread leaves GA(3)'s or SA(3)'s linear part undetermined (a wall, a
floor: points on one plane), the estimate is the SIM(3) fit (for GA(3)) or the
SE(3) fit (for SA(3)) of the same flow, expressed as an element of the requested
group; ``MotionEstimate.fallback`` names the group used and ``reason`` says why.
When even the rigid fit is undetermined (collinear points, fewer than three
distinct points) the motion is invalid.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ..lie import LieGroup, get_group
from ..sceneflow import SceneFlowResult
from .exact import ExactParams, RIGID_FALLBACK, irls_closed_form, observability, refine_reprojection
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

    When ``valid`` is False, ``matrix`` is the identity and ``reason`` says why. When
    ``fallback`` is set ("sim3" or "se3"), ``group``'s own fit was not determined by the
    points' spread and ``matrix`` is that smaller group's fit, an element of ``group``
    (docs/method.md section 2.3); ``reason`` then says why.
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
    zeta_bar: np.ndarray | None = None  # log(matrix^-1): the path solver's zeta_bar (docs/method.md (5))
    fallback: str = ""  # the group whose fit was used instead of ``group``'s ("" = group's own), method.md 2.3


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
        fallback, why = "", ""
        try:
            if p.estimator == "induced":
                M = estimate_induced(self.group, x, v, w)
                inliers, rms = 1.0, float("nan")
            else:
                # (3b) on the flow's weights first (a wall: no affine fit), then on the fit's final weights
                fit_group, lim = p.group, p.exact.max_spread_error
                obs0 = obs = observability(x, w, flow.intrinsics.fx, p.exact)
                if p.group in RIGID_FALLBACK:
                    if obs.affine_error <= lim:
                        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                            M, inliers, rms, w_fit = self._fit_exact(p.group, flow)  # checked below
                        obs = observability(x, w_fit, flow.intrinsics.fx, p.exact)
                    if obs.affine_error > lim:
                        fit_group = fallback = RIGID_FALLBACK[p.group]
                        why = (f"{p.group} linear part not determined by the point spread "
                               f"(predicted error {obs.affine_error:.2g} > {lim:g}: "
                               f"points nearly planar or too few for their noise); {fallback} fit used")
                if fit_group in ("se3", "sim3"):
                    obs = obs0
                    if obs.rigid_error <= lim:
                        M, inliers, rms, w_fit = self._fit_exact(fit_group, flow)
                        obs = observability(x, w_fit, flow.intrinsics.fx, p.exact)
                    if obs.rigid_error > lim:
                        return invalid_motion(
                            flow.seq, flow.seq_next, p.group, p.estimator,
                            f"rotation not determined by the point spread (predicted error "
                            f"{obs.rigid_error:.2g} > {lim:g}: points nearly collinear, "
                            f"fewer than 3 distinct or too few for their noise)",
                        )
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
            flow.seq, flow.seq_next, p.group, p.estimator, g, twist, True, why,
            n_points=n, inlier_ratio=inliers, rms_px=rms, zeta_bar=zbar, fallback=fallback,
        )

    def _fit_exact(self, group_name: str, flow: SceneFlowResult) -> tuple[np.ndarray, float, float, np.ndarray]:
        """The exact estimator in ``group_name``: IRLS closed form, then robust Gauss-Newton
        (docs/method.md (3)). Returns (point motion M, inlier ratio, rms px, final weights)."""
        p = self.params
        x, v, w = flow.points, flow.displacements, flow.weights
        M, w1 = irls_closed_form(group_name, x, x + v, w, p.exact, flow.intrinsics.fx)
        ref = refine_reprojection(
            get_group(group_name), M, x, flow.pixels_next, x[:, 2] + v[:, 2], flow.intrinsics_next.K, w1, p.exact
        )
        return ref.M, ref.inlier_ratio, ref.rms_px, ref.weights


def integrate_path(motions: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Camera path g_c(0) = I, g_c(t+1) = g_c(t) g(xi_t) (docs/method.md 4.1); (N+1, 4, 4)."""
    path = np.empty((len(motions) + 1, 4, 4))
    path[0] = np.eye(4)
    for i, g in enumerate(motions):
        path[i + 1] = path[i] @ g
    return path


__all__ = [
    "ESTIMATORS", "ExactParams", "MotionEstimate", "MotionEstimator", "MotionParams",
    "integrate_path", "invalid_motion",
]

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
group; ``MotionEstimate.fallback`` names the group used and ``reason`` says why. SIM(3), SA(3)
and GA(3) start from the SE(3) fit and keep to its consensus (docs/method.md (3l), (3m)): their
extra freedom may not be spent on pairs the rigid fit calls outliers (an object moving in front
of a wall), and the spread test reads the weights of both fits.

The fallback chain (docs/method.md section 2.4): a fit that is not determined even as a rigid
motion, or that too few pairs agree with, does not make the frame uncorrected while the flow still
holds information: the rotation-only fit of the same pixel pairs (the homography at infinity,
:mod:`.rotation`, no depth needed) is taken instead (``kind`` "rotation"). Only a flow with no
usable pairs at all gives an invalid motion (``kind`` "none"); the motion stage then bridges it at
constant velocity for a few frames (:mod:`.chain`) before the path restarts. Each motion carries its
covariance, which the path uses to weight it.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..lie import LieGroup, get_group
from ..sceneflow import SceneFlowResult
from .exact import ExactParams, RefineResult, irls_closed_form, refine_from_rigid, refine_reprojection
from .observability import RIGID_FALLBACK, observability
from .induced import estimate_induced
from .rotation import fit_rotation

ESTIMATORS = ("exact", "induced")
KINDS = ("fit", "rotation", "bridge", "none")  # how a motion was known, best first (docs/method.md 2.4)
UNKNOWN_VARIANCE = 1.0  # variance (m^2, rad^2) of a twist component a motion's kind does not estimate


@dataclass
class MotionParams:
    """Which group and estimator, and when a motion counts as invalid."""

    group: str = "se3"  # se3 | sim3 | sa3 | ga3
    estimator: str = "exact"  # exact | induced
    min_points: int = 50  # fewer scene-flow pairs: motion invalid
    min_inlier_ratio: float = 0.25  # exact: fewer robust inliers than this share: the rotation-only fit instead
    rotation_fallback: bool = True  # exact: a fit not taken falls back to the rotation-only fit (docs/method.md 2.4)
    min_rotation_inliers: float = 0.1  # ... which needs this share of the pairs to agree with it
    min_rotation_points: int = 8  # ... and at least this many pairs (fewer than min_points: no group fit)
    max_rotation_sigma: float = 0.01  # ... and its rotation determined to this (rad, RMS over the axes)
    translation_prior_mm: float = 0.0  # exact: a fit's translation is drawn towards 0 with this std per frame
    # step (mm), along what the flow cannot tell from a rotation (docs/method.md (3n)); 0: off
    bridge_frames: int = 3  # a flow with nothing in it is bridged at constant velocity for up to this many
    # consecutive frames before the path restarts (0: never; docs/method.md 2.4, the motion stage's MotionBridge)
    exact: ExactParams = field(default_factory=ExactParams)

    def validate(self) -> None:
        get_group(self.group)
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"motion estimator must be one of {ESTIMATORS}, got {self.estimator!r}")
        if not self.translation_prior_mm >= 0:
            raise ValueError(f"motion translation_prior_mm must be >= 0, got {self.translation_prior_mm}")
        if self.bridge_frames < 0:
            raise ValueError(f"motion bridge_frames must be >= 0, got {self.bridge_frames}")
        if self.min_rotation_points < 3:
            raise ValueError(f"motion min_rotation_points must be >= 3, got {self.min_rotation_points}")
        if not (0 <= self.min_rotation_inliers <= 1 and self.max_rotation_sigma > 0):
            raise ValueError("motion min_rotation_inliers must be in [0, 1] and max_rotation_sigma > 0, got "
                             f"{self.min_rotation_inliers}, {self.max_rotation_sigma}")


@dataclass
class MotionEstimate:
    """Camera motion g(xi_t) from frame ``seq`` to ``seq_next`` (see module conventions).

    When ``valid`` is False, ``matrix`` is the identity and ``reason`` says why. When
    ``fallback`` is set ("sim3" or "se3"), ``group``'s own fit was not determined by the
    points' spread and ``matrix`` is that smaller group's fit, an element of ``group``
    (docs/method.md section 2.3); ``reason`` then says why. ``kind`` says how the motion was
    known (:data:`KINDS`, docs/method.md 2.4): the fit, the rotation-only fit of the same flow
    (translation 0), a constant-velocity bridge over a flow with nothing in it, or not at all
    (``valid`` False). ``covariance``: of ``twist`` (n x n; components the kind does not estimate
    at :data:`UNKNOWN_VARIANCE`), None when unknown (an invalid motion, an old recording).
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
    kind: str = "fit"  # how the motion was known: fit | rotation | bridge | none (docs/method.md 2.4)
    covariance: np.ndarray | None = None  # (n, n) of ``twist``, docs/method.md (3k)

    @property
    def rotation_sigma(self) -> float:
        """RMS standard deviation of the camera's rotation over its three axes (rad); inf when unknown."""
        if self.covariance is None:
            return float("inf")
        P = rotation_projector(get_group(self.group))
        return float(np.sqrt(max(np.trace(P @ self.covariance @ P.T), 0.0) / 3.0))


def rotation_projector(group: LieGroup) -> np.ndarray:
    """(3, n): a twist's rotation vector, the antisymmetric part of its linear generators (to first order)."""
    P = np.zeros((3, group.dim))
    for k in range(3, group.dim):
        L = group.basis[k, :3, :3]
        P[:, k] = 0.5 * np.array([L[2, 1] - L[1, 2], L[0, 2] - L[2, 0], L[1, 0] - L[0, 1]])
    return P


def with_translation_prior(m: MotionEstimate, group: LieGroup, sigma_m: float) -> MotionEstimate:
    """``m`` with the prior t ~ N(0, sigma_m² I) on its camera translation (docs/method.md (3n)): the
    conditional update of the twist and its covariance. A translation the flow determines well (its
    variance far below sigma_m²) keeps its value; the part it cannot tell from a rotation (pitch against
    a sideways step, yaw against a vertical one, when parallax is small) goes to the rotation."""
    S = m.covariance
    K = S[:, :3] @ np.linalg.inv(S[:3, :3] + np.eye(3) * sigma_m ** 2)
    twist = m.twist - K @ m.twist[:3]
    g = group.exp(twist)
    if not np.all(np.isfinite(g)):
        return m
    cov = S - K @ S[:3, :]
    return replace(m, matrix=g, twist=twist, zeta_bar=group.log(group.inverse(g)), covariance=0.5 * (cov + cov.T))


def invalid_motion(seq: int, seq_next: int, group: str, estimator: str, reason: str) -> MotionEstimate:
    """An identity motion flagged invalid (the path holds still across it)."""
    g = get_group(group)
    return MotionEstimate(
        seq, seq_next, group, estimator, g.identity(), np.zeros(g.dim), False, reason, zeta_bar=np.zeros(g.dim),
        kind="none",
    )


class MotionEstimator:
    """Estimates :class:`MotionEstimate` from a :class:`SceneFlowResult`."""

    def __init__(self, params: MotionParams | None = None) -> None:
        self.params = params or MotionParams()
        self.params.validate()
        self.group: LieGroup = get_group(self.params.group)

    def estimate(self, flow: SceneFlowResult) -> MotionEstimate:
        """The camera motion of ``flow``: the group's fit, else the rotation-only fit of the same pairs,
        else invalid (docs/method.md 2.4)."""
        p = self.params
        n = len(flow)
        if flow.problem:
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator, flow.problem)
        if n < max(p.min_points, p.exact.min_points):
            why = f"only {n} usable scene-flow pairs (need {p.min_points})"
            if n < p.min_rotation_points:
                return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator, why)
            return self._rotation_or_invalid(flow, why)
        try:
            if p.estimator == "induced":
                M = estimate_induced(self.group, flow.points, flow.displacements, flow.weights)
                return self._motion(flow, M, 1.0, float("nan"), "", "", None)
            return self._estimate_exact(flow)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as e:
            return self._rotation_or_invalid(flow, f"fit failed: {e}")

    def _estimate_exact(self, flow: SceneFlowResult) -> MotionEstimate:
        """The exact fit with its observability test (docs/method.md 2.3), then the fallback chain (2.4).
        A group larger than SE(3) starts from the SE(3) fit and is kept to its consensus ((3l), (3m)), and
        (3b) on its final weights leaves out pairs the rigid fit rejects (an object in front of a wall)."""
        p = self.params
        x, w = flow.points, flow.weights
        fits: dict[str, RefineResult] = {}  # by group: the larger groups and a fallback share the SE(3) fit
        # (3b) on the flow's weights first (a wall: no affine fit), then on the fit's final weights
        fit_group, lim, fallback, why = p.group, p.exact.max_spread_error, "", ""
        obs0 = obs = observability(x, w, flow.intrinsics.fx, p.exact)
        if p.group in RIGID_FALLBACK:
            if obs.affine_error <= lim:
                with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                    fit = self._fit_exact(p.group, flow, fits)  # checked below
                obs = observability(x, self._spread_weights(fit), flow.intrinsics.fx, p.exact)
            if obs.affine_error > lim:
                fit_group = fallback = RIGID_FALLBACK[p.group]
                where = ("the point spread" if obs is obs0 else
                         "the spread of the pairs that agree with the rigid fit")
                why = (f"{p.group} linear part not determined by {where} "
                       f"(predicted error {obs.affine_error:.2g} > {lim:g}: points nearly planar"
                       f"{'' if obs is obs0 else ' apart from pairs that move with something else'}"
                       f" or too few for their noise); {fallback} fit used")
        if fit_group in ("se3", "sim3"):
            obs = obs0
            if obs.rigid_error <= lim:
                fit = self._fit_exact(fit_group, flow, fits)
                obs = observability(x, self._spread_weights(fit), flow.intrinsics.fx, p.exact)
            if obs.rigid_error > lim:
                return self._rotation_or_invalid(
                    flow, f"rotation not determined by the point spread (predicted error "
                          f"{obs.rigid_error:.2g} > {lim:g}: points nearly collinear, "
                          f"fewer than 3 distinct or too few for their noise)")
        M, inliers, rms, cov = fit.M, fit.inlier_ratio, fit.rms_px, fit.covariance
        if not np.all(np.isfinite(M)):
            return self._rotation_or_invalid(flow, "fit is not finite")
        if inliers < p.min_inlier_ratio:
            return self._rotation_or_invalid(flow, f"only {inliers:.0%} of scene-flow pairs agree with one motion")
        m = self._motion(flow, M, inliers, rms, why, fallback, self._twist_covariance(M, cov, fit_group))
        if p.translation_prior_mm > 0 and m.valid and m.covariance is not None:
            sigma = p.translation_prior_mm * 1e-3 * max(flow.seq_next - flow.seq, 1)
            m = with_translation_prior(m, self.group, sigma)
        return m

    def _rotation_or_invalid(self, flow: SceneFlowResult, why: str) -> MotionEstimate:
        """The rotation-only fit of the flow's pixel pairs when it holds (docs/method.md (3j)), else invalid."""
        p = self.params
        if p.estimator != "exact" or not p.rotation_fallback:
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator, why)
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                r = fit_rotation(flow.pixels, flow.pixels_next, flow.intrinsics.K, flow.intrinsics_next.K,
                                 flow.weights, p.exact)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as e:
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator, f"{why}; rotation-only fit failed: {e}")
        if not (np.all(np.isfinite(r.R)) and r.sigma <= p.max_rotation_sigma):
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator,
                                  f"{why}; rotation-only fit not determined (sigma {r.sigma:.2g} rad > "
                                  f"{p.max_rotation_sigma:g})")
        if r.inlier_ratio < p.min_rotation_inliers:
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator,
                                  f"{why}; only {r.inlier_ratio:.0%} of the pairs agree with a rotation")
        M = np.eye(4)
        M[:3, :3] = r.R
        g = self.group
        cov = np.eye(g.dim) * UNKNOWN_VARIANCE
        P = rotation_projector(g)
        B = np.linalg.pinv(P)  # the rotation generators' share of each twist coordinate
        cov = cov - B @ P @ cov @ P.T @ B.T + B @ r.covariance @ B.T  # rotation block: the fit's
        return self._motion(flow, M, r.inlier_ratio, r.rms_px, f"{why}; rotation-only fit of the same flow used",
                            "", cov, kind="rotation")

    def _motion(self, flow: SceneFlowResult, M: np.ndarray, inliers: float, rms: float, why: str, fallback: str,
                cov: np.ndarray | None, kind: str = "fit") -> MotionEstimate:
        p = self.params
        g = self.group.inverse(M)
        if not np.all(np.isfinite(g)):
            return invalid_motion(flow.seq, flow.seq_next, p.group, p.estimator, "fit is not finite")
        return MotionEstimate(
            flow.seq, flow.seq_next, p.group, p.estimator, g, self.group.log(g), True, why,
            n_points=len(flow), inlier_ratio=inliers, rms_px=rms, zeta_bar=self.group.log(M), fallback=fallback,
            kind=kind, covariance=cov,
        )

    def _twist_covariance(self, M: np.ndarray, cov: np.ndarray | None, fit_group: str) -> np.ndarray | None:
        """The covariance of the camera twist log(M^-1) from that of the fit's left update of M
        (docs/method.md (3k)); a smaller group's fit (2.3) is embedded in the requested group."""
        if cov is None or not np.all(np.isfinite(cov)):
            return None
        g = self.group
        if fit_group != g.name:  # the smaller group's coordinates in the requested group's
            fb = get_group(fit_group)
            C = g.vee(fb.basis).T  # (n, n_fb)
            cov = C @ cov @ C.T
        # M' = exp(d) M  =>  g' = g exp(-d): twist' = twist - J_r(twist)^-1 d to first order
        Jinv = np.linalg.inv(g.right_jacobian(g.log(g.inverse(M))))
        return Jinv @ cov @ Jinv.T

    @staticmethod
    def _spread_weights(fit: RefineResult) -> np.ndarray:
        """The weights (3b) is tested on: a larger group's carry the SE(3) fit's (docs/method.md (3l), (3m))."""
        return fit.weights if fit.spread_weights is None else fit.spread_weights

    def _fit_exact(self, group_name: str, flow: SceneFlowResult, fits: dict[str, RefineResult]) -> RefineResult:
        """The exact estimator in ``group_name`` (point motion M, final weights, covariance of the left
        update of M), kept in ``fits``. SE(3) (and any group with robust weighting off): IRLS closed form,
        then robust Gauss-Newton (docs/method.md (3)); SIM(3), SA(3), GA(3): the Gauss-Newton started at
        the SE(3) fit and kept to its consensus, (3l) and (3m)."""
        if group_name not in fits:
            p = self.params
            x, v, w = flow.points, flow.displacements, flow.weights
            args = (x, flow.pixels_next, x[:, 2] + v[:, 2], flow.intrinsics_next.K)
            if group_name == "se3" or not p.exact.robust:
                M, w1 = irls_closed_form(group_name, x, x + v, w, p.exact, flow.intrinsics.fx)
                fits[group_name] = refine_reprojection(get_group(group_name), M, *args, w1, p.exact)
            else:
                rigid = self._fit_exact("se3", flow, fits)
                fits[group_name] = refine_from_rigid(get_group(group_name), rigid, *args, w, p.exact)
        return fits[group_name]


def integrate_path(motions: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Camera path g_c(0) = I, g_c(t+1) = g_c(t) g(xi_t) (docs/method.md 4.1); (N+1, 4, 4)."""
    path = np.empty((len(motions) + 1, 4, 4))
    path[0] = np.eye(4)
    for i, g in enumerate(motions):
        path[i + 1] = path[i] @ g
    return path


__all__ = [
    "ESTIMATORS", "ExactParams", "KINDS", "MotionEstimate", "MotionEstimator", "MotionParams", "UNKNOWN_VARIANCE",
    "integrate_path", "invalid_motion", "rotation_projector",
]

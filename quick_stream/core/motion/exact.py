"""The `exact` estimator: a robust weighted least-squares fit of the group element.

docs/method.md section 2.2 ("exact"). Given scene-flow pairs (x, x' = x + v) it finds
the point motion M in the group G with x' ~ M x, in two steps:

1. closed-form start, robustly reweighted (IRLS, Cauchy weights on the 3D
   residual): weighted Kabsch for SE(3), Umeyama for SIM(3), linear least
   squares for GA(3), the GA(3) fit scaled to det = 1 for SA(3);
2. robust Gauss-Newton refinement in the group's own basis, with residuals where
   the measurements live: the image-plane error of the projected point
   (px, from the optical flow) and the depth error scaled by the sensor's depth
   noise (sigma_z = depth_noise * z^2). Depth noise along the ray dominates the
   3D error of an RGB-D point, so a plain 3D fit under-uses the precise flow.
   Updates are left perturbations M <- exp(delta) M, whose first-order
   Jacobian column k is E_k [M x; 1] for every group.

Both loops iterate until converged, with an upper bound (``init_iters``,
``gn_iters``): they stop when an iteration moves the fitted motion by less than
``tol`` times every point's expected error (IRLS: the change of M x in units of
:func:`point_sigma`; Gauss-Newton: the change J delta of the normalised residuals),
docs/method.md (3a). At that point the weights, which are a function of M, have
stopped changing too. No randomness: the estimator is deterministic.

Cauchy reweighting with a MAD scale makes moving objects (people walking
through the view) outliers instead of pulling the estimate. The scale is capped
in units of the expected noise: at 2 for the IRLS, at 1.25 for the Gauss-Newton
(``gn_max_scale``). Run to convergence, the Gauss-Newton with the wider cap of 2
let 61 % moving pixels (jointvosf two_people_walking) pull the fit 0.5 deg off the
background along the weakly determined rotation/translation direction, which
two fixed iterations had hidden (docs/method.md section 2.2).

Observability (docs/method.md section 2.3, equation (3b)): :func:`observability`
measures the weighted spread of the points against their expected error. GA(3)
and SA(3) need spread in all three directions (on a plane the out-of-plane
column of the linear part is not determined); SE(3) and SIM(3) need points that
are not collinear (else the rotation about their line is not determined). The
estimator (:class:`~quick_stream.core.motion.MotionEstimator`) falls back from GA(3)
to SIM(3) and from SA(3) to SE(3) when the affine part is unobservable
(:data:`RIGID_FALLBACK`), and marks the motion invalid when even the rigid part is.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..lie import LieGroup, so3


@dataclass
class ExactParams:
    """Parameters of the exact estimator."""

    init_iters: int = 30  # at most this many IRLS iterations of the closed-form fit (stops when converged)
    gn_iters: int = 15  # at most this many robust Gauss-Newton iterations (stops when converged)
    sigma_px: float = 0.5  # expected optical-flow error (px)
    depth_noise: float = 0.0015  # depth sigma = depth_noise * z^2 (m); Kinect/RealSense-like
    robust: bool = True  # Cauchy reweighting; False = plain weighted least squares (for comparison)
    cauchy_c: float = 2.385  # Cauchy constant (95 % efficiency), in units of the robust scale
    max_scale: float = 2.0  # cap on the IRLS robust scale, in units of the expected noise
    min_points: int = 12  # fewer surviving pairs: motion invalid
    damping: float = 1e-6  # Levenberg damping relative to the normal matrix diagonal
    tol: float = 0.1  # converged: an iteration moved no point by more than tol x its expected error (3a)
    max_spread_error: float = 3e-3  # observability (3b): largest predicted error of the linear part
    gn_max_scale: float = 1.25  # cap on the Gauss-Newton's robust scale (units of the expected noise), (3a)

    @classmethod
    def describe(cls) -> dict[str, str]:
        return {f.name: repr(f.default) for f in fields(cls)}


def cauchy_weights(r: np.ndarray, c: float, max_scale: float = np.inf) -> tuple[np.ndarray, float]:
    """Cauchy IRLS weights for normalised residuals ``r``.

    Scale = 1.4826 * median(r) (MAD), capped at ``max_scale``: residuals are in
    units of the expected noise, so the cap keeps a majority of moving pixels
    (MAD breaks down past 50 % outliers) from widening the kernel until the
    estimate follows them.
    """
    s = min(1.4826 * float(np.median(r)), max_scale) + 1e-12
    return 1.0 / (1.0 + (r / (c * s)) ** 2), s


def _weighted_means(x: np.ndarray, y: np.ndarray, w: np.ndarray):
    wn = w / w.sum()
    mx = wn @ x
    my = wn @ y
    return wn, mx, my


def fit_closed_form(group_name: str, x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least-squares M with y ~ M x, closed form per group (docs/method.md section 2.2).

    SE(3): Kabsch; SIM(3): Umeyama (with scale); GA(3): linear least squares;
    SA(3): the GA(3) fit with its linear part scaled to unit determinant.
    """
    wn, mx, my = _weighted_means(x, y, w)
    xc, yc = x - mx, y - my
    M = np.eye(4)
    if group_name in ("se3", "sim3"):
        H = (xc * wn[:, None]).T @ yc  # weighted cross-covariance sum w x y^T
        R = so3.nearest_rotation(H.T)  # Kabsch: the rotation maximising tr(R H)
        A = R
        if group_name == "sim3":
            var_x = float(wn @ np.einsum("ni,ni->n", xc, xc))
            A = R * (float(np.trace(R @ H)) / var_x)  # Umeyama: tr(R H) = tr(D S)
    elif group_name in ("ga3", "sa3"):
        C = (xc * wn[:, None]).T @ xc  # 3x3
        B = (yc * wn[:, None]).T @ xc  # 3x3
        A = np.linalg.solve(C.T, B.T).T  # A C = B
        if group_name == "sa3":
            det = np.linalg.det(A)
            if det <= 0:
                raise np.linalg.LinAlgError("affine fit has det <= 0, not in SA(3)")
            A = A / np.cbrt(det)
    else:
        raise ValueError(f"unknown group {group_name!r}")
    M[:3, :3] = A
    M[:3, 3] = my - A @ mx
    return M


def point_sigma(x: np.ndarray, f: float, params: ExactParams) -> np.ndarray:
    """Expected 3D error sigma_i of each RGB-D point: depth noise along the ray, flow noise across it
    (docs/method.md (3a))."""
    z = x[:, 2]
    return np.hypot(params.depth_noise * z * z, z * params.sigma_px / f)


def irls_closed_form(
    group_name: str, x: np.ndarray, y: np.ndarray, w0: np.ndarray, params: ExactParams, f: float = 500.0
) -> tuple[np.ndarray, np.ndarray]:
    """IRLS over :func:`fit_closed_form`: Cauchy weights on the 3D residual in units of :func:`point_sigma`.

    Iterates until the fit moves no point by more than ``params.tol`` of its expected error,
    at most ``params.init_iters`` times (docs/method.md (3a)). Returns (M, weights of the last fit).
    """
    w = w0.copy()
    M = fit_closed_form(group_name, x, y, w)
    sig = point_sigma(x, f, params)
    for _ in range(params.init_iters if params.robust else 0):
        r = np.linalg.norm(x @ M[:3, :3].T + M[:3, 3] - y, axis=1) / sig
        rw, _ = cauchy_weights(r, params.cauchy_c, params.max_scale)
        w = w0 * rw
        M_new = fit_closed_form(group_name, x, y, w)
        D = M_new - M
        step = float(np.max(np.linalg.norm(x @ D[:3, :3].T + D[:3, 3], axis=1) / sig))
        M = M_new
        if step < params.tol:
            break
    return M, w


@dataclass
class Observability:
    """How well the weighted point spread determines a group's linear part (docs/method.md (3b)).

    ``rho``: eigenvalues of the weighted covariance C of the points about their weighted mean,
    in units of the mean squared expected point error (largest first); ``n_eff``: the effective
    number of points (sum w)^2 / sum w^2. ``affine_error`` / ``rigid_error``: the predicted
    relative error of the linear part along its worst-determined direction, eps(rho3) and
    eps(rho2 + rho3), eps(r) = 1/r + 1/sqrt(n_eff r) (bias from the noise in the points plus
    one standard error).
    """

    rho: np.ndarray
    n_eff: float
    affine_error: float
    rigid_error: float

    def error(self, group_name: str) -> float:
        """The predicted linear-part error that decides whether ``group_name``'s fit is determined."""
        return self.affine_error if group_name in ("ga3", "sa3") else self.rigid_error


def _spread_error(r: float, n_eff: float) -> float:
    """eps(r) = 1/r + 1/sqrt(n_eff r), docs/method.md (3b); inf when there is no spread."""
    if not r > 0:
        return float("inf")
    return 1.0 / r + 1.0 / np.sqrt(n_eff * r)


def observability(x: np.ndarray, w: np.ndarray, f: float, params: ExactParams) -> Observability:
    """The spread test of docs/method.md (3b) for points ``x`` with weights ``w`` (focal length ``f`` px).

    rho_k = lambda_k(C) / s^2 with C = sum w_n (x - m)(x - m)^T (w_n = w / sum w, m = sum w_n x)
    and s^2 = sum w_n sigma^2 (:func:`point_sigma`): the spread along each principal axis in
    units of the expected error of a point. GA(3)/SA(3) need rho_3 (the out-of-plane spread):
    the noise in x biases the affine column along e_3 by about 1/rho_3 (errors in variables) and
    its standard error is 1/sqrt(n_eff rho_3). SE(3)/SIM(3) rotate about e_1 with spread rho_2 + rho_3
    around that axis (collinear points: 0).
    """
    w = np.asarray(w, float)
    sw = float(w.sum())
    if not (len(x) and sw > 0 and np.isfinite(sw)):
        return Observability(np.zeros(3), 0.0, float("inf"), float("inf"))
    wn = w / sw
    xc = x - wn @ x
    C = (xc * wn[:, None]).T @ xc
    s2 = float(wn @ point_sigma(x, f, params) ** 2)
    rho = np.clip(np.linalg.eigvalsh(C)[::-1] / s2, 0.0, None)
    n_eff = 1.0 / float(wn @ wn)
    return Observability(
        rho, n_eff, _spread_error(float(rho[2]), n_eff), _spread_error(float(rho[1] + rho[2]), n_eff)
    )


RIGID_FALLBACK = {"ga3": "sim3", "sa3": "se3"}
"""The group fitted instead when an affine group's linear part is unobservable (docs/method.md 2.3).

SIM(3) is the largest of the four groups inside GA(3) whose fit a plane determines; SA(3) has
det = 1, which a similarity only meets at scale 1, so SE(3)."""


@dataclass
class RefineResult:
    M: np.ndarray
    weights: np.ndarray  # final robust weights (0..1) times the input weights
    rms_px: float  # robust scale of the image residual (px)
    inlier_ratio: float  # share of pairs with weight > 0.5
    iterations: int = 0  # Gauss-Newton steps taken
    converged: bool = True  # False: stopped at params.gn_iters before the step fell below params.tol


def refine_reprojection(
    group: LieGroup,
    M: np.ndarray,
    x: np.ndarray,
    p1: np.ndarray,
    z1: np.ndarray,
    K1: np.ndarray,
    w0: np.ndarray,
    params: ExactParams,
) -> RefineResult:
    """Robust Gauss-Newton on image-plane + depth residuals, left updates in ``group``'s basis.

    Residuals per pair (all dimensionless, docs/method.md (3)): ((u - u1), (v - v1)) / sigma_px and
    (Z - z1) / (depth_noise z1^2), with (u, v, Z) the projection of M x through
    ``K1``. Jacobian column k of M x is (E_k [M x; 1])[:3]. The Cauchy weights are recomputed
    at every iterate; iteration stops when the step changes no pair's residual by more than
    ``params.tol`` (max_i |J_i delta| < tol, docs/method.md (3a)) or after ``params.gn_iters`` steps.
    The returned weights belong to the returned M.
    """
    fx, fy, cx, cy = K1[0, 0], K1[1, 1], K1[0, 2], K1[1, 2]
    n = group.dim
    # dy/d delta = E_k [y; 1]: as one matmul, yh (N, 4) @ Ecat (4, 3n) -> (N, 3, n)
    Ecat = np.ascontiguousarray(group.basis[:, :3, :].transpose(2, 1, 0).reshape(4, 3 * n))
    sz = params.depth_noise * z1 * z1
    w = w0
    rw = np.ones(len(x))
    converged = False
    steps = 0
    while True:
        y = x @ M[:3, :3].T + M[:3, 3]
        X, Y, Z = y[:, 0], y[:, 1], y[:, 2]
        iz = 1.0 / Z
        ru = (fx * X * iz + cx - p1[:, 0]) / params.sigma_px
        rv = (fy * Y * iz + cy - p1[:, 1]) / params.sigma_px
        rz = (Z - z1) / sz
        e = np.sqrt(ru * ru + rv * rv + rz * rz)
        rw = cauchy_weights(e, params.cauchy_c, params.gn_max_scale)[0] if params.robust else np.ones_like(e)
        w = w0 * rw
        if converged or steps >= params.gn_iters:
            break
        # dy/d delta_k = E_k [y; 1] -> (N, 3, n)
        yh = np.concatenate([y, np.ones((len(y), 1))], 1)
        dy = (yh @ Ecat).reshape(-1, 3, n)
        a = fx * iz / params.sigma_px
        b = fy * iz / params.sigma_px
        Ju = a[:, None] * (dy[:, 0] - (X * iz)[:, None] * dy[:, 2])
        Jv = b[:, None] * (dy[:, 1] - (Y * iz)[:, None] * dy[:, 2])
        Jz = dy[:, 2] / sz[:, None]
        sw = np.sqrt(w)[:, None]
        J = np.concatenate([Ju * sw, Jv * sw, Jz * sw], 0)
        r = np.concatenate([ru, rv, rz]) * np.concatenate([sw[:, 0]] * 3)
        A = J.T @ J
        A[np.diag_indices(n)] *= 1.0 + params.damping
        delta = -np.linalg.solve(A, J.T @ r)
        M = group.exp(delta) @ M
        steps += 1
        # (3a): the largest change of a pair's (unweighted, normalised) residual this step makes
        du, dv, dz = Ju @ delta, Jv @ delta, Jz @ delta
        converged = bool(np.max(du * du + dv * dv + dz * dz) < params.tol * params.tol)
    img = np.hypot(ru, rv) * params.sigma_px
    rms_px = float(np.sqrt(np.sum(w * img * img) / max(np.sum(w), 1e-12)))
    return RefineResult(M=M, weights=w, rms_px=rms_px, inlier_ratio=float(np.mean(rw > 0.5)),
                        iterations=steps, converged=converged)

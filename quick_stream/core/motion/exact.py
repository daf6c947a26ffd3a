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
from ..robust import median


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
    s = min(1.4826 * median(r), max_scale) + 1e-12
    return 1.0 / (1.0 + (r / (c * s)) ** 2), s


def _norms(d: np.ndarray) -> np.ndarray:
    """Euclidean norm of each column of a (3, N) array."""
    return np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])


def fit_closed_form(group_name: str, xt: np.ndarray, yt: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least-squares M with y ~ M x, closed form per group (docs/method.md section 2.2).

    ``xt``, ``yt``: the points as (3, N) arrays (one row per coordinate). SE(3): Kabsch; SIM(3):
    Umeyama (with scale); GA(3): linear least squares; SA(3): the GA(3) fit with its linear part
    scaled to unit determinant.
    """
    wn = w / w.sum()
    mx, my = xt @ wn, yt @ wn
    xc, yc = xt - mx[:, None], yt - my[:, None]
    xw = xc * wn
    M = np.eye(4)
    if group_name in ("se3", "sim3"):
        H = xw @ yc.T  # weighted cross-covariance sum w x y^T
        R = so3.nearest_rotation(H.T)  # Kabsch: the rotation maximising tr(R H)
        A = R
        if group_name == "sim3":
            var_x = float(np.sum(xw * xc))
            A = R * (float(np.trace(R @ H)) / var_x)  # Umeyama: tr(R H) = tr(D S)
    elif group_name in ("ga3", "sa3"):
        C = xw @ xc.T  # 3x3
        B = yc @ xw.T  # 3x3
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
    z = np.ascontiguousarray(x[:, 2])
    a, b = params.depth_noise * z * z, z * (params.sigma_px / f)
    return np.sqrt(a * a + b * b)


def irls_closed_form(
    group_name: str, x: np.ndarray, y: np.ndarray, w0: np.ndarray, params: ExactParams, f: float = 500.0
) -> tuple[np.ndarray, np.ndarray]:
    """IRLS over :func:`fit_closed_form`: Cauchy weights on the 3D residual in units of :func:`point_sigma`.

    Iterates until the fit moves no point by more than ``params.tol`` of its expected error,
    at most ``params.init_iters`` times (docs/method.md (3a)). Returns (M, weights of the last fit).
    """
    xt, yt = np.ascontiguousarray(x.T), np.ascontiguousarray(y.T)
    w = w0.copy()
    M = fit_closed_form(group_name, xt, yt, w)
    sig = point_sigma(x, f, params)
    for _ in range(params.init_iters if params.robust else 0):
        r = _norms(M[:3, :3] @ xt + M[:3, 3:] - yt) / sig
        rw, _ = cauchy_weights(r, params.cauchy_c, params.max_scale)
        w = w0 * rw
        M_new = fit_closed_form(group_name, xt, yt, w)
        D = M_new - M
        step = float(np.max(_norms(D[:3, :3] @ xt + D[:3, 3:]) / sig))
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
    xt = np.ascontiguousarray(x.T)
    xc = xt - (xt @ wn)[:, None]
    C = (xc * wn) @ xc.T
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

# (m, m') -> row of the per-point matrices Q in _normal_equations (5: Q[0, 1] = Q[1, 0] = 0)
_Q_INDEX = np.array([[0, 5, 1], [5, 2, 3], [1, 3, 4]])
_UPPER = np.triu_indices(4, 1)  # (l, l') above the diagonal


def _normal_equations(B: np.ndarray, y: np.ndarray, xn: np.ndarray, yn: np.ndarray, a: np.ndarray,
                      b: np.ndarray, isz: np.ndarray, w: np.ndarray, ru: np.ndarray, rv: np.ndarray,
                      rz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton normal equations ``A = sum_i w_i J_i^T J_i``, ``g = sum_i w_i J_i^T r_i`` of the
    residuals (3), summed in the points' own 3D space (docs/method.md (3h)).

    ``J_i = P_i B(y_i)``: ``P_i`` the residuals' 3x3 Jacobian at the moved point ``y_i`` (rows
    ``a (1, 0, -xn)``, ``b (0, 1, -yn)``, ``isz (0, 0, 1)``), ``B(y) = sum_l yh_l B_l`` the point's
    (3, n) Jacobian of the left update with ``yh = (y, 1)`` and ``B_l[m, k] = E_k[m, l]`` (``B``:
    the B_l stacked, (12, n)). Then ``A = sum_{l,l'} B_l^T S_{ll'} B_l'`` with
    ``S_{ll'} = sum_i yh_il yh_il' Q_i``, ``Q_i = w_i P_i^T P_i``, and ``g = sum_l B_l^T T_l`` with
    ``T_l = sum_i yh_il w_i P_i^T r_i``: a few sums over the points instead of a (3N, n) Jacobian.
    """
    aw2, bw2 = a * a * w, b * b * w
    Q = np.empty((5, len(w)))  # the distinct entries of Q_i: 00, 02, 11, 12, 22
    Q[0] = aw2
    np.multiply(aw2, -xn, out=Q[1])
    Q[2] = bw2
    np.multiply(bw2, -yn, out=Q[3])
    Q[4] = aw2 * xn * xn + bw2 * yn * yn + isz * isz * w
    s = np.empty((3, len(w)))  # w_i P_i^T r_i
    np.multiply(a * w, ru, out=s[0])
    np.multiply(b * w, rv, out=s[1])
    s[2] = isz * w * rz - xn * s[0] - yn * s[1]
    G = np.zeros((4, 4, 6))  # sum_i yh_l yh_l' Q_i (the 5 entries and a zero)
    for l in range(3):
        G[l, l:3, :5] = (y[l:] * y[l]) @ Q.T
    G[:3, 3, :5] = y @ Q.T
    G[3, 3, :5] = Q.sum(axis=1)
    G[_UPPER[1], _UPPER[0]] = G[_UPPER]
    S = G[:, :, _Q_INDEX].transpose(0, 2, 1, 3).reshape(12, 12)  # [l, m], [l', m']
    T = np.empty((4, 3))
    T[:3] = y @ s.T
    T[3] = s.sum(axis=1)
    return B.T @ S @ B, B.T @ T.reshape(12)



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
    B = np.ascontiguousarray(group.basis[:, :3, :].transpose(2, 1, 0)).reshape(12, n)  # [l, m], k: E_k[m, l]
    xt = np.ascontiguousarray(x.T)
    isp = 1.0 / params.sigma_px
    u1, v1 = p1[:, 0] - cx, p1[:, 1] - cy  # the target pixels about the principal point
    isz = 1.0 / (params.depth_noise * z1 * z1)
    converged = False
    steps = 0
    while True:
        y = M[:3, :3] @ xt + M[:3, 3:]
        Z = y[2]
        iz = 1.0 / Z
        xn, yn = y[0] * iz, y[1] * iz
        ru = (fx * xn - u1) * isp
        rv = (fy * yn - v1) * isp
        rz = (Z - z1) * isz
        e = np.sqrt(ru * ru + rv * rv + rz * rz)
        rw = cauchy_weights(e, params.cauchy_c, params.gn_max_scale)[0] if params.robust else np.ones_like(e)
        w = w0 * rw
        if converged or steps >= params.gn_iters:
            break
        a = (fx * isp) * iz  # d ru / d X; d ru / d Z = -a xn
        b = (fy * isp) * iz
        A, g = _normal_equations(B, y, xn, yn, a, b, isz, w, ru, rv, rz)
        A[np.diag_indices(n)] *= 1.0 + params.damping
        delta = -np.linalg.solve(A, g)
        M = group.exp(delta) @ M
        steps += 1
        # (3a): the largest change of a pair's (unweighted, normalised) residual this step makes
        D = group.hat(delta)
        dyd = D[:3, :3] @ y + D[:3, 3:]  # dy/d delta . delta
        du = a * (dyd[0] - xn * dyd[2])
        dv = b * (dyd[1] - yn * dyd[2])
        dz = dyd[2] * isz
        converged = bool(np.max(du * du + dv * dv + dz * dz) < params.tol * params.tol)
    img2 = (ru * ru + rv * rv) * params.sigma_px ** 2  # squared image residual, px^2
    rms_px = float(np.sqrt(np.sum(w * img2) / max(np.sum(w), 1e-12)))
    return RefineResult(M=M, weights=w, rms_px=rms_px, inlier_ratio=float(np.mean(rw > 0.5)),
                        iterations=steps, converged=converged)

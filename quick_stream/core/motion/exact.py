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

Observability (docs/method.md section 2.3, equation (3b)): :func:`~.observability.observability`
measures the weighted spread of the points against their expected error. GA(3)
and SA(3) need spread in all three directions (on a plane the out-of-plane
column of the linear part is not determined); SE(3) and SIM(3) need points that
are not collinear (else the rotation about their line is not determined). The
estimator (:class:`~quick_stream.core.motion.MotionEstimator`) falls back from GA(3)
to SIM(3) and from SA(3) to SE(3) when the affine part is unobservable
(:data:`~.observability.RIGID_FALLBACK`), and marks the motion invalid when even the rigid part is.

SIM(3), SA(3) and GA(3) start from the SE(3) fit and keep to its consensus (:func:`refine_from_rigid`,
docs/method.md (3l), (3m)); their observability is tested on weights that carry the SE(3) fit's, so an
object moving in front of a wall cannot lend the affine fit the out-of-plane spread a wall lacks.
"""
from __future__ import annotations

from dataclasses import dataclass

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
    max_noise_scale: float = 10.0  # the pair's own image noise, measured (3i), at most this x sigma_px ...
    max_depth_scale: float = 1000.0  # ... and its depth noise at most this x depth_noise: depth that lags or is
    # garbage is weighted down until it decides nothing (depth only ever adds information), docs/method.md (3i)



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


_QUANTILE = {(1, 0.25): 0.31863936396437515,  # lower quartile of |r| for r ~ N(0, 1) (half-normal)
             (1, 0.5): 0.6744897501960817,  # its median
             (2, 0.25): float(np.sqrt(-2.0 * np.log(0.75))),  # lower quartile of |r| for r ~ N(0, I_2) (Rayleigh)
             (2, 0.5): float(np.sqrt(-2.0 * np.log(0.5)))}  # its median


def noise_scale(r: np.ndarray, dims: int, cap: float, q: float = 0.25) -> float:
    """A residual channel's noise in units of the expected (docs/method.md (3i)): the ``q`` quantile of
    the magnitudes ``r`` (of ``dims``-dimensional residuals) over that of normal noise, at least 1
    (never tighter than expected) and at most ``cap``. The image channel takes the lower quartile,
    which stays within 1.55x the noise when half the pairs move with something else (bounded up to
    three quarters);
    the depth channel the median, which also sees an error spread over the whole frame (depth that
    lags the colour or is offset from it)."""
    n = len(r)
    if n < 8 or not cap > 1.0:
        return 1.0
    k = int(q * n)
    v = float(np.partition(r, k)[k])
    return min(max(v / _QUANTILE[dims, q], 1.0), cap) if np.isfinite(v) else 1.0


@dataclass
class RefineResult:
    M: np.ndarray
    weights: np.ndarray  # final robust weights (0..1) times the input weights
    rms_px: float  # robust scale of the image residual (px)
    inlier_ratio: float  # share of pairs with weight > 0.5
    iterations: int = 0  # Gauss-Newton steps taken
    converged: bool = True  # False: stopped at params.gn_iters before the step fell below params.tol
    covariance: np.ndarray | None = None  # (n, n) of the left update delta at M, docs/method.md (3k)
    spread_weights: np.ndarray | None = None  # what (3b) is tested on when not ``weights``: (3l), (3m)

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
    A = None
    while True:
        y = M[:3, :3] @ xt + M[:3, 3:]
        Z = y[2]
        iz = 1.0 / Z
        xn, yn = y[0] * iz, y[1] * iz
        ru = (fx * xn - u1) * isp
        rv = (fy * yn - v1) * isp
        rz = (Z - z1) * isz
        s_img = noise_scale(np.sqrt(ru * ru + rv * rv), 2, params.max_noise_scale)
        s_z = noise_scale(np.abs(rz), 1, params.max_depth_scale, 0.5)
        ru, rv, rz = ru / s_img, rv / s_img, rz / s_z
        e = np.sqrt(ru * ru + rv * rv + rz * rz)
        rw = cauchy_weights(e, params.cauchy_c, params.gn_max_scale)[0] if params.robust else np.ones_like(e)
        w = w0 * rw
        a = (fx * isp / s_img) * iz  # d ru / d X; d ru / d Z = -a xn
        b = (fy * isp / s_img) * iz
        if converged or steps >= params.gn_iters:
            break
        A, g = _normal_equations(B, y, xn, yn, a, b, isz / s_z, w, ru, rv, rz)
        delta = -np.linalg.solve(A + np.diag(np.diag(A) * params.damping), g)
        M = group.exp(delta) @ M
        steps += 1
        # (3a): the largest change of a pair's (unweighted, normalised) residual this step makes
        D = group.hat(delta)
        dyd = D[:3, :3] @ y + D[:3, 3:]  # dy/d delta . delta
        du = a * (dyd[0] - xn * dyd[2])
        dv = b * (dyd[1] - yn * dyd[2])
        dz = dyd[2] * isz / s_z
        converged = bool(np.max(du * du + dv * dv + dz * dz) < params.tol * params.tol)
    img2 = (ru * ru + rv * rv) * (params.sigma_px * s_img) ** 2  # squared image residual, px^2
    rms_px = float(np.sqrt(np.sum(w * img2) / max(np.sum(w), 1e-12)))
    if A is None or steps:  # the normal matrix at the returned M (the loop's last one is the step's start)
        A = _normal_equations(B, y, xn, yn, a, b, isz / s_z, w, ru, rv, rz)[0]
    return RefineResult(M=M, weights=w, rms_px=rms_px, inlier_ratio=float(np.mean(rw > 0.5)),
                        iterations=steps, converged=converged, covariance=fit_covariance(A, w, e))


def consensus_cost_change(rigid: RefineResult, M: np.ndarray, x: np.ndarray, p1: np.ndarray, z1: np.ndarray,
                          K1: np.ndarray, params: ExactParams) -> float:
    """Delta C of docs/method.md (3l): sum_i w_i c_i (rho(e_i(M)) - rho(e_i(M_R))) over the SE(3) fit
    ``rigid``'s final weights w_i c_i, rho the Cauchy loss at the Gauss-Newton's capped scale, e_i = |r_i|
    of (3) over the noise (3i) measured at M_R. Positive: ``M`` explains that consensus worse than M_R."""
    def residuals(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        y = x @ A[:3, :3].T + A[:3, 3]
        ru = (K1[0, 0] * y[:, 0] / y[:, 2] + K1[0, 2] - p1[:, 0]) / params.sigma_px
        rv = (K1[1, 1] * y[:, 1] / y[:, 2] + K1[1, 2] - p1[:, 1]) / params.sigma_px
        return np.sqrt(ru * ru + rv * rv), np.abs(y[:, 2] - z1) / (params.depth_noise * z1 * z1)

    (img_r, z_r), (img_g, z_g) = residuals(rigid.M), residuals(M)
    s_img = noise_scale(img_r, 2, params.max_noise_scale)
    s_z = noise_scale(z_r, 1, params.max_depth_scale, 0.5)
    k2 = (params.cauchy_c * params.gn_max_scale) ** 2
    rho_r = np.log1p(((img_r / s_img) ** 2 + (z_r / s_z) ** 2) / k2)
    rho_g = np.log1p(((img_g / s_img) ** 2 + (z_g / s_z) ** 2) / k2)
    return 0.5 * k2 * float(rigid.weights @ (rho_g - rho_r))


def refine_from_rigid(group: LieGroup, rigid: RefineResult, x: np.ndarray, p1: np.ndarray, z1: np.ndarray,
                      K1: np.ndarray, w0: np.ndarray, params: ExactParams) -> RefineResult:
    """A group larger than SE(3), started at the SE(3) fit ``rigid`` of the same pairs (weights ``w0``)
    and kept to its consensus, docs/method.md (3l), (3m): :func:`refine_reprojection` from ``rigid.M``
    on ``w0``, taken when it explains the rigid fit's consensus no worse than ``rigid`` (3l); else its
    extra freedom went to pairs that move with something else, and it is refitted on ``w0 c_R c_G``
    (3m; inliers: ``c_R > 0.5`` and ``c_G > 0.5``). ``spread_weights``: ``w0 c_R c_G``, what (3b) is
    tested on."""
    c_r = np.divide(rigid.weights, w0, out=np.zeros_like(rigid.weights), where=w0 > 0)
    ref = refine_reprojection(group, rigid.M, x, p1, z1, K1, w0, params)
    if not consensus_cost_change(rigid, ref.M, x, p1, z1, K1, params) <= 0.0:  # NaN: refit
        ref = refine_reprojection(group, rigid.M, x, p1, z1, K1, rigid.weights, params)
        c_g = np.divide(ref.weights, rigid.weights, out=np.zeros_like(c_r), where=rigid.weights > 0)
        ref.inlier_ratio = float(np.mean((c_r > 0.5) & (c_g > 0.5)))
        ref.spread_weights = ref.weights
    else:
        ref.spread_weights = ref.weights * c_r
    return ref


def fit_covariance(A: np.ndarray, w: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Covariance of the Gauss-Newton's left update at its solution, docs/method.md (3k):
    ``A^-1`` times the weighted residual variance per residual (normalised residuals: 1 when the
    measured noise is right), at least 1. Infinite where ``A`` is singular."""
    sw = float(np.sum(w))
    var = max(float(np.sum(w * e * e)) / max(3.0 * sw - len(A), 1e-12), 1.0) if sw > 0 else np.inf
    try:
        return np.linalg.inv(A) * var
    except np.linalg.LinAlgError:
        return np.full(A.shape, np.inf)

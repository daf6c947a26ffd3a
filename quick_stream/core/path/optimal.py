"""Optimal stabilizing path on one keyframe segment (docs/method.md section 4).

Composition order (see docs/conventions.md): the camera path is g_c(t+1) = g_c(t) g(xi_t)
with g(xi_t) = T_t^-1 T_{t+1} the camera motion. The stabilizing transformation g_s(t)
is the pose of the virtual (stabilized) camera relative to the real one, so the
stabilized camera is g_c(t) g_s(t), and a point with real-camera coordinates x has
virtual-camera coordinates g_s(t)^-1 x. It integrates on the right (docs/method.md (4)):

    g_s(t0) = C0,    g_s(t+1) = g_s(t) exp(zeta(t)),    g_s(tf) = C1 (end-constraints).

``zeta_bar(t) = log(g(xi_t)^-1)`` undoes the frame's motion (docs/method.md (5):
[-A^-1 v; sigma^-1(A^-1)]); with zeta = zeta_bar the stabilized camera stays at the
segment's first pose to first order. The solver minimises docs/method.md (5)

    J = 1/2 sum_t |zeta(t) - zeta_bar(t)|_W^2   subject to the end-constraints.

Its optimality conditions are the discrete Euler-Poincare equation in multiplier form,
docs/method.md (6):

    W (zeta_t - zeta_bar_t) = J_r(zeta_t)^T lam_t,   lam_{t-1} = Ad(exp(zeta_t)^-1)^T lam_t,

with lam_{N-1} = mu, the multiplier of the end-constraint. :func:`solve_segment` solves
(6) and the end-constraint together by Newton's method on (zeta, mu) with the Jacobian of
docs/method.md (6a): the transport and the chart Jacobians are re-linearised at every
iterate (nothing is frozen); only the chart-curvature block K_t comes from a Taylor model
(finite differences when a step converges slowly), so convergence is quadratic up to a
tiny linear rate. It starts from the commuting closed form zeta = zeta_bar + c,
docs/method.md (6b), and a backtracking line search on the residual accepts each step.
If Newton does not converge the segment gets a fallback path that still meets the
end-constraint (docs/method.md 4.1).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..lie import LieGroup


@dataclass
class PathParams:
    """Parameters of the segment solver."""

    weights: tuple[float, ...] = ()  # diagonal of W per twist component; empty = identity
    max_iters: int = 15  # Newton iterations on the optimality conditions (6) + end-constraint
    tol: float = 1e-10  # max |stationarity residual of (6)| / W and |end-constraint residual| that count as met
    fd_step: float = 1e-7  # finite-difference step on the twist for the derivative of J_r (6a)
    init_iters: int = 30  # Newton iterations of the commuting closed form (6b) (start and fallback)

    def weight_vector(self, n: int) -> np.ndarray:
        if not self.weights:
            return np.ones(n)
        w = np.asarray(self.weights, dtype=np.float64)
        if w.shape != (n,) or np.any(w <= 0) or not np.all(np.isfinite(w)):
            raise ValueError(f"path weights must be {n} positive numbers, got {self.weights}")
        return w


@dataclass
class PathSolution:
    """Result of :func:`solve_segment` for a segment of N frame steps.

    ``converged``: the optimality conditions (6) and the end-constraint hold to ``tol``.
    Otherwise ``fallback`` names the path returned instead when it meets the end-constraint
    ("commuting": zeta_bar + c of docs/method.md (6b); "shifted iterate": the last Newton
    iterate shifted by a constant c onto the end-constraint), and is "" when no path
    could meet it (then ``corrections`` are not usable and ``residual`` says by how much).
    """

    zeta: np.ndarray  # (N, n)
    corrections: np.ndarray  # (N+1, 4, 4): g_s at the segment's frames t0..tf
    cost: float  # J
    residual: float  # |log(C1^-1 g_s(tf))|
    iterations: int  # Newton iterations on (6)
    converged: bool
    reason: str = ""
    multiplier: np.ndarray = field(default_factory=lambda: np.zeros(0))
    fallback: str = ""
    init_iterations: int = 0  # Newton iterations of the commuting closed form (6b)


def zeta_bar(group: LieGroup, motions: np.ndarray) -> np.ndarray:
    """(N, 4, 4) camera motions -> (N, n) twists of their inverses (docs/method.md (5))."""
    return group.log(group.inverse(np.asarray(motions, dtype=np.float64)))


def path_cost(zeta: np.ndarray, zbar: np.ndarray, w: np.ndarray) -> float:
    """J = 1/2 sum |zeta - zeta_bar|_W^2 with W = diag(w) (docs/method.md (5))."""
    d = zeta - zbar
    return 0.5 * float(np.sum(d * d * w))


def integrate(group: LieGroup, C0: np.ndarray, zeta: np.ndarray) -> np.ndarray:
    """g_s(t0) = C0, g_s(t+1) = g_s(t) exp(zeta(t)); (N, n) -> (N+1, 4, 4) (docs/method.md (4))."""
    E = group.exp(zeta)
    out = np.empty((len(zeta) + 1, 4, 4))
    out[0] = C0
    for t in range(len(zeta)):
        out[t + 1] = out[t] @ E[t]
    return out


@dataclass
class _Linearisation:
    """Everything (6) and the end-constraint need at one iterate ``zeta``.

    ``Phi[t] = Ad(B_t^-1)`` with ``B_t = exp(zeta_{t+1}) ... exp(zeta_{N-1})`` (the backward
    transport of (6) in closed form: lam_t = Phi[t]^T mu); ``A[t] = Phi[t] J_r(zeta_t)``: a right
    perturbation d of zeta_t moves the product exp(zeta_0)...exp(zeta_{N-1}) by exp(A[t] d) on the
    right. ``X = target^-1 prod`` and the end-constraint residual ``c = vee(X - I)`` (e in (6a):
    zero exactly when the constraint holds near X = I, log(X) to first order, free of the
    numerical SA(3)/GA(3) log).
    """

    Jr: np.ndarray  # (N, n, n)
    Phi: np.ndarray  # (N, n, n)
    A: np.ndarray  # (N, n, n)
    X: np.ndarray  # (4, 4)
    c: np.ndarray  # (n,)


def _linearise(group: LieGroup, zeta: np.ndarray, target_inv: np.ndarray) -> _Linearisation:
    N = len(zeta)
    E = group.exp(zeta)
    B = np.empty((N + 1, 4, 4))  # B[t] = exp(zeta_t) ... exp(zeta_{N-1}), B[N] = I
    B[N] = np.eye(4)
    for t in range(N - 1, -1, -1):
        B[t] = E[t] @ B[t + 1]
    Jr = group.right_jacobian(zeta)
    Phi = group.Ad(group.inverse(B[1:]))
    X = target_inv @ B[0]
    return _Linearisation(Jr, Phi, Phi @ Jr, X, group.vee(X - np.eye(4)))


def _stationarity(zeta: np.ndarray, zbar: np.ndarray, w: np.ndarray, mu: np.ndarray,
                  lin: _Linearisation) -> np.ndarray:
    """F_t = W (zeta_t - zeta_bar_t) - J_r(zeta_t)^T lam_t, lam_t = Phi_t^T mu: (6) holds iff F = 0."""
    return (zeta - zbar) * w - np.einsum("tji,j->ti", lin.A, mu)


def _merit(F: np.ndarray, c: np.ndarray, w: np.ndarray) -> float:
    """Half the squared residual of Newton's system (F scaled by W^-1 to twist units)."""
    return 0.5 * float(np.sum((F / w) ** 2) + c @ c)


def _constraint_jacobian_left(group: LieGroup, X: np.ndarray) -> np.ndarray:
    """Q with Q[:, k] = vee(X E_k): c = vee(X - I) moves by Q d when X -> X exp(d) (Q = I at c = 0)."""
    return np.swapaxes(group.vee(X @ group.basis), -1, -2)


_TAYLOR: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # group name -> J_r's derivatives at 0


def _jr_taylor(group: LieGroup) -> tuple[np.ndarray, np.ndarray]:
    """First and second derivatives of J_r at 0 in the linear coordinates: (m, n, n), (m, m, n, n).

    Central differences, once per group. J_r(zeta) ~ I + sum_j u_j D1_j + 1/2 sum_jk u_j u_k D2_jk.
    """
    if group.name not in _TAYLOR:
        n = group.dim
        m = n - 3
        e = np.eye(n)[3:]
        h1, h2 = 1e-5, 1e-4
        D1 = (group.right_jacobian(h1 * e) - group.right_jacobian(-h1 * e)) / (2 * h1)
        pp = h2 * (e[:, None] + e[None, :])
        pm = h2 * (e[:, None] - e[None, :])
        J = group.right_jacobian(np.stack([pp, pm, -pm, -pp]).reshape(-1, n)).reshape(4, m, m, n, n)
        D2 = (J[0] - J[1] - J[2] + J[3]) / (4 * h2 * h2)
        _TAYLOR[group.name] = (D1, D2)
    return _TAYLOR[group.name]


def _chart_curvature_model(group: LieGroup, zeta: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """K_t of :func:`_chart_curvature` from J_r's second-order Taylor model at 0 (error O(|u|^2 |lam|))."""
    D1, D2 = _jr_taylor(group)
    N, n = zeta.shape
    K = np.zeros((N, n, n))
    K[:, :, 3:] = np.einsum("jai,ta->tij", D1, lam) + np.einsum("tk,jkai,ta->tij", zeta[:, 3:], D2, lam)
    return K


def _chart_curvature(group: LieGroup, zeta: np.ndarray, Jr: np.ndarray, lam: np.ndarray,
                     h: float) -> np.ndarray:
    """K_t = d(J_r(zeta)^T lam_t)/d zeta at zeta_t (N, n, n), by forward differences.

    Every chart here is ``[[sigma(u), t], [0, 1]]`` (docs/conventions.md), so J_r depends on
    the linear coordinates u = zeta[3:] only and the translation columns of K are zero.
    """
    N, n = zeta.shape
    Z = zeta[:, None, :] + h * np.eye(n)[None, 3:]  # (N, n-3, n)
    Jp = group.right_jacobian(Z)  # (N, n-3, n, n)
    base = np.einsum("tki,tk->ti", Jr, lam)
    K = np.zeros((N, n, n))
    K[:, :, 3:] = (np.einsum("tjki,tk->tij", Jp, lam) - base[:, :, None]) / h
    return K


def _newton_step(group: LieGroup, lin: _Linearisation, F: np.ndarray, w: np.ndarray, mu: np.ndarray,
                 K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Newton step (dzeta, dmu) on F = 0, c = 0 with the Jacobian of docs/method.md (6a).

    dF_t/dzeta_t = W - K_t, dF_t/dzeta_s = A_t^T M(mu) A_s for s > t (0 for s < t),
    dF_t/dmu = -A_t^T, dc/dzeta_s = Q A_s, with M(mu) x = ad(x)^T mu. The zeta block is
    block upper triangular plus a rank structure, so H^-1 is a backward sweep carrying
    S = sum_{s>t} A_s x_s; the end-constraint row then gives an n x n system for dmu.
    """
    N, n = F.shape
    M = np.einsum("ikj,k->ji", group.ad(np.eye(n)), mu)  # column i: ad(e_i)^T mu
    Dinv = np.linalg.inv(np.diag(w)[None] - K)
    A = lin.A
    Y = Dinv @ np.concatenate([-F[:, :, None], np.swapaxes(A, 1, 2)], axis=2)  # (N, n, n+1)
    DA = Dinv @ np.swapaxes(A, 1, 2)
    S = np.zeros((n, n + 1))
    for t in range(N - 1, -1, -1):
        Y[t] -= DA[t] @ (M @ S)
        S += A[t] @ Y[t]
    QS = _constraint_jacobian_left(group, lin.X) @ S  # sum_t Q A_t Y_t
    dmu = np.linalg.solve(QS[:, 1:], -lin.c - QS[:, 0])
    return Y[:, :, 0] + Y[:, :, 1:] @ dmu, dmu


def _shift_onto_constraint(group: LieGroup, zeta0: np.ndarray, target_inv: np.ndarray, tol: float,
                           max_iters: int) -> tuple[np.ndarray, _Linearisation, int, bool]:
    """zeta0 + c with the constant c that meets the end-constraint (docs/method.md (6b)).

    Newton on the n unknowns c with the exact Jacobian Q sum_t A_t, a backtracking line
    search on |X - I|_F (X = target^-1 prod; vee(X - I) also vanishes at half-turns, this
    does not), and, while X is far from I, the residual log(X) with its Jacobian
    J_r(log X)^-1 sum_t A_t instead of vee(X - I). Returns (zeta, its linearisation,
    iterations, |vee(X - I)| <= tol).
    """
    c = np.zeros(zeta0.shape[1])
    lin = _linearise(group, zeta0, target_inv)
    eye = np.eye(4)
    r = float(np.linalg.norm(lin.X - eye))
    for it in range(max_iters + 1):
        if r < 1.0 and np.linalg.norm(lin.c) <= tol:
            return zeta0 + c, lin, it, True
        if it == max_iters:
            break
        if np.abs(lin.X - eye).max() > 0.5:
            res = group.log(lin.X)
            jac = np.linalg.solve(group.right_jacobian(res), lin.A.sum(axis=0))
        else:
            res = lin.c
            jac = _constraint_jacobian_left(group, lin.X) @ lin.A.sum(axis=0)
        d = np.linalg.solve(jac, -res)
        a = 1.0
        while True:
            trial = _linearise(group, zeta0 + c + a * d, target_inv)
            rt = float(np.linalg.norm(trial.X - eye))
            if rt < (1.0 - 1e-4 * a) * r or a < 1e-6:
                break
            a *= 0.5
        if not rt < r:
            break
        c, lin, r = c + a * d, trial, rt
    return zeta0 + c, lin, it, False


@dataclass
class _NewtonResult:
    zeta: np.ndarray
    mu: np.ndarray
    converged: bool
    iterations: int
    init_iterations: int
    stationarity: float  # max |F / w| at the end
    end: float  # |vee(X - I)| at the end
    why: str  # why it stopped without converging


def _newton(group: LieGroup, zbar: np.ndarray, w: np.ndarray, target_inv: np.ndarray,
            p: PathParams) -> _NewtonResult:
    """Newton's method on (6) and the end-constraint (docs/method.md (6a), section 4.1).

    Start: the commuting closed form (6b) (to 1e-6 only: Newton meets the end-constraint
    too) and mu fitted to (6) there by least squares. Each step solves the linearised
    system (:func:`_newton_step`) with the chart-curvature block K from J_r's Taylor model,
    or by finite differences once a step contracted the residual less than 100-fold; a
    backtracking (Armijo) line search on the merit accepts it (the Newton direction is a
    descent direction of the merit).
    """
    N, n = zbar.shape
    zeta, mu = zbar.copy(), np.zeros(n)
    it = init_its = 0
    stat = end = np.inf
    try:
        zeta, lin, init_its, _ = _shift_onto_constraint(group, zbar, target_inv, max(p.tol, 1e-6), p.init_iters)
        At = np.swapaxes(lin.A, 1, 2).reshape(N * n, n)
        mu = np.linalg.lstsq(At, np.tile(w * (zeta[0] - zbar[0]), N), rcond=None)[0]
        F = _stationarity(zeta, zbar, w, mu, lin)
        phi = _merit(F, lin.c, w)
        exact_k = False
        while True:
            stat, end = float(np.abs(F / w).max()), float(np.linalg.norm(lin.c))
            if stat <= p.tol and end <= p.tol:
                return _NewtonResult(zeta, mu, True, it, init_its, stat, end, "")
            if it == p.max_iters:
                why = "iteration limit"
                break
            it += 1
            lam = np.einsum("tji,j->ti", lin.Phi, mu)
            K = (_chart_curvature(group, zeta, lin.Jr, lam, p.fd_step) if exact_k
                 else _chart_curvature_model(group, zeta, lam))
            dz, dm = _newton_step(group, lin, F, w, mu, K)
            a = 1.0
            while True:
                zt, mt = zeta + a * dz, mu + a * dm
                try:
                    lt = _linearise(group, zt, target_inv)
                    Ft = _stationarity(zt, zbar, w, mt, lt)
                    # a trial far from the end-constraint is refused: vee(X - I) also vanishes at half-turns
                    pt = _merit(Ft, lt.c, w) if np.abs(lt.X - np.eye(4)).max() < 0.5 else np.inf
                except (ValueError, np.linalg.LinAlgError, FloatingPointError):
                    pt = np.inf
                if pt <= (1.0 - 1e-4 * a) * phi or a < 1e-6:
                    break
                a *= 0.5
            if not pt < phi:
                why = "line search stalled"
                break
            exact_k = exact_k or a < 1.0 or pt > 1e-2 * phi
            zeta, mu, lin, F, phi = zt, mt, lt, Ft, pt  # every accepted step lowers the merit
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as e:
        why = f"solver failed: {e}"
    return _NewtonResult(zeta, mu, False, it, init_its, stat, end, why)


def solve_segment(
    group: LieGroup,
    motions: np.ndarray,
    C0: np.ndarray | None = None,
    C1: np.ndarray | None = None,
    params: PathParams | None = None,
    zbar: np.ndarray | None = None,
) -> PathSolution:
    """Optimal corrections g_s over one segment (docs/method.md section 4).

    ``motions``: the segment's N camera motions g(xi_t) (N, 4, 4); ``C0``/``C1``: the
    corrections required at the opening and closing keyframes (identity by default,
    the paper's choice). ``zbar`` may pass precomputed zeta_bar twists.
    """
    p = params or PathParams()
    n = group.dim
    w = p.weight_vector(n).astype(np.float64)
    C0 = np.eye(4) if C0 is None else np.asarray(C0, dtype=np.float64)
    C1 = np.eye(4) if C1 is None else np.asarray(C1, dtype=np.float64)
    zbar = zeta_bar(group, motions) if zbar is None else np.asarray(zbar, dtype=np.float64)
    N = len(zbar)
    if N == 0:
        raise ValueError("a segment needs at least one frame step")
    target_inv = group.inverse(group.inverse(C0) @ C1)  # required product: exp(zeta_0)...exp(zeta_{N-1})

    newton = _newton(group, zbar, w, target_inv, p)
    zeta, mu, converged, reason = newton.zeta, newton.mu, newton.converged, ""
    fallback = ""
    if not converged:
        reason = (f"optimality residual {newton.stationarity:.2e}, end-constraint residual {newton.end:.2e} "
                  f"after {newton.iterations} Newton iterations ({newton.why})")
        zeta, fallback = _fallback(group, zbar, w, target_inv, p, newton.zeta if newton.iterations else None)
        reason += (f"; fallback: the {fallback} path (docs/method.md 4.1)" if fallback
                   else "; no fallback path met the end-constraint")
    corrections = integrate(group, C0, zeta)
    try:
        res = float(np.linalg.norm(group.log(group.inverse(C1) @ corrections[-1])))
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        res = float("inf")
    return PathSolution(
        zeta=zeta,
        corrections=corrections,
        cost=path_cost(zeta, zbar, w),
        residual=res,
        iterations=newton.iterations,
        converged=converged,
        reason=reason,
        multiplier=mu,
        fallback=fallback,
        init_iterations=newton.init_iterations,
    )


def _fallback(group: LieGroup, zbar: np.ndarray, w: np.ndarray, target_inv: np.ndarray, p: PathParams,
              last: np.ndarray | None) -> tuple[np.ndarray, str]:
    """A path that meets the end-constraint when Newton did not converge (docs/method.md 4.1).

    Candidates: the commuting closed form (6b) and the last Newton iterate (the one with
    the smallest residual; None when Newton took no step) shifted by a constant onto the
    end-constraint; the one with the lower J wins. Returns (zeta, name), or (zeta_bar, "")
    when neither meets the end-constraint to ``p.tol``.
    """
    cands = []
    for start, name in ((zbar, "commuting"), (last, "shifted iterate")):
        if start is None:
            continue
        try:
            z, _, _, ok = _shift_onto_constraint(group, start, target_inv, p.tol, p.init_iters)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            continue
        if ok:
            cands.append((path_cost(z, zbar, w), z, name))
    if not cands:
        return zbar.copy(), ""
    _, z, name = min(cands, key=lambda c: c[0])
    return z, name

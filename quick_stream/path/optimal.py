"""Optimal stabilizing path on one keyframe segment (paper eqs. (path), (zeta_dot); design note section 4).

Composition order (see docs/conventions.md): the camera path is g_c(t+1) = g_c(t) g(xi_t)
with g(xi_t) = T_t^-1 T_{t+1} the camera motion. The stabilizing transformation g_s(t)
is the pose of the virtual (stabilized) camera relative to the real one, so the
stabilized camera is g_c(t) g_s(t), and a point with real-camera coordinates x has
virtual-camera coordinates g_s(t)^-1 x. It integrates on the right:

    g_s(t0) = C0,    g_s(t+1) = g_s(t) exp(zeta(t)),    g_s(tf) = C1 (end-constraints).

``zeta_bar(t) = log(g(xi_t)^-1)`` undoes the frame's motion (design note section 4:
[-A^-1 v; sigma^-1(A^-1)]); with zeta = zeta_bar the stabilized camera stays at the
segment's first pose to first order. The solver minimises

    J = 1/2 sum_t |zeta(t) - zeta_bar(t)|_W^2   subject to the end-constraints.

Its optimality conditions are the discrete Euler-Poincare equation in multiplier
form (design note: integrate lam = W zeta - b, b = W zeta_bar, instead of zeta):

    zeta(t) = W^-1 (b(t) + lam(t)),     lam(t-1) = Ad(exp(zeta(t))^-1)^T lam(t),

i.e. lam' = ad(zeta)^T lam integrated exactly over each frame step (the chart's
first-order Jacobian taken as the identity). The multiplier is integrated
backward from the segment's end, where it is the unknown ``mu``; shooting on
``mu`` with Newton steps and a finite-difference Jacobian (all n+1 perturbed
sweeps run as one batch) meets ``log(C1^-1 g_s(tf)) = 0``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ..lie import LieGroup


@dataclass
class PathParams:
    """Parameters of the segment solver."""

    weights: tuple[float, ...] | None = None  # diagonal of W per twist component; None = identity
    max_iters: int = 15  # Newton iterations of the shooting
    tol: float = 1e-10  # end-constraint residual norm that counts as met
    fd_step: float = 1e-6  # finite-difference step on the multiplier

    @classmethod
    def describe(cls) -> dict[str, str]:
        return {f.name: repr(f.default) for f in fields(cls)}

    def weight_vector(self, n: int) -> np.ndarray:
        if self.weights is None:
            return np.ones(n)
        w = np.asarray(self.weights, dtype=np.float64)
        if w.shape != (n,) or np.any(w <= 0) or not np.all(np.isfinite(w)):
            raise ValueError(f"path weights must be {n} positive numbers, got {self.weights}")
        return w


@dataclass
class PathSolution:
    """Result of :func:`solve_segment` for a segment of N frame steps."""

    zeta: np.ndarray  # (N, n)
    corrections: np.ndarray  # (N+1, 4, 4): g_s at the segment's frames t0..tf
    cost: float  # J
    residual: float  # |log(C1^-1 g_s(tf))|
    iterations: int
    converged: bool
    reason: str = ""
    multiplier: np.ndarray = field(default_factory=lambda: np.zeros(0))


def zeta_bar(group: LieGroup, motions: np.ndarray) -> np.ndarray:
    """(N, 4, 4) camera motions -> (N, n) twists of their inverses (design note section 4)."""
    return group.log(group.inverse(np.asarray(motions, dtype=np.float64)))


def path_cost(zeta: np.ndarray, zbar: np.ndarray, w: np.ndarray) -> float:
    """J = 1/2 sum |zeta - zeta_bar|_W^2 with W = diag(w) (paper eq. (path))."""
    d = zeta - zbar
    return 0.5 * float(np.sum(d * d * w))


def integrate(group: LieGroup, C0: np.ndarray, zeta: np.ndarray) -> np.ndarray:
    """g_s(t0) = C0, g_s(t+1) = g_s(t) exp(zeta(t)); (N, n) -> (N+1, 4, 4)."""
    E = group.exp(zeta)
    out = np.empty((len(zeta) + 1, 4, 4))
    out[0] = C0
    for t in range(len(zeta)):
        out[t + 1] = out[t] @ E[t]
    return out


def chain(E: np.ndarray) -> np.ndarray:
    """Products E_0 E_1 ... E_{N-1} for a batch: E (B, N, 4, 4) -> (B, 4, 4)."""
    P = E[:, 0].copy()
    for t in range(1, E.shape[1]):
        P = P @ E[:, t]
    return P


def linearize(group: LieGroup, zeta: np.ndarray, w: np.ndarray) -> np.ndarray:
    """G (N, n, n) with zeta_t(mu) = zeta_bar_t + G_t mu near ``zeta``.

    From the discrete optimality condition W (zeta_t - zeta_bar_t) = J_r(zeta_t)^T lam_t,
    lam_t = Ad(B_t^-1)^T mu, B_t = exp(zeta_{t+1}) ... exp(zeta_{N-1}): the multiplier
    transported backward from the segment's end (lam(t-1) = Ad(exp(zeta_t)^-1)^T lam(t),
    the Euler-Poincare equation lam' = ad(zeta)^T lam over one frame step).
    """
    N, n = zeta.shape
    A = group.Ad(group.inverse(group.exp(zeta)))  # (N, n, n)
    Jr = group.right_jacobian(zeta)  # (N, n, n)
    Phi = np.empty((N, n, n))
    Phi[N - 1] = np.eye(n)
    for t in range(N - 1, 0, -1):
        Phi[t - 1] = Phi[t] @ A[t]
    # G_t = W^-1 J_r,t^T Phi_t^T
    return np.einsum("tji,tkj->tik", Jr, Phi) / w[None, :, None]


def solve_segment(
    group: LieGroup,
    motions: np.ndarray,
    C0: np.ndarray | None = None,
    C1: np.ndarray | None = None,
    params: PathParams | None = None,
    zbar: np.ndarray | None = None,
) -> PathSolution:
    """Optimal corrections g_s over one segment (paper section "Optimal camera paths").

    ``motions``: the segment's N camera motions g(xi_t) (N, 4, 4); ``C0``/``C1``: the
    corrections required at the opening and closing keyframes (identity by default,
    the paper's choice). ``zbar`` may pass precomputed zeta_bar twists.
    """
    p = params or PathParams()
    n = group.dim
    w = p.weight_vector(n)
    C0 = np.eye(4) if C0 is None else np.asarray(C0, dtype=np.float64)
    C1 = np.eye(4) if C1 is None else np.asarray(C1, dtype=np.float64)
    zbar = zeta_bar(group, motions) if zbar is None else np.asarray(zbar, dtype=np.float64)
    N = len(zbar)
    if N == 0:
        raise ValueError("a segment needs at least one frame step")
    target = group.inverse(C0) @ C1  # required product exp(zeta_0)...exp(zeta_{N-1})
    target_inv = group.inverse(target)
    w = w.astype(np.float64)

    def residuals(prod: np.ndarray) -> np.ndarray:
        # vee(target^-1 prod - I): zero exactly when the end-constraint holds, equal to
        # log(target^-1 prod) to first order, and free of the numerical SA(3)/GA(3) log.
        return group.vee(target_inv @ prod - np.eye(4))

    mu = np.zeros(n)
    h = p.fd_step
    probes = np.vstack([np.zeros(n), h * np.eye(n)])  # (n+1, n)
    zeta = zbar.copy()
    reason = ""
    converged = False
    r = np.full(n, np.inf)
    it = 0
    try:
        for it in range(1, p.max_iters + 1):
            # Newton step on the end multiplier mu: zeta(mu) linearised at the current
            # iterate (transport and chart Jacobians vectorised over the segment), the
            # residual's Jacobian by finite differences, all probes in one batch.
            G = linearize(group, zeta, w)
            Z = zbar[None] + np.einsum("tij,bj->bti", G, mu + probes)  # (n+1, N, n)
            r_b = residuals(chain(group.exp(Z)))
            r = r_b[0]
            if np.linalg.norm(r) < p.tol:
                zeta = Z[0]
                converged = True
                break
            Jac = (r_b[1:] - r).T / h
            mu = mu + np.linalg.lstsq(Jac, -r, rcond=None)[0]
            zeta = zbar + np.einsum("tij,j->ti", G, mu)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as e:
        zeta = zbar.copy()
        reason = f"solver failed: {e}"
    if not converged and not reason:
        reason = f"end-constraint residual {np.linalg.norm(r):.2e} after {p.max_iters} iterations"
    corrections = integrate(group, C0, zeta)
    res = float(np.linalg.norm(group.log(group.inverse(C1) @ corrections[-1]))) if not reason.startswith(
        "solver failed") else float("inf")
    return PathSolution(
        zeta=zeta,
        corrections=corrections,
        cost=path_cost(zeta, zbar, w),
        residual=res,
        iterations=it,
        converged=converged,
        reason=reason,
        multiplier=mu,
    )

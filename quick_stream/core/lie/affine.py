"""SA(3) and GA(3) with the chart ``phi(U) = expm(U^T) expm(U - U^T)``.

docs/method.md (3f):
    exp(xi) = [[phi(U), t], [0, 1]],   U = sum_k u_k E~_k,   xi = [t(3), u(n-3)].
``phi`` is the Riemannian exponential of the left-invariant metric on GL(3) (Zacur et al. 2014)
and, unlike ``expm``, is surjective onto GL+(3) and SL(3). ``det phi(U) = e^{tr U}``, so the
trace-free sl(3) basis keeps SA(3) in SL(3).

Writing ``U = S + W`` (symmetric + skew): ``phi(U) = expm(S - W) expm(2W)``; the skew factor is a
rotation (batched Rodrigues, ``so3``), only ``expm(U^T)`` needs a general matrix exponential (batched, ``lie.expm``).

``phi`` has no closed-form inverse (docs/method.md 3.2):
:func:`phi_inverse` runs damped Gauss-Newton on the coordinates ``u`` with the analytic
Jacobian (Frechet derivative of expm via the block identity
``expm([[X, E], [0, X]]) = [[expm X, L(X, E)], [0, expm X]]``), started from a second-order
polar-decomposition guess, with a homotopy (continuation) fallback.
"""
from __future__ import annotations

import numpy as np

from . import so3
from .base import LieGroup
from .expm import expm as _expm

__all__ = ["SA3", "GA3", "phi", "phi_derivative", "phi_inverse"]

SL_DET_TOL = 1e-6  # |det A - 1| accepted by SA3.log (A is rescaled onto SL(3) before solving)


def phi(U: np.ndarray) -> np.ndarray:
    """``expm(U^T) expm(U - U^T)`` (docs/method.md (3f)); (..., 3, 3) -> (..., 3, 3)."""
    U = np.asarray(U, dtype=np.float64)
    return _expm(np.swapaxes(U, -1, -2)) @ so3.exp(so3.vee(U - np.swapaxes(U, -1, -2)))


def phi_derivative(U: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``phi(U)`` and its directional derivatives ``D phi(U)[E_k]`` for each ``E_k`` in ``dirs``.

    U (B, 3, 3), dirs (m, 3, 3) -> (phi (B, 3, 3), dphi (B, m, 3, 3)). Product rule on (3f):
    ``D phi[E] = L(U^T, E^T) expm(U - U^T) + expm(U^T) R hat(Jr(w) vee(E - E^T))``, where
    ``R = expm(U - U^T) = so3.exp(w)`` and L is the Frechet derivative of expm (block identity).
    """
    U = np.asarray(U, dtype=np.float64)
    B, m = U.shape[0], dirs.shape[0]
    X = np.swapaxes(U, -1, -2)
    blk = np.zeros((B, m, 6, 6))
    blk[:, :, :3, :3] = X[:, None]
    blk[:, :, 3:, 3:] = X[:, None]
    blk[:, :, :3, 3:] = np.swapaxes(dirs, -1, -2)
    big = _expm(blk.reshape(B * m, 6, 6)).reshape(B, m, 6, 6)
    eX = big[:, 0, :3, :3]
    L = big[:, :, :3, 3:]
    w = so3.vee(U - X)
    R = so3.exp(w)
    delta = so3.vee(dirs - np.swapaxes(dirs, -1, -2))  # (m, 3)
    dR = R[:, None] @ so3.hat(np.einsum("bij,mj->bmi", so3.right_jacobian(w), delta))
    return eX @ R, L @ R[:, None] + eX[:, None] @ dR


def _initial_guess(A: np.ndarray) -> np.ndarray:
    """Second-order guess for ``phi^-1(A)`` from the polar decomposition ``A = P Q``.

    BCH gives ``log phi(S + W) = U + [S, W] + O(3)`` and ``log(P Q) = S_P + K + [S_P, K]/2 + O(3)``
    with ``S_P = log P``, ``K = log Q``, hence ``U ~= S_P + K - [S_P, K] / 2``.
    """
    Us, sv, Vt = np.linalg.svd(A)
    SP = (Us * np.log(sv)[:, None, :]) @ np.swapaxes(Us, -1, -2)
    K = so3.hat(so3.log(Us @ Vt))
    return SP + K - 0.5 * (SP @ K - K @ SP)


def _newton(
    A: np.ndarray, u: np.ndarray, lin: np.ndarray, max_iter: int = 100
) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt / Gauss-Newton for ``phi(sum u_k lin_k) = A``, vectorised over the batch.

    Steps solve ``(J^T J + mu diag) du = -J^T r`` (capped at 1, max-abs, to keep expm finite).
    A step is accepted if ``|r|_F`` decreases (then ``mu /= 10``, -> Gauss-Newton). The Jacobian
    (one batched 6x6 expm per direction, the expensive part) is reused while the residual keeps
    shrinking at least 10x per step (chord steps need only ``phi``), and recomputed otherwise;
    a step rejected with a fresh Jacobian raises ``mu *= 8``. Returns (u, max-abs residual).
    """
    B, m = u.shape
    u = u.copy()
    tol_stop = 1e-15 * np.maximum(1.0, np.abs(A).max(axis=(-2, -1)))
    P, dP = phi_derivative(np.einsum("bk,kij->bij", u, lin), lin)
    r = (P - A).reshape(B, 9)
    J = np.swapaxes(dP.reshape(B, m, 9), -1, -2)  # (B, 9, m)
    cost = np.einsum("bi,bi->b", r, r)
    fresh = np.ones(B, dtype=bool)  # J was evaluated at the current u
    want = np.zeros(B, dtype=bool)  # recompute J before the next step
    mu = np.full(B, 1e-12)
    active = np.flatnonzero(np.abs(r).max(axis=-1) > tol_stop)
    eye = np.eye(m)
    for _ in range(max_iter):
        if active.size == 0:
            break
        redo = active[want[active]]
        if redo.size:
            _, dPr = phi_derivative(np.einsum("bk,kij->bij", u[redo], lin), lin)
            J[redo] = np.swapaxes(dPr.reshape(-1, m, 9), -1, -2)
            fresh[redo], want[redo] = True, False
        Ja, ra = J[active], r[active]
        Jt = np.swapaxes(Ja, -1, -2)
        JtJ = Jt @ Ja
        lam = mu[active] * np.trace(JtJ, axis1=1, axis2=2) / m + 1e-300
        du = -np.linalg.solve(JtJ + lam[:, None, None] * eye, (Jt @ ra[..., None]))[..., 0]
        big = np.abs(du).max(axis=-1)
        du *= np.minimum(1.0, 1.0 / np.maximum(big, 1e-300))[:, None]
        ut = u[active] + du
        rt = (phi(np.einsum("bk,kij->bij", ut, lin)) - A[active]).reshape(-1, 9)
        ct = np.einsum("bi,bi->b", rt, rt)
        was_fresh, old = fresh[active], cost[active]
        ok = ct < old
        acc, rej = active[ok], active[~ok]
        u[acc], r[acc], cost[acc] = ut[ok], rt[ok], ct[ok]
        mu[acc] = np.maximum(mu[acc] / 10.0, 1e-12)
        fresh[acc] = False
        want[acc] = ct[ok] > 1e-2 * old[ok]  # chord again only after a >10x residual reduction
        want[rej] = ~was_fresh[~ok]  # a failed chord step: refresh J and retry
        mu[rej[was_fresh[~ok]]] *= 8.0  # a failed Newton step: more damping
        rn = np.abs(r[active]).max(axis=-1)
        ts = tol_stop[active]
        # Quadratic convergence: after a full Newton step of size h the error is O(h^2), so a step
        # below 1e-8 with a small residual means the iterate is at round-off level already.
        small = was_fresh & (np.abs(du).max(axis=-1) <= 1e-8 * (1.0 + np.abs(ut).max(axis=-1)))
        done = np.where(
            ok,
            (rn <= ts) | (small & (rn <= 100.0 * ts)),
            (rn <= 100.0 * ts) | (was_fresh & (mu[active] > 1e12)),
        )
        active = active[~done]
    return u, np.abs(r).max(axis=-1)


def phi_inverse(
    A: np.ndarray, lin: np.ndarray, lin_vee: np.ndarray, tol: float = 1e-12
) -> np.ndarray:
    """Numerical inverse of phi (docs/method.md 3.2): coordinates ``u`` (B, m) with ``phi(sum u_k lin_k) = A``.

    A (B, 3, 3) must lie in the group spanned by ``lin`` (det > 0; det = 1 for sl(3)); ``lin_vee``
    (m, 9) is the pseudo-inverse giving coordinates from ``vec(U)``. Damped Gauss-Newton from
    :func:`_initial_guess`; elements that fail are retried by continuation along
    ``A(s) = expm(s log P) expm(s log Q)``, s in (0, 1]. Raises ValueError if the max-abs residual
    stays above ``tol * max(1, |A|_max)``.
    """
    A = np.asarray(A, dtype=np.float64)
    scale = np.maximum(1.0, np.abs(A).max(axis=(-2, -1)))
    U0 = _initial_guess(A)
    with np.errstate(over="ignore", invalid="ignore"):
        u, res = _newton(A, U0.reshape(-1, 9) @ lin_vee.T, lin)
    bad = np.flatnonzero(~(res <= tol * scale))
    for i in bad:  # continuation fallback, one element at a time
        Us, sv, Vt = np.linalg.svd(A[i])
        SP = (Us * np.log(sv)) @ Us.T
        k = so3.log(Us @ Vt)
        ui = np.zeros((1, lin.shape[0]))
        for n_steps in (8, 32, 128):
            ui = np.zeros((1, lin.shape[0]))
            ri = np.array([np.inf])
            for s in np.linspace(0.0, 1.0, n_steps + 1)[1:]:
                As = (_expm(s * SP) @ so3.exp(s * k))[None]
                with np.errstate(over="ignore", invalid="ignore"):
                    ui, ri = _newton(As, ui, lin)
            if ri[0] <= tol * scale[i]:
                break
        u[i], res[i] = ui[0], ri[0]
        if not res[i] <= tol * scale[i]:
            raise ValueError(
                f"phi_inverse did not converge for element {i}: residual {res[i]:.3g} "
                f"(tolerance {tol * scale[i]:.3g})"
            )
    return u


class _PhiGroup(LieGroup):
    """Shared implementation: R^3 x| H with H = SL(3) or GL+(3) and the chart of docs/method.md (3f)."""

    _special: bool = False

    def _U(self, xi: np.ndarray) -> np.ndarray:
        return np.einsum("...k,kij->...ij", xi[..., 3:], self.linear_basis)

    def _exp(self, xi: np.ndarray) -> np.ndarray:
        """``[[phi(U), t], [0, 1]]`` (docs/method.md (3f))."""
        g = np.zeros(xi.shape[:-1] + (4, 4))
        g[..., :3, :3] = phi(self._U(xi))
        g[..., :3, 3] = xi[..., :3]
        g[..., 3, 3] = 1.0
        return g

    def _check_det(self, A: np.ndarray, where: str) -> np.ndarray:
        det = np.linalg.det(A)
        if np.any(~(det > 0.0)):
            raise ValueError(
                f"{self.name}.{where}: linear part has det <= 0 (min {np.nanmin(det):.3g}); "
                f"not in GL+(3)"
            )
        if self._special and where == "log" and np.any(np.abs(det - 1.0) > SL_DET_TOL):
            bad = det[np.argmax(np.abs(det - 1.0))]
            raise ValueError(
                f"{self.name}.log: det of linear part is {bad:.9g}, not 1 (tolerance {SL_DET_TOL}); "
                f"not in SL(3) - use project() first"
            )
        return det

    def _log(self, g: np.ndarray) -> np.ndarray:
        """Translation, then ``phi^-1(A)`` by :func:`phi_inverse` (SA(3): A rescaled to det 1 first)."""
        self._check_affine(g)
        A = g[:, :3, :3]
        det = self._check_det(A, "log")
        if self._special:
            A = A / np.cbrt(det)[:, None, None]
        u = phi_inverse(A, self.linear_basis, self._lin_vee_mat)
        return np.concatenate([g[:, :3, 3], u], axis=-1)

    def _exp_derivative(self, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Translation columns are E_k; linear columns are ``D phi(U)[E~_k]`` (:func:`phi_derivative`)."""
        P, dP = phi_derivative(self._U(xi), self.linear_basis)
        g = np.zeros((xi.shape[0], 4, 4))
        g[:, :3, :3] = P
        g[:, :3, 3] = xi[:, :3]
        g[:, 3, 3] = 1.0
        dg = np.zeros((xi.shape[0], self.dim, 4, 4))
        dg[:, :3] = self.basis[:3]
        dg[:, 3:, :3, :3] = dP
        return g, dg

    def _project_linear(self, A: np.ndarray) -> np.ndarray:
        """SA(3): ``A / det(A)^(1/3)``; GA(3): ``A`` unchanged. Both require det(A) > 0."""
        det = self._check_det(A, "project")
        return A / np.cbrt(det)[:, None, None] if self._special else A.copy()


class SA3(_PhiGroup):
    """Special affine group R^3 x| SL(3), n = 11 (docs/method.md 3.1).

    sl(3) basis: hat(e1), hat(e2), hat(e3); the symmetric off-diagonals e2e3^T + e3e2^T,
    e1e3^T + e3e1^T, e1e2^T + e2e1^T (``|hat(e_k)|``, entrywise absolute value);
    diag(1, -1, 0), diag(0, 1, -1). Not orthonormal: vee uses the pseudo-inverse.
    """

    name = "sa3"
    _special = True

    def _linear_basis(self) -> np.ndarray:
        skew = [so3.hat(e) for e in np.eye(3)]
        sym = [np.abs(S) for S in skew]
        return np.stack(skew + sym + [np.diag([1.0, -1.0, 0.0]), np.diag([0.0, 1.0, -1.0])])


class GA3(_PhiGroup):
    """General (positive) affine group R^3 x| GL+(3), n = 12.

    gl(3) basis ``E~_k = e_m e_n^T`` in column-major order ``k = 3(n-1) + m`` (docs/method.md 3.1),
    so ``u = vec(U)`` (column-stacked).
    """

    name = "ga3"
    _special = False

    def _linear_basis(self) -> np.ndarray:
        lin = np.zeros((9, 3, 3))
        for k in range(9):
            lin[k, k % 3, k // 3] = 1.0
        return lin

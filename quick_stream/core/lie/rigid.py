"""SE(3) and SIM(3) with the decoupled exponential chart (docs/method.md (3e)).

Twist ``xi = [t(3), w(3)]`` (SE(3)) or ``[t(3), w(3), a]`` (SIM(3)); basis: translation
generators, then ``hat(e_1..3)``, then (SIM(3)) ``I_3``.

Charts (docs/method.md (3e)):
    SE(3):  exp(xi) = [[expm(hat w), t], [0, 1]]
    SIM(3): exp(xi) = [[e^a expm(hat w), t], [0, 1]]
i.e. translation is NOT coupled to rotation through the SE(3) V-matrix; log is closed form
``(t, log R[, ln s])`` with ``s = det(A)^(1/3)``, ``R = A / s``.

Chart Jacobians (derived from ``g^-1 dg`` and ``dg g^-1``; docs/method.md (3g)):
    J_r = blockdiag(e^-a R^T, Jr_SO3(w), 1)
    J_l = [[I, hat(t) Jl_SO3(w), -t], [0, Jl_SO3(w), 0], [0, 0, 1]]
(SE(3): drop the last row/column and set a = 0.)
"""
from __future__ import annotations

import numpy as np

from . import so3
from .base import LieGroup

__all__ = ["SE3", "SIM3"]

# Tolerance on |R^T R - I| accepted by log() (elements accumulated over long paths drift a little).
ORTHO_TOL = 1e-6


class _Rigid(LieGroup):
    """Shared implementation of SE(3) (``_scaled = False``) and SIM(3) (``_scaled = True``)."""

    _scaled: bool = False

    def _linear_basis(self) -> np.ndarray:
        lin = [so3.hat(e) for e in np.eye(3)]
        if self._scaled:
            lin.append(np.eye(3))
        return np.stack(lin)

    def _split(self, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = xi[..., 6] if self._scaled else np.zeros(xi.shape[:-1])
        return xi[..., :3], xi[..., 3:6], a

    def _exp(self, xi: np.ndarray) -> np.ndarray:
        """The decoupled chart ``[[e^a expm(hat w), t], [0, 1]]`` (docs/method.md (3e))."""
        t, w, a = self._split(xi)
        g = np.zeros(xi.shape[:-1] + (4, 4))
        g[..., :3, :3] = np.exp(a)[..., None, None] * so3.exp(w)
        g[..., :3, 3] = t
        g[..., 3, 3] = 1.0
        return g

    def _log(self, g: np.ndarray) -> np.ndarray:
        """Closed-form inverse of the decoupled chart: ``(t, log_SO3(A / s)[, ln s])``, ``s = det(A)^(1/3)``."""
        self._check_affine(g)
        A = g[:, :3, :3]
        det = np.linalg.det(A)
        if np.any(det <= 0.0):
            raise ValueError(
                f"{self.name}.log: linear part has det <= 0 (min {det.min():.3g}); not in {self.name}"
            )
        s = np.cbrt(det)
        if not self._scaled and np.any(np.abs(s - 1.0) > ORTHO_TOL):
            raise ValueError(f"{self.name}.log: det(R) = {det[np.argmax(np.abs(s - 1))]:.9g} != 1")
        R = A / s[:, None, None]
        err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
        if np.any(err > ORTHO_TOL):
            what = "A / det(A)^(1/3)" if self._scaled else "rotation part"
            raise ValueError(
                f"{self.name}.log: {what} is not orthonormal (|R^T R - I| = {err.max():.3g} > "
                f"{ORTHO_TOL}); use project() first"
            )
        parts = [g[:, :3, 3], so3.log(R)]
        if self._scaled:
            parts.append(np.log(s)[:, None])
        return np.concatenate(parts, axis=-1)

    def _exp_derivative(self, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``d exp / d xi_k``: translation -> E_k; rotation -> e^a R hat(Jr e_k); scale -> e^a R."""
        g = self._exp(xi)
        _, w, _ = self._split(xi)
        sR = g[:, :3, :3]
        dg = np.zeros((xi.shape[0], self.dim, 4, 4))
        dg[:, :3] = self.basis[:3]
        Jr = so3.right_jacobian(w)
        dg[:, 3:6, :3, :3] = sR[:, None] @ so3.hat(np.swapaxes(Jr, -1, -2))
        if self._scaled:
            dg[:, 6, :3, :3] = sR
        return g, dg

    def right_jacobian(self, xi: np.ndarray) -> np.ndarray:
        """Closed form ``J_r = blockdiag(e^-a R^T, Jr_SO3(w)[, 1])`` of the decoupled chart (module doc)."""
        xi = self._check_twist(xi)
        _, w, a = self._split(xi)
        J = np.zeros(xi.shape[:-1] + (self.dim, self.dim))
        J[..., :3, :3] = np.exp(-a)[..., None, None] * np.swapaxes(so3.exp(w), -1, -2)
        J[..., 3:6, 3:6] = so3.right_jacobian(w)
        if self._scaled:
            J[..., 6, 6] = 1.0
        return J

    def left_jacobian(self, xi: np.ndarray) -> np.ndarray:
        """Closed form ``J_l = [[I, hat(t) Jl, -t], [0, Jl, 0], [0, 0, 1]]`` (module doc)."""
        xi = self._check_twist(xi)
        t, w, _ = self._split(xi)
        J = np.zeros(xi.shape[:-1] + (self.dim, self.dim))
        Jl = so3.left_jacobian(w)
        J[..., :3, :3] = np.eye(3)
        J[..., :3, 3:6] = so3.hat(t) @ Jl
        J[..., 3:6, 3:6] = Jl
        if self._scaled:
            J[..., :3, 6] = -t
            J[..., 6, 6] = 1.0
        return J

    def _project_linear(self, A: np.ndarray) -> np.ndarray:
        """The nearest rotation (:func:`so3.nearest_rotation`), times the mean singular value for SIM(3)."""
        R = so3.nearest_rotation(A)
        if self._scaled:
            R = R * np.linalg.svd(A, compute_uv=False).mean(axis=-1)[:, None, None]
        return R


class SE3(_Rigid):
    """Rigid motions R^3 x| SO(3), n = 6, twist ``[t, w]`` (docs/method.md 3.1, (3e))."""

    name = "se3"
    _scaled = False


class SIM3(_Rigid):
    """Similarities R^3 x| (R+ x SO(3)), n = 7, twist ``[t, w, a]``, linear part ``e^a R``."""

    name = "sim3"
    _scaled = True

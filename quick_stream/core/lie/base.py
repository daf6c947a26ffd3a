"""Generic part of the affine matrix Lie groups used by QuICK.

Every group here is a subgroup of GA(3) = R^3 x| GL+(3), represented by 4x4 matrices
``g = [[A, t], [0, 0, 0, 1]]`` (docs/method.md 3.1). A group is defined by its Lie-algebra
basis ``E_1..E_n`` (docs/method.md (3c)): the first three are the translation generators
(``e_k`` in the last column), the rest span the linear part. Twist coordinates are therefore
``xi = [t(3), u(n-3)]`` (translation first), and ``hat``/``vee`` identify ``E_k`` with ``e_k``.

The exponential is a *decoupled* chart ``exp(xi) = [[sigma(u), t], [0, 1]]`` (docs/method.md
(3e) for SE(3)/SIM(3), (3f) for SA(3)/GA(3)), NOT ``expm(hat(xi))``.
Subclasses implement ``_exp``/``_log``/``_exp_derivative`` on flattened batches; everything else
(``ad``, ``Ad``, Jacobians, actions) is generic and vectorised over leading dimensions.

Structure follows manif/Sophus: one interface, one property-test suite (tests/unit/test_lie_groups.py).
"""
from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

__all__ = ["LieGroup", "translation_basis"]


def translation_basis() -> np.ndarray:
    """The three translation generators ``E_k = [[0, e_k], [0, 0]]`` (docs/method.md (3c), k <= 3)."""
    E = np.zeros((3, 4, 4))
    for k in range(3):
        E[k, k, 3] = 1.0
    return E


def _embed_linear(lin: np.ndarray) -> np.ndarray:
    """(m, 3, 3) linear generators -> (m, 4, 4) algebra elements ``[[E~, 0], [0, 0]]``."""
    E = np.zeros((lin.shape[0], 4, 4))
    E[:, :3, :3] = lin
    return E


class LieGroup(ABC):
    """Uniform interface of an affine matrix Lie group with its chart (docs/method.md section 3).

    Attributes:
        name: short key ("se3", "sim3", "sa3", "ga3").
        dim: number of twist coordinates ``n``.
        basis: (n, 4, 4) Lie-algebra basis ``E_k`` (translation generators first).
        linear_basis: (n-3, 3, 3) the linear parts ``E~_k`` of ``E_4..E_n``.
    """

    name: str = ""

    def __init__(self) -> None:
        lin = np.asarray(self._linear_basis(), dtype=np.float64)
        basis = np.concatenate([translation_basis(), _embed_linear(lin)], axis=0)
        n = basis.shape[0]
        B = basis.reshape(n, 16).T  # (16, n)
        if np.linalg.matrix_rank(B) != n:
            raise AssertionError(f"{type(self).__name__}: basis is linearly dependent")
        self.dim: int = n
        self.basis: np.ndarray = basis
        self.linear_basis: np.ndarray = lin
        # vee by least squares in the (possibly non-orthonormal) basis: coords = pinv(B) vec(X).
        self._vee_mat = np.linalg.pinv(B)  # (n, 16)
        self._lin_vee_mat = np.linalg.pinv(lin.reshape(n - 3, 9).T)  # (n-3, 9)
        for M in (basis, lin, self._vee_mat, self._lin_vee_mat):
            M.setflags(write=False)
        # Structure constants: C[i, j] = vee([E_i, E_j]), so ad(xi)[:, j] = sum_i xi_i C[i, j].
        comm = basis[:, None] @ basis[None, :] - basis[None, :] @ basis[:, None]
        self._struct = self.vee(comm)  # (n, n, n)

    def __repr__(self) -> str:
        return f"<LieGroup {self.name} dim={self.dim}>"

    # ------------------------------------------------------------------ subclass hooks
    @abstractmethod
    def _linear_basis(self) -> np.ndarray:
        """(n-3, 3, 3) generators of the linear part, in the order of docs/method.md 3.1."""

    @abstractmethod
    def _exp(self, xi: np.ndarray) -> np.ndarray:
        """(B, n) -> (B, 4, 4): the group's chart."""

    @abstractmethod
    def _log(self, g: np.ndarray) -> np.ndarray:
        """(B, 4, 4) -> (B, n): inverse of :meth:`_exp`; raise ValueError outside the group."""

    @abstractmethod
    def _exp_derivative(self, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, n) -> (g (B, 4, 4), dg (B, n, 4, 4)) with ``dg[:, k] = d exp(xi) / d xi_k``."""

    @abstractmethod
    def _project_linear(self, A: np.ndarray) -> np.ndarray:
        """(B, 3, 3) -> (B, 3, 3): nearest linear part in the group."""

    # ------------------------------------------------------------------ algebra
    def hat(self, xi: np.ndarray) -> np.ndarray:
        """(..., n) -> (..., 4, 4): ``sum_k xi_k E_k`` (docs/method.md (3c))."""
        xi = self._check_twist(xi)
        return np.einsum("...k,kij->...ij", xi, self.basis)

    def vee(self, X: np.ndarray) -> np.ndarray:
        """(..., 4, 4) -> (..., n): least-squares coordinates of ``X`` in the basis.

        Exact inverse of :meth:`hat` on the algebra; for ``X`` outside it, the coordinates of its
        Frobenius-orthogonal projection (the pseudo-inverse handles the non-orthonormal SA(3) basis).
        """
        X = np.asarray(X, dtype=np.float64)
        if X.shape[-2:] != (4, 4):
            raise ValueError(f"{self.name}.vee expects (..., 4, 4), got {X.shape}")
        return X.reshape(X.shape[:-2] + (16,)) @ self._vee_mat.T

    def ad(self, xi: np.ndarray) -> np.ndarray:
        """(..., n) -> (..., n, n): ``[ad(xi)]`` with column k = ``vee([hat(xi), E_k])``.

        docs/method.md (3d); the path solver's Jacobian uses it (docs/method.md (6a)).
        """
        xi = self._check_twist(xi)
        return np.einsum("...i,ijk->...kj", xi, self._struct)

    # ------------------------------------------------------------------ group
    def identity(self) -> np.ndarray:
        """The 4x4 identity."""
        return np.eye(4)

    def compose(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Group product ``a @ b`` (batched, broadcasting)."""
        return np.asarray(a, dtype=np.float64) @ np.asarray(b, dtype=np.float64)

    def inverse(self, g: np.ndarray) -> np.ndarray:
        """Affine inverse ``[[A^-1, -A^-1 t], [0, 1]]``; (..., 4, 4) -> (..., 4, 4)."""
        g = self._check_matrix(g)
        Ainv = np.linalg.inv(g[..., :3, :3])
        out = np.zeros_like(g)
        out[..., :3, :3] = Ainv
        out[..., :3, 3] = -np.einsum("...ij,...j->...i", Ainv, g[..., :3, 3])
        out[..., 3, 3] = 1.0
        return out

    def exp(self, xi: np.ndarray) -> np.ndarray:
        """(..., n) -> (..., 4, 4): the chart ``[[sigma(u), t], [0, 1]]`` (docs/method.md (3e), (3f))."""
        xi = self._check_twist(xi)
        lead = xi.shape[:-1]
        return self._exp(xi.reshape(-1, self.dim)).reshape(lead + (4, 4))

    def log(self, g: np.ndarray) -> np.ndarray:
        """(..., 4, 4) -> (..., n): inverse of :meth:`exp`. Raises ValueError outside the group."""
        g = self._check_matrix(g)
        lead = g.shape[:-2]
        return self._log(g.reshape(-1, 4, 4)).reshape(lead + (self.dim,))

    def Ad(self, g: np.ndarray) -> np.ndarray:
        """(..., 4, 4) -> (..., n, n): ``[Ad(g)]`` with column k = ``vee(g E_k g^-1)`` (docs/method.md (3d))."""
        g = self._check_matrix(g)
        gi = self.inverse(g)
        conj = g[..., None, :, :] @ self.basis @ gi[..., None, :, :]  # (..., n, 4, 4)
        return np.swapaxes(self.vee(conj), -1, -2)

    # ------------------------------------------------------------------ Jacobians of the chart
    def right_jacobian(self, xi: np.ndarray) -> np.ndarray:
        """(..., n) -> (..., n, n): ``log(exp(xi)^-1 exp(xi + d)) = J_r d + O(|d|^2)`` (docs/method.md (3g)).

        Generic: column k = ``vee(exp(xi)^-1 d exp / d xi_k)`` (every chart here has
        ``exp(d) = I + hat(d) + O(|d|^2)``, so ``log(I + X) = vee(X)`` to first order).
        """
        xi = self._check_twist(xi)
        lead = xi.shape[:-1]
        g, dg = self._exp_derivative(xi.reshape(-1, self.dim))
        M = self.inverse(g)[:, None] @ dg
        return np.swapaxes(self.vee(M), -1, -2).reshape(lead + (self.dim, self.dim))

    def left_jacobian(self, xi: np.ndarray) -> np.ndarray:
        """(..., n) -> (..., n, n): ``log(exp(xi + d) exp(xi)^-1) = J_l d + O(|d|^2)``.

        Generic: column k = ``vee(d exp / d xi_k exp(xi)^-1)``; ``J_l = Ad(exp(xi)) J_r``.
        """
        xi = self._check_twist(xi)
        lead = xi.shape[:-1]
        g, dg = self._exp_derivative(xi.reshape(-1, self.dim))
        M = dg @ self.inverse(g)[:, None]
        return np.swapaxes(self.vee(M), -1, -2).reshape(lead + (self.dim, self.dim))

    # ------------------------------------------------------------------ action on points
    def act(self, g: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Apply ``g`` to points: ``A x + t``. g (..., 4, 4), x (..., N, 3) -> (..., N, 3)."""
        g = self._check_matrix(g)
        x = np.asarray(x, dtype=np.float64)
        return x @ np.swapaxes(g[..., :3, :3], -1, -2) + g[..., None, :3, 3]

    def act_jacobian(self, g: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Derivative of ``exp(d) g x`` w.r.t. a LEFT perturbation ``d`` at ``d = 0``.

        Since ``exp(d) = I + hat(d) + O(|d|^2)`` in every chart here, this equals
        ``d/dd [(I + hat(d)) g x]``: column k is ``(E_k [y; 1])[:3]`` with ``y = g x``.
        g (4, 4), x (N, 3) -> (N, 3, n) (leading dims broadcast like :meth:`act`).
        """
        y = self.act(g, x)
        J = np.einsum("kij,...j->...ik", self.basis[:, :3, :3], y)
        return J + self.basis[:, :3, 3].T  # translation column of E_k, broadcast over points

    # ------------------------------------------------------------------ misc
    def random(self, rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
        """A random element ``exp(scale * N(0, I_n))`` (for tests)."""
        return self.exp(scale * rng.standard_normal(self.dim))

    def project(self, M: np.ndarray) -> np.ndarray:
        """Nearest group element to an affine matrix whose linear part is near the group.

        Keeps the translation column, resets the last row to ``[0, 0, 0, 1]`` and projects the
        linear part (group-specific, see ``_project_linear``). (..., 4, 4) -> (..., 4, 4).
        """
        M = self._check_matrix(M)
        lead = M.shape[:-2]
        M = M.reshape(-1, 4, 4)
        out = np.zeros_like(M)
        out[:, :3, :3] = self._project_linear(M[:, :3, :3])
        out[:, :3, 3] = M[:, :3, 3]
        out[:, 3, 3] = 1.0
        return out.reshape(lead + (4, 4))

    def _check_twist(self, xi: np.ndarray) -> np.ndarray:
        xi = np.asarray(xi, dtype=np.float64)
        if xi.ndim == 0 or xi.shape[-1] != self.dim:
            raise ValueError(f"{self.name}: twist must have shape (..., {self.dim}), got {xi.shape}")
        return xi

    def _check_matrix(self, g: np.ndarray) -> np.ndarray:
        g = np.asarray(g, dtype=np.float64)
        if g.ndim < 2 or g.shape[-2:] != (4, 4):
            raise ValueError(f"{self.name}: expected (..., 4, 4) matrices, got {g.shape}")
        return g

    def _check_affine(self, g: np.ndarray, tol: float = 1e-9) -> None:
        """Raise ValueError unless every matrix in the (B, 4, 4) batch has last row [0, 0, 0, 1]."""
        err = np.abs(g[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0)
        if err > tol:
            raise ValueError(f"{self.name}.log: last row is not [0, 0, 0, 1] (max deviation {err:.3g})")

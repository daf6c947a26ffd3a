"""The paper's estimator: the mean of induced twists (docs/method.md 2.1, (2a), (2), (2b)).

For an affine group with basis E_k = [[Et_k, t_k], [0, 0]],
the induced twist of a point x with displacement v is xi = Ad(h)^-T [v; 0] with
h = [[I, x/|x|^2], [0, 1]]. Worked out, its translation part is v and its
linear-part component k is v^T Et_k x / |x|^2. :func:`induced_twists` computes
that one general formula for any group; the definition (:func:`induced_twist_paper`) and the
per-group closed forms (:func:`closed_form_twists`) are kept only to test it.

The induced twist describes how the *points* move (x -> x + v), so the mean is
a point-motion twist; the camera motion is its inverse (see docs/conventions.md).
Known bias (docs/method.md 2.1): a pure roll comes back strongly
under-estimated and lateral motions are counted twice.
"""
from __future__ import annotations

import numpy as np

from ..lie import LieGroup


def induced_twists(group: LieGroup, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Induced twists (N, n) of points ``x`` (N, 3) with displacements ``v`` (N, 3).

    General formula of docs/method.md (2): translation part = v,
    component k of the linear part = v^T Et_k x / |x|^2.
    """
    lin = group.basis[3:, :3, :3]  # (n-3, 3, 3)
    r2 = np.einsum("ni,ni->n", x, x)
    u = np.einsum("ni,kij,nj->nk", v, lin, x) / r2[:, None]
    return np.concatenate([v, u], axis=1)


def induced_twist_paper(group: LieGroup, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """One induced twist straight from the paper's definition xi = Lambda^-T [v; 0], Lambda = Ad(h).

    docs/method.md (2a); slow, for tests of :func:`induced_twists`.
    """
    h = np.eye(4)
    h[:3, 3] = x / (x @ x)
    lam = group.Ad(h)
    rhs = np.zeros(group.dim)
    rhs[:3] = v
    return np.linalg.solve(lam.T, rhs)


def closed_form_twists(group_name: str, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The per-group closed forms of docs/method.md (2) (2.1), for tests of :func:`induced_twists`.

    SE(3): omega = x cross v / |x|^2; SIM(3): plus a = x.v / |x|^2; SA(3): omega,
    the symmetric part "|hat(x)| v" read as the symmetric matrix with x's entries
    (docs/method.md 2.1), then x^T E7 v and x^T E8 v; GA(3): vec(v x^T)/|x|^2
    (column-major).
    """
    r2 = np.einsum("ni,ni->n", x, x)[:, None]
    omega = np.cross(x, v) / r2
    if group_name == "se3":
        return np.concatenate([v, omega], 1)
    if group_name == "sim3":
        return np.concatenate([v, omega, np.einsum("ni,ni->n", x, v)[:, None] / r2], 1)
    if group_name == "sa3":
        # |hat(x)| = symmetric matrix with x's entries: [[0, x3, x2], [x3, 0, x1], [x2, x1, 0]]
        xs = np.zeros((len(x), 3, 3))
        xs[:, 1, 2] = xs[:, 2, 1] = x[:, 0]
        xs[:, 0, 2] = xs[:, 2, 0] = x[:, 1]
        xs[:, 0, 1] = xs[:, 1, 0] = x[:, 2]
        s = np.einsum("nij,nj->ni", xs, v) / r2
        e7 = (x[:, 0] * v[:, 0] - x[:, 1] * v[:, 1])[:, None] / r2
        e8 = (x[:, 1] * v[:, 1] - x[:, 2] * v[:, 2])[:, None] / r2
        return np.concatenate([v, omega, s, e7, e8], 1)
    if group_name == "ga3":
        u = np.einsum("ni,nj->nji", v, x).reshape(len(x), 9) / r2  # column-major vec(v x^T)
        return np.concatenate([v, u], 1)
    raise ValueError(f"no closed form for group {group_name!r}")


def estimate_induced(group: LieGroup, x: np.ndarray, v: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Point motion M (4x4) = exp(weighted mean induced twist) (docs/method.md (2b)).

    With unit weights this is exactly the paper's camera twist; the caller inverts
    it to get the camera motion.
    """
    xi = induced_twists(group, x, v)
    if w is None:
        mean = xi.mean(axis=0)
    else:
        mean = (w[:, None] * xi).sum(0) / w.sum()
    return group.exp(mean)

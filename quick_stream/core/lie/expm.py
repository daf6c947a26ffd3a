"""Vectorised matrix exponential for stacks of small matrices.

``scipy.linalg.expm`` loops in Python over a stack (about 8 us of overhead per
matrix), which dominated the SA(3)/GA(3) path solver. Here: scaling and squaring
with a degree-12 Taylor polynomial (Horner form) after scaling every matrix of
the batch by one common power of two so that the largest 1-norm is <= 1/4; the
truncation error is then below 0.25^13 / 13! ~ 2.4e-18 relative, and each of
the few squarings is one batched matmul. phi (docs/method.md (3f)) and the
Frechet-derivative block trick both call it.
"""
from __future__ import annotations

import numpy as np

_DEGREE = 12


def expm(X: np.ndarray) -> np.ndarray:
    """expm of every (k, k) matrix in a (..., k, k) stack."""
    X = np.asarray(X, dtype=np.float64)
    k = X.shape[-1]
    lead = X.shape[:-2]
    Xs = X.reshape(-1, k, k)
    if Xs.shape[0] == 0:
        return X.copy()
    norm = float(np.max(np.abs(Xs).sum(axis=-2), initial=0.0))  # max 1-norm over the batch
    if not np.isfinite(norm):
        raise FloatingPointError("expm: non-finite matrix entry")
    s = max(0, int(np.ceil(np.log2(norm / 0.25)))) if norm > 0.25 else 0
    A = Xs / (2.0 ** s)
    eye = np.eye(k)
    E = eye + A / _DEGREE
    for j in range(_DEGREE - 1, 0, -1):
        E = eye + (A @ E) / j
    for _ in range(s):
        E = E @ E
    return E.reshape(lead + (k, k))

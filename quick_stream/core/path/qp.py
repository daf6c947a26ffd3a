"""The crop budget's quadratic programs, solved in their duals (docs/method.md (11)).

min 1/2 (v - v0)^T H (v - v0) subject to C v >= d: :func:`dual_qp` on all the rows,
:func:`working_set_qp` on the rows that matter. Used by the budget's SQP (:mod:`.budget`) and the
border fill's zoom track (:mod:`.coverage`).
"""
from __future__ import annotations

from typing import Callable

import numpy as np


def dual_qp(C: np.ndarray, d: np.ndarray, HinvCt: np.ndarray, v0: np.ndarray,
            soft: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """min 1/2 (v - v0)^T H (v - v0) s.t. C v >= d, solved in its dual: y >= 0 minimising
    1/2 y^T C H^-1 C^T y - y^T (d - C v0) by non-negative least squares on the Cholesky factor,
    v = v0 + H^-1 C^T y (docs/method.md (11)). ``HinvCt``: H^-1 C^T. Returns (v, y).

    The dual's matrix gets 1e-10 of its mean diagonal on the rows ``soft`` (bool, default all):
    a quadratic penalty that keeps an infeasible set of those rows solvable, met as closely as it
    can be; the other rows hold exactly."""
    from scipy.optimize import nnls  # not at module level: only the motion stage needs it (PathPlanner loads it)

    M = C @ HinvCt
    eps = 1e-10 * max(float(np.trace(M)) / len(M), 1e-30)
    M[np.diag_indices_from(M)] += eps if soft is None else eps * soft
    L = np.linalg.cholesky(M)
    y, _ = nnls(L.T, np.linalg.solve(L, d - C @ v0), maxiter=50 * len(d))
    return v0 + HinvCt @ y, y


def working_set_qp(C: np.ndarray, d: np.ndarray, hinv_ct: Callable[[np.ndarray], np.ndarray], v0: np.ndarray,
                   soft: np.ndarray, start: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """:func:`dual_qp` (docs/method.md (11)) on a working set of the rows: first ``start`` (bool per row),
    then, while its answer breaks other rows by more than ``tol``, those too. A convex QP's answer under
    some of its constraints that meets the others is its answer under all, so this is :func:`dual_qp`'s
    answer (y 0 off the set), at the cost of the rows that matter. ``hinv_ct(rows)``: H^-1 rows^T.
    Returns (v, y)."""
    work = start.copy()
    while True:
        idx = np.flatnonzero(work)
        v, y_work = dual_qp(C[idx], d[idx], hinv_ct(C[idx]), v0, soft[idx])
        broken = ~work & (C @ v < d - tol)
        if not broken.any():
            y = np.zeros(len(d))
            y[idx] = y_work
            return v, y
        work |= broken

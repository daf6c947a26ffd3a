"""Observability of a fit: how well the points' spread determines a group's linear part (docs/method.md 2.3).

:func:`observability` measures the weighted spread of the points against their expected error (3b).
GA(3) and SA(3) need spread in all three directions (on a plane the out-of-plane column of the linear
part is not determined); SE(3) and SIM(3) need points that are not collinear (else the rotation about
their line is not determined). The estimator (:class:`~quick_stream.core.motion.MotionEstimator`) falls
back from GA(3) to SIM(3) and from SA(3) to SE(3) when the affine part is unobservable
(:data:`RIGID_FALLBACK`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .exact import ExactParams, point_sigma


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

"""The rotation-only fit of a scene flow's pixel pairs: the homography at infinity (docs/method.md (3j)).

A camera that only turns moves every pixel by ``K' R K^-1`` whatever its depth. So the flow says
how the camera turned even when the depth it was lifted with does not hold (noisy stereo depth,
depth that lags the colour, holes) or the group's full fit is not determined: the bearings
``b = K^-1 [p, 1] / |.|`` of a sample and ``b'`` of where the flow put it in the next frame satisfy
``b' = R b`` up to the parallax of the camera's translation. This is what a 2D stabiliser fits (a
similarity of the image is this rotation seen through a pinhole), so a 3D stabiliser that falls
back to it is never worse than one.

The fit is a weighted Kabsch on the bearings, reweighted with Cauchy weights on the angle between
``b'`` and ``R b`` in pixels (times the focal length) over the pair's own measured noise (the lower
quartile, as the full fit measures it, (3i)), iterated until the rotation moves by less than a
tenth of a pixel's angle. Its covariance is the inverse of the weighted normal matrix
``sum_i w_i (I - c_i c_i^T)``, ``c_i = R b_i``, times the noise's angle squared: the rotation about
the optical axis is the least determined (the bearings' spread about it is the field of view's).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..lie import so3
from .exact import ExactParams, cauchy_weights, noise_scale


@dataclass
class RotationFit:
    """A rotation-only fit: ``R`` maps bearings of frame t to frame t+1 (the point motion's rotation)."""

    R: np.ndarray  # (3, 3) point rotation, b' ~ R b
    covariance: np.ndarray  # (3, 3) of the rotation vector of a left perturbation exp(w) R (rad^2)
    inlier_ratio: float  # share of pairs with Cauchy weight > 0.5
    rms_px: float  # robust RMS of the angular residual, px
    weights: np.ndarray  # final weights (input weights times the Cauchy weights)

    @property
    def sigma(self) -> float:
        """RMS standard deviation of the rotation over its three axes (rad)."""
        return float(np.sqrt(np.trace(self.covariance) / 3.0))


def bearings(pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit bearing vectors ``K^-1 [p, 1] / |K^-1 [p, 1]|`` of pixels (N, 2): (N, 3)."""
    b = np.empty((len(pixels), 3))
    b[:, 0] = (pixels[:, 0] - K[0, 2]) / K[0, 0]
    b[:, 1] = (pixels[:, 1] - K[1, 2]) / K[1, 1]
    b[:, 2] = 1.0
    return b / np.sqrt(np.einsum("ij,ij->i", b, b))[:, None]


def fit_rotation(pixels: np.ndarray, pixels_next: np.ndarray, K: np.ndarray, K_next: np.ndarray,
                 w0: np.ndarray, params: ExactParams) -> RotationFit:
    """The robust rotation-only fit of docs/method.md (3j) to the pixel pairs (N, 2) -> (N, 2).

    ``w0``: the flow's weights. Raises ``np.linalg.LinAlgError`` when no weight is left."""
    b0, b1 = bearings(pixels, K), bearings(pixels_next, K_next)
    f = 0.5 * (K_next[0, 0] + K_next[1, 1])
    px = params.sigma_px / f  # one expected pixel error, as an angle
    w = np.asarray(w0, float).copy()
    R = np.eye(3)
    rw = np.ones(len(w))
    s = 1.0
    for _ in range(max(params.init_iters, 1)):
        if not w.sum() > 0:
            raise np.linalg.LinAlgError("no weight left for the rotation-only fit")
        R_new = so3.nearest_rotation(((b0 * w[:, None]).T @ b1).T)  # Kabsch: max sum w b1 . R b0
        step = float(np.linalg.norm(so3.log(R_new @ R.T)))
        R = R_new
        d = b1 - b0 @ R.T
        r = np.sqrt(np.einsum("ij,ij->i", d, d)) / px  # angle residual, in expected pixel errors
        s = noise_scale(r, 2, params.max_noise_scale)
        rw, _ = cauchy_weights(r / s, params.cauchy_c, params.max_scale)
        w = w0 * rw
        if step < params.tol * px:
            break
    c = b0 @ R.T
    N = w.sum() * np.eye(3) - (c * w[:, None]).T @ c  # sum w (I - c c^T)
    cov = np.linalg.inv(N) * (s * px) ** 2
    rms = float(np.sqrt(np.sum(w * r * r) / max(np.sum(w), 1e-300))) * params.sigma_px
    return RotationFit(R, cov, float(np.mean(rw > 0.5)), rms, w)

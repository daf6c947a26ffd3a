"""Batched SO(3) primitives: hat/vee, Rodrigues exp, robust log, Jacobians.

These are the rotational building blocks of the decoupled SE(3)/SIM(3) chart
(docs/method.md (3e)) and of the rotation factor of phi (docs/method.md (3f)).
Every function accepts arbitrary leading dimensions ``(...)`` and works in float64.

Conventions (the usual ones, e.g. Sola et al. 2018 "A micro Lie theory", Sophus):

* ``hat(a) @ b == np.cross(a, b)``;
* ``exp(w) = expm(hat(w))`` (Rodrigues);
* ``log`` returns the rotation vector with angle in ``[0, pi]``;
* right Jacobian: ``exp(w + d) = exp(w) exp(Jr(w) d) + O(|d|^2)``;
* left Jacobian:  ``exp(w + d) = exp(Jl(w) d) exp(w) + O(|d|^2)``, ``Jl(w) = Jr(-w) = Jr(w)^T``.
"""
from __future__ import annotations

import numpy as np

__all__ = ["hat", "vee", "exp", "log", "right_jacobian", "left_jacobian", "nearest_rotation", "polar_rotation"]

# Below this angle the trigonometric coefficients are evaluated by Taylor series.
_SMALL = 1e-4
# Above this angle (cos < about -0.995) log() recovers the axis from the symmetric part.
_NEAR_PI = np.pi - 0.1


def hat(w: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) skew matrix with ``hat(a) b = a x b`` (docs/method.md 3.1)."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def vee(W: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3): inverse of :func:`hat` applied to the skew part of ``W``."""
    W = np.asarray(W, dtype=np.float64)
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def _coeffs(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``sin(t)/t``, ``(1-cos t)/t^2``, ``(t-sin t)/t^3``, Taylor-expanded near 0."""
    t2 = theta * theta
    small = theta < _SMALL
    ts = np.where(small, 1.0, theta)  # safe divisor
    sn, cs = np.sin(ts), np.cos(ts)
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, sn / ts)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - cs) / (ts * ts))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (ts - sn) / (ts * ts * ts))
    return a, b, c


def exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula ``expm(hat(w)) = I + sin(t)/t W + (1-cos t)/t^2 W^2`` (docs/method.md 3.2).

    (..., 3) -> (..., 3, 3); Taylor coefficients for ``|w| < 1e-4``.
    """
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)
    a, b, _ = _coeffs(theta)
    W = hat(w)
    return np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of ``R`` (inverse of :func:`exp`, angle in ``[0, pi]``); (..., 3, 3) -> (..., 3).

    The angle comes from ``atan2(|vee(R - R^T)|/2, (tr R - 1)/2)``. Away from pi the axis is the
    skew part scaled by ``t / sin t`` (Taylor near 0); within 0.1 rad of pi, where the skew part
    vanishes, the axis is read off the symmetric part ``(R + R^T)/2 - cos(t) I = (1 - cos t) a a^T``
    and its sign taken from the skew part.
    """
    R = np.asarray(R, dtype=np.float64)
    s = vee(R)  # = sin(t) a
    sin_t = np.linalg.norm(s, axis=-1)
    cos_t = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(sin_t, cos_t)
    a, _, _ = _coeffs(theta)
    out = s / a[..., None]
    near_pi = theta > _NEAR_PI
    if np.any(near_pi):
        Rp, tp, sp = R[near_pi], theta[near_pi], s[near_pi]
        B = 0.5 * (Rp + np.swapaxes(Rp, -1, -2)) - np.cos(tp)[:, None, None] * np.eye(3)
        B = B / (1.0 - np.cos(tp))[:, None, None]  # ~ a a^T
        diag = np.diagonal(B, axis1=-2, axis2=-1)
        idx = np.argmax(diag, axis=-1)
        col = np.take_along_axis(B, idx[:, None, None], axis=-1)[..., 0]  # a * a_idx
        axis = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.einsum("ni,ni->n", axis, sp) < 0.0, -1.0, 1.0)
        out[near_pi] = (sign * tp)[:, None] * axis
    return out


def nearest_rotation(A: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) each 3x3 ``A``; (..., 3, 3) -> (..., 3, 3).

    ``A = U S V^T`` -> ``U diag(1, 1, det(U V^T)) V^T``: the orthogonal polar factor, its sign fixed
    so a reflection never comes out (Kabsch). For a rotation it is the rotation, for ``s R`` (SIM(3))
    exactly ``R``; of an affine part (SA(3), GA(3)) scale and shear are dropped. The one place the
    package projects onto SO(3): fits, reports, plots and the renderer's rotation reference.
    """
    U, _, Vt = np.linalg.svd(np.asarray(A, dtype=np.float64))
    return polar_rotation(U, Vt)


def polar_rotation(U: np.ndarray, Vt: np.ndarray) -> np.ndarray:
    """:func:`nearest_rotation` from the SVD factors ``U``, ``Vt`` of ``A`` (a caller that has them)."""
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0.0, 1.0, d)
    D = np.stack([np.ones_like(d), np.ones_like(d), d], axis=-1)
    return (U * D[..., None, :]) @ Vt


def right_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3) right Jacobian ``Jr(w) = I - (1-cos t)/t^2 W + (t - sin t)/t^3 W^2``; (..., 3) -> (..., 3, 3).

    ``exp(w + d) = exp(w) exp(Jr(w) d) + O(|d|^2)`` (Chirikjian 2011, vol. 2, eq. 10.86;
    the decoupled SE(3)/SIM(3) chart's Jacobian is built from it, docs/method.md (3g)).
    """
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)
    _, b, c = _coeffs(theta)
    W = hat(w)
    return np.eye(3) - b[..., None, None] * W + c[..., None, None] * (W @ W)


def left_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian ``Jl(w) = Jr(-w) = Jr(w)^T``; ``exp(w + d) = exp(Jl d) exp(w)`` to first order."""
    return right_jacobian(-np.asarray(w, dtype=np.float64))

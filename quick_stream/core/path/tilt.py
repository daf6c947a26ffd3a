"""A correction's tilt held to a cap, the rest of its turn given as an image shift (docs/method.md 4.5, (19)).

A correction g_s that turns the virtual camera's optical axis by θ away from the real one's renders
through the homography K R K^-1: a perspective warp whose affine part at the centre has the singular
value ratio cos θ (a keystone). Hand-held footage swings by 10-15°, and a stabilizer that removes
such a swing this way shows it as a distortion a 2D stabilizer, which removes the swing by shifting
the image, does not have. Above the cap θ_c the correction keeps turning the axis only up to a soft
limit and shifts the image for the rest, so that the image centre still lands where the whole turn
puts it:

    R = R_sw(n, θ) R_tw,   R' = R_sw(n, c(θ)) R_tw,   L' = R' S U,   S = [[1, 0, a], [0, 1, b], [0, 0, 1]]   (19)

with L = R U the linear part of g_s (its polar factors; U = I for SE(3)), R_sw the turn of the optical
axis about n = e_z x R e_z, R_tw the turn about it, and (a, b, 1) ∝ R_tw^T R_sw(n, c(θ))^T R e_z:
S moves a virtual-camera point by (a z, b z), so its image by (f_x a, f_y b) whatever its depth: a shift
of the output, not a parallax. c(θ) = θ up to θ_c - β and θ_c - β + β tanh((θ - θ_c + β) / β) above
(β = ``knee``; c and its slope are continuous). The translation is kept. Every stage that reads a
correction (the crop budget, the warp, the border fill) reads the capped one, so the crop planned is
the crop rendered.
"""
from __future__ import annotations

import numpy as np

from ..lie import so3
from ..render.shape_term import without_image_shift


def capped_angle(theta: np.ndarray, cap: float, knee: float) -> np.ndarray:
    """c(θ) of (19): θ below ``cap - knee``, then rising to ``cap`` with a continuous slope (radians)."""
    lo = cap - knee
    theta = np.asarray(theta, dtype=np.float64)
    return np.where(theta <= lo, theta, lo + knee * np.tanh((theta - lo) / max(knee, 1e-12)))


def tilt(corrections: np.ndarray) -> np.ndarray:
    """θ (...,) of each correction (..., 4, 4): the angle between the virtual and the real optical axis (rad)."""
    R = so3.nearest_rotation(np.asarray(corrections, dtype=np.float64)[..., :3, :3])
    return np.arccos(np.clip(R[..., 2, 2], -1.0, 1.0))


def _axis_angle_rotation(n: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) by ``angle`` (...,) about unit axes ``n`` (..., 3)."""
    return so3.exp(n * np.asarray(angle)[..., None])


def limit_tilt(corrections: np.ndarray, cap: float, knee: float) -> np.ndarray:
    """(19): ``corrections`` (..., 4, 4) with each tilt above ``cap - knee`` (radians) turned by c(θ) and the rest of
    the turn given as an image shift; those below it are returned unchanged, bit for bit. ``cap`` <= 0: all unchanged."""
    C = np.asarray(corrections, dtype=np.float64)
    if cap <= 0:
        return C
    theta = tilt(C)
    over = theta > cap - knee
    if not np.any(over):
        return C
    out = C.copy()
    Co = C[over]
    L = Co[:, :3, :3]
    R = so3.nearest_rotation(L)
    U = np.swapaxes(R, -1, -2) @ L  # L = R U
    axis = R[:, :, 2]  # R e_z: the virtual optical axis in real-camera coordinates
    n = np.cross(np.array([0.0, 0.0, 1.0]), axis)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    th = theta[over]
    sw = _axis_angle_rotation(n, th)
    tw = np.swapaxes(sw, -1, -2) @ R  # R = R_sw R_tw, R_tw about e_z
    sw_c = _axis_angle_rotation(n, capped_angle(th, cap, knee))
    v = np.einsum("bji,bj->bi", tw, np.einsum("bji,bj->bi", sw_c, axis))  # R_tw^T R_sw'^T R e_z
    S = np.broadcast_to(np.eye(3), L.shape).copy()
    S[:, 0, 2], S[:, 1, 2] = v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]
    out_o = Co.copy()
    out_o[:, :3, :3] = sw_c @ tw @ S @ U
    out[over] = out_o
    return out



def _swing_to(a: np.ndarray) -> np.ndarray:
    """The rotations (..., 3, 3) turning e_z onto the unit vectors ``a`` (..., 3) about e_z x a (identity when a = e_z)."""
    ez = np.array([0.0, 0.0, 1.0])
    n = np.cross(ez, a)
    s = np.linalg.norm(n, axis=-1)
    angle = np.arctan2(s, a[..., 2])
    n = np.where(s[..., None] > 1e-15, n / np.maximum(s, 1e-300)[..., None], np.array([1.0, 0.0, 0.0]))
    return _axis_angle_rotation(n, angle)


def effective_rotation(corrections: np.ndarray) -> np.ndarray:
    """The rotation (..., 3, 3) a correction (..., 4, 4) renders at the image centre (docs/method.md 4.5): the turn
    that puts the virtual optical axis where the correction puts it, L e_z, with the twist of its rotation R' of (19)
    (the point transform's linear part with rows 0 and 1 taken off along row 2, then its polar rotation). For a
    correction without a shift it is the correction's polar rotation; for one (19) capped, the whole turn R again."""
    L = np.asarray(corrections, dtype=np.float64)[..., :3, :3]
    R_cap = np.swapaxes(so3.nearest_rotation(without_image_shift(np.linalg.inv(L))), -1, -2)
    twist = np.swapaxes(_swing_to(R_cap[..., :, 2]), -1, -2) @ R_cap
    axis = L[..., :, 2] / np.linalg.norm(L[..., :, 2], axis=-1, keepdims=True)
    return _swing_to(axis) @ twist

"""The shape term of the content-preserving warp and its reference grid: docs/method.md 5.1, (13).

E_s holds every cell's corner triangles to similar copies of a *reference* grid's
(:func:`similarity_normal`, its normal matrix); the reference is by default the input grid
moved by the correction's rotation alone, K R K^-1 (:func:`rotation_references`), the
parallax-free part of the correction (:mod:`.warp` says why). Shared by the warp and by the
path's crop budget, which predicts the warp's mesh.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..frame import Intrinsics
from ..lie import so3


@lru_cache(maxsize=16)
def _corner_triangles(gx: int, gy: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex indices (V1, V2, V3) of every cell's 4 corner triangles: a corner and its two neighbours."""
    jj, ii = np.mgrid[0:gy, 0:gx]
    ii, jj = ii.ravel(), jj.ravel()
    # Vertex indices of each cell's corners in cyclic order 00, 10, 11, 01.
    cyc = np.stack([jj * (gx + 1) + ii, jj * (gx + 1) + ii + 1,
                    (jj + 1) * (gx + 1) + ii + 1, (jj + 1) * (gx + 1) + ii], axis=1)
    k1 = np.concatenate([cyc[:, q] for q in range(4)])
    k2 = np.concatenate([cyc[:, (q - 1) % 4] for q in range(4)])
    k3 = np.concatenate([cyc[:, (q + 1) % 4] for q in range(4)])
    for a in (k1, k2, k3):
        a.setflags(write=False)
    return k1, k2, k3


def similarity_normal(reference: np.ndarray) -> np.ndarray:
    """S^T S of the similarity term of docs/method.md (13), with (u, v) taken from ``reference`` (..., gy+1, gx+1, 2).

    For each corner triangle (V1, V2, V3) of every cell, (u, v) are the coordinates of
    the reference's V1 in the frame of its edge V2 -> V3, and the residual pair is
    ``V1 - V2 - u (V3 - V2) - v R90 (V3 - V2)`` with R90 (x, y) = (y, -x), linear in
    X = [x_0..x_n-1, y_0..y_n-1]: zero exactly when every output triangle is a similar
    copy of its reference triangle. All coefficients are dimensionless. Leading
    dimensions of ``reference`` are a batch: returns (..., 2n, 2n).
    """
    ref = np.asarray(reference, dtype=np.float64)
    gy, gx = ref.shape[-3] - 1, ref.shape[-2] - 1
    n = (gx + 1) * (gy + 1)
    k1, k2, k3 = _corner_triangles(gx, gy)
    flat = ref.reshape(*ref.shape[:-3], -1, 2)
    e = flat[..., k3, :] - flat[..., k2, :]
    d = flat[..., k1, :] - flat[..., k2, :]
    ee = np.einsum("...ij,...ij->...i", e, e)
    u = np.einsum("...ij,...ij->...i", d, e) / ee
    v = (d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]) / ee  # d . R90 e
    m = len(k1)
    r = np.arange(m)
    S = np.zeros(ref.shape[:-3] + (2 * m, 2 * n))
    # x rows: V1x - (1-u) V2x - u V3x - v (V3y - V2y); y rows: V1y - (1-u) V2y - u V3y + v (V3x - V2x)
    S[..., r, k1] = 1.0
    S[..., r, k2] = -(1.0 - u)
    S[..., r, k3] = -u
    S[..., r, n + k3] = -v
    S[..., r, n + k2] = v
    S[..., m + r, n + k1] = 1.0
    S[..., m + r, n + k2] = -(1.0 - u)
    S[..., m + r, n + k3] = -u
    S[..., m + r, k3] = v
    S[..., m + r, k2] = -v
    return np.swapaxes(S, -1, -2) @ S


def without_image_shift(L: np.ndarray) -> np.ndarray:
    """A point transform's linear part L (..., 3, 3) with an image shift of the output taken out (the tilt cap's
    S^-1, docs/method.md (19)): rows 0 and 1 less their share along row 2 (a shift changes no triangle's shape)."""
    r2 = L[..., 2:3, :]
    return np.concatenate([L[..., :2, :] - (np.sum(L[..., :2, :] * r2, axis=-1, keepdims=True)
                                            / np.sum(r2 * r2, axis=-1, keepdims=True)) * r2, r2], axis=-2)


def rotation_references(K: np.ndarray, point_transforms: np.ndarray, src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grid vertices ``src`` moved by each correction's rotation alone: the homography K R K^-1.

    R is the rotation of the point transform's linear part (its polar factor: the part
    itself for SE(3); scale has no image effect; shear is left to the data term), after an image
    shift of the output (the tilt cap's, docs/method.md (19)) is taken out. A
    rotation moves every pixel by this homography whatever its depth, so it is the
    parallax-free part of the correction. ``K`` (..., 3, 3) and ``point_transforms``
    (..., 4, 4) broadcast; where a vertex would leave the virtual camera's front
    half-space the input grid itself is the reference. Returns the references
    (..., gy+1, gx+1, 2) and where the rotation could be used (...,) bool.
    """
    R = so3.nearest_rotation(without_image_shift(np.asarray(point_transforms, dtype=np.float64)[..., :3, :3]))
    K = np.asarray(K, dtype=np.float64)
    Hr = K @ R @ np.linalg.inv(K)
    pts = src.reshape(-1, 2)
    h = np.einsum("...ij,mj->...mi", Hr[..., :, :2], pts) + Hr[..., None, :, 2]
    ok = np.all(np.isfinite(h), axis=(-1, -2)) & np.all(h[..., 2] > 1e-3, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        moved = h[..., :2] / h[..., 2:]
    out = np.where(ok[..., None, None], moved, pts)
    return out.reshape(out.shape[:-2] + src.shape), ok


def rotation_reference(intrinsics: Intrinsics, point_transform: np.ndarray, src: np.ndarray) -> np.ndarray | None:
    """:func:`rotation_references` for one correction; None when a vertex would leave the front half-space."""
    ref, ok = rotation_references(intrinsics.K, point_transform, src)
    return ref if bool(ok) else None

"""The documented ranges of the wire's numbers that feed math (docs/wire-format.md, "Ranges"), checked
at decode: a value outside them is a :class:`~.codec.WireError` naming the message, seq and field.

Finite is not enough: a motion whose matrix entries are 1e308 is finite, yet one product with a
pose overflows, and a pose chain integrated through it (the recorder's Foxglove poses) stays
non-finite from there on. So, besides finiteness (checked where each field is read):

* transforms (``motion.matrix``, ``correction.matrix``/``camera``, ``frame.pose``): every entry
  within ``MAX_ENTRY``; motions and corrections also have the last row ``[0, 0, 0, 1]`` and a linear
  part with a positive determinant and a condition number within ``MAX_CONDITION``, and a motion's
  linear part is in its group: a rotation (``se3``), a scaled rotation (``sim3``), determinant 1
  (``sa3``), within ``GROUP_TOL``;
* zooms within ``ZOOM_RANGE``;
* intrinsics: a pinhole field of view within ``FOV_DEG`` in each direction and the principal
  point within the image, give or take its size; sizes up to ``MAX_SIDE``;
* timestamps (``t_ns``, ``pub_ns``, ...) ``0 <= t < 2^63`` ns.
"""
from __future__ import annotations

import math

import numpy as np

from ...core.frame import Intrinsics
from ...core.render.framing import ZOOM_LIMIT
from .codec import Reader

MAX_ENTRY = 1e6  # |entry| of a transform: translations within 1000 km (m), linear parts within 1e6
MAX_CONDITION = 1e6  # largest / smallest singular value of a transform's linear part
GROUP_TOL = 1e-4  # |A^T A / s^2 - I| (se3, sim3; s = det(A)^(1/3)) and |det A - 1| (sa3)
ROW_TOL = 1e-6  # last row of a transform against [0, 0, 0, 1]
ZOOM_RANGE = (1.0 / ZOOM_LIMIT, ZOOM_LIMIT)  # framing zooms (the stabilizer's own are in [1, ZOOM_LIMIT]: 100)
FOV_DEG = (0.5, 179.0)  # field of view of the intrinsics, degrees, in each direction
MAX_SIDE = 16384  # intrinsics' width and height (the largest --max-frame-side)
MAX_TIME_NS = 2**63  # timestamps are ns in [0, 2^63): int64 everywhere they are used


def transform(r: Reader, name: str, m: np.ndarray, group: str | None = None, affine: bool = True) -> np.ndarray:
    """The 4x4 ``m`` read from field ``name`` if it is in range (module doc); ``affine=False`` checks
    the entries' magnitude only (a ground-truth pose, as a dataset gives it)."""
    if np.max(np.abs(m), initial=0.0) > MAX_ENTRY:
        raise r.error(name, f"entry {np.max(np.abs(m)):.3g} outside [-{MAX_ENTRY:g}, {MAX_ENTRY:g}]")
    if not affine:
        return m
    row = np.max(np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)))
    if row > ROW_TOL:
        raise r.error(name, f"last row {m[3].tolist()} is not [0, 0, 0, 1]")
    A = m[:3, :3]
    det = float(np.linalg.det(A))
    sv = np.linalg.svd(A, compute_uv=False)
    if not det > 0 or not sv[0] <= MAX_CONDITION * sv[-1]:
        raise r.error(name, f"linear part is singular, mirrored or ill-conditioned (det {det:.3g}, singular values "
                            f"{', '.join(f'{s:.3g}' for s in sv)}; condition number <= {MAX_CONDITION:g} expected)")
    if group in ("se3", "sim3"):
        s = np.cbrt(det)
        err = float(np.max(np.abs(A.T @ A / s**2 - np.eye(3))))
        if group == "se3":
            err = max(err, abs(s - 1.0))
        if err > GROUP_TOL:
            what = "a rotation" if group == "se3" else "a scaled rotation"
            raise r.error(name, f"linear part is not {what} ({err:.3g} off, tolerance {GROUP_TOL:g}) as group "
                                f"{group} says")
    elif group == "sa3" and abs(det - 1.0) > GROUP_TOL:
        raise r.error(name, f"linear part has determinant {det:.9g}, not 1 as group sa3 says")
    return m


def zoom(r: Reader, name: str, value: float | None) -> float | None:
    lo, hi = ZOOM_RANGE
    if value is not None and not lo <= value <= hi:
        raise r.error(name, f"zoom {value:g} outside [{lo:g}, {hi:g}]")
    return value


def time_ns(r: Reader, name: str, value: int | None) -> int | None:
    """A timestamp field (None: nil, where the field is optional)."""
    if value is not None and not 0 <= value < MAX_TIME_NS:
        raise r.error(name, f"timestamp {value} ns outside [0, 2^63)")
    return value


def intrinsics(r: Reader, name: str, k: Intrinsics) -> Intrinsics:
    """``k`` if it is a plausible pinhole camera for its image size (module doc)."""
    if k.width > MAX_SIDE or k.height > MAX_SIDE:
        raise r.error(name, f"image size {k.width}x{k.height} in the intrinsics exceeds {MAX_SIDE}")
    lo, hi = FOV_DEG
    for f, side, axis in ((k.fx, k.width, "fx"), (k.fy, k.height, "fy")):
        fov = math.degrees(2 * math.atan(side / (2 * f)))
        if not lo <= fov <= hi:
            raise r.error(f"{name}.{axis}", f"focal length {f:g} px gives a field of view of {fov:.3g} degrees over "
                                            f"{side} px, outside [{lo:g}, {hi:g}]")
    for c, side, axis in ((k.cx, k.width, "cx"), (k.cy, k.height, "cy")):
        if not -side <= c <= 2 * side:
            raise r.error(f"{name}.{axis}", f"principal point {c:g} px outside [-{side}, {2 * side}] (the image "
                                            "give or take its size)")
    return k

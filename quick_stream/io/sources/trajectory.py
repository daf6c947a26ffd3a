"""TUM trajectory helpers: quaternions, pose interpolation, reading and writing.

TUM trajectory files hold one pose per line, ``timestamp tx ty tz qx qy qz qw``
(seconds, metres, unit quaternion in Hamilton convention with the scalar LAST),
describing the camera-to-world transform; ``#`` lines are comments. Poses are
4x4 numpy arrays throughout this module.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ...core.lie import so3


class TrajectoryError(ValueError):
    """A trajectory file or pose is malformed; the message names the file and line."""


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """3x3 rotation matrix of the quaternion ``q = (qx, qy, qz, qw)`` (normalised first)."""
    q = np.asarray(q, dtype=np.float64)
    n = float(np.linalg.norm(q))
    if q.shape != (4,) or not math.isfinite(n) or n < 1e-12:
        raise TrajectoryError(f"quaternion {tuple(q.ravel())} has zero or non-finite norm")
    return Rotation.from_quat(q).as_matrix()


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` of a 3x3 rotation matrix, canonical: ``qw >= 0`` (and, for a
    half turn, the first non-zero of ``qx, qy, qz`` positive), as SciPy's ``as_quat(canonical=True)``.
    Shepperd's method (the largest of the trace and the diagonal picks the stable formula), in plain
    floats: a 3x3 costs microseconds, not SciPy's tens (a recorder converts two poses a frame)."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(R, dtype=np.float64)[:3, :3].tolist()
    tr = m00 + m11 + m22
    if tr >= m00 and tr >= m11 and tr >= m22:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s)
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        q = (0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif m11 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m11 - m00 - m22, 0.0))
        q = ((m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 + m22 - m00 - m11, 0.0))
        q = ((m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s)
    n = math.sqrt(sum(c * c for c in q))
    out = np.array(q) / n
    lead = out[3] if out[3] != 0.0 else next((c for c in out[:3] if c != 0.0), 1.0)
    return -out if lead < 0 else out


def pose_from_tum(t: Sequence[float], q: Sequence[float]) -> np.ndarray:
    """4x4 pose from translation ``(tx, ty, tz)`` and quaternion ``(qx, qy, qz, qw)``."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def pose_to_tum(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(translation, quaternion ``(qx, qy, qz, qw)``) of a 4x4 pose; the quaternion is that of the
    rotation nearest the pose's linear part (a SIM(3), SA(3) or GA(3) path's scale and shear are
    dropped, as in the Foxglove poses)."""
    T = np.asarray(T, dtype=float)
    return T[:3, 3].copy(), matrix_to_quat(so3.nearest_rotation(T[:3, :3]))


def slerp(q0: Sequence[float], q1: Sequence[float], a: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions (shortest path), ``a`` in [0, 1]."""
    q0 = np.asarray(q0, dtype=float) / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=float) / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:  # nearly identical: normalised lerp is accurate and stable
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(d, 1.0))
    s = math.sin(theta)
    return (math.sin((1 - a) * theta) * q0 + math.sin(a * theta) * q1) / s


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    """Pose a fraction ``a`` of the way from T0 to T1 (linear translation, slerp rotation)."""
    t0, q0 = pose_to_tum(T0)
    t1, q1 = pose_to_tum(T1)
    return pose_from_tum(t0 + a * (t1 - t0), slerp(q0, q1, a))


def poses_at(
    timestamps_s: np.ndarray, poses: np.ndarray, query_s: Iterable[float], max_dt: float
) -> list[np.ndarray | None]:
    """Trajectory poses interpolated at each query time.

    ``timestamps_s`` must be sorted ascending. A query outside
    ``[timestamps_s[0], timestamps_s[-1]]`` or farther than ``max_dt`` from the
    nearest sample gets None; otherwise the pose is interpolated between the two
    samples that bracket it.
    """
    ts = np.asarray(timestamps_s, dtype=float)
    out: list[np.ndarray | None] = []
    for t in query_s:
        if len(ts) == 0 or not (ts[0] <= t <= ts[-1]):
            out.append(None)
            continue
        i = int(np.searchsorted(ts, t, side="right")) - 1  # ts[i] <= t
        if i >= len(ts) - 1 or ts[i] == t:
            out.append(np.array(poses[i], dtype=float) if ts[i] == t else None)
            continue
        t0, t1 = ts[i], ts[i + 1]
        if min(t - t0, t1 - t) > max_dt:
            out.append(None)
            continue
        out.append(interpolate_pose(poses[i], poses[i + 1], (t - t0) / (t1 - t0)))
    return out


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file -> (timestamps_s (N,), poses (N, 4, 4)), sorted by time.

    Raises :class:`TrajectoryError` naming the file and line for a malformed line,
    and OSError when the file cannot be read.
    """
    path = Path(path)
    stamps, poses = [], []
    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.replace(",", " ").split()
            try:
                vals = [float(v) for v in fields]
            except ValueError:
                vals = []
            if len(vals) != 8 or not all(math.isfinite(v) for v in vals):
                raise TrajectoryError(
                    f"{path}:{lineno}: expected 'timestamp tx ty tz qx qy qz qw' (8 finite "
                    f"numbers), got {line[:80]!r}"
                )
            try:
                poses.append(pose_from_tum(vals[1:4], vals[4:8]))
            except TrajectoryError as e:
                raise TrajectoryError(f"{path}:{lineno}: {e}") from None
            stamps.append(vals[0])
    ts = np.array(stamps, dtype=float)
    order = np.argsort(ts, kind="stable")
    return ts[order], np.array(poses, dtype=float).reshape(-1, 4, 4)[order]


def write_tum_trajectory(
    path: str | Path, timestamps_s: Sequence[float], poses: Sequence[np.ndarray | None]
) -> int:
    """Write poses (4x4, camera-to-world) as a TUM trajectory file; returns lines written.

    Entries whose pose is None (unknown) are skipped, since the format has no
    way to mark a missing pose.
    """
    if len(timestamps_s) != len(poses):
        raise ValueError(f"{len(timestamps_s)} timestamps but {len(poses)} poses")
    lines = ["# timestamp tx ty tz qx qy qz qw\n"]
    for t, T in zip(timestamps_s, poses):
        if T is None:
            continue
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"pose at t={t} must be a finite 4x4 matrix, got shape {T.shape}")
        tr, q = pose_to_tum(T)
        vals = " ".join(f"{v:.9f}" for v in (*tr, *q))
        lines.append(f"{float(t):.9f} {vals}\n")
    Path(path).write_text("".join(lines), encoding="utf-8")
    return len(lines) - 1

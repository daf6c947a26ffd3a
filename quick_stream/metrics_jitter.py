"""Signal side of the quality metrics: per-pair motion, low-frequency energy ratio, residual jitter.

Design note section 6 (stability, Liu et al. 2013 / CodingFlow 2017) plus our
residual-jitter measure; the conventions are documented in
:mod:`quick_stream.metrics`. Pure numpy/scipy, so it can score any motion
signal (e.g. a stabiliser's own estimated path) without images.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter1d


def motion_of(H: np.ndarray) -> tuple[float, float, float]:
    """(tx px, ty px, angle deg) of a centred homography: the centre's displacement and the similarity angle.

    The angle is atan2(a10 - a01, a00 + a11), the rotation of the similarity
    closest to the affine part (robust to stretch, unlike atan2(a10, a00)).
    """
    H = H / H[2, 2]
    ang = math.atan2(H[1, 0] - H[0, 1], H[0, 0] + H[1, 1])
    return float(H[0, 2]), float(H[1, 2]), math.degrees(ang)


def low_frequency_ratio(signal: np.ndarray, low_bins: int = 5) -> float:
    """Power in spectrum bins 1..low_bins (the 2nd to 6th for 5) over bins 1..N//2; DC excluded.

    Real FFT of the signal as given (its mean only affects the excluded DC bin).
    A signal without any variation (all power ~0) scores 1: nothing to stabilise.
    """
    x = np.asarray(signal, float)
    if len(x) < 2:
        return 1.0
    power = np.abs(np.fft.rfft(x)) ** 2
    power = power[1:]
    total = float(power.sum())
    if total <= 1e-18 * len(x) ** 2 or np.ptp(x) < 1e-9:
        return 1.0
    return float(power[:low_bins].sum() / total)


def trajectory_jitter(motions: np.ndarray, sigma_frames: float) -> tuple[float, float]:
    """(jitter px, jitter deg) of per-pair motions (N, 3) = (tx, ty, angle deg).

    The motions are summed into a trajectory starting at 0; the high-pass is the
    trajectory minus its Gaussian smoothing (``sigma_frames``, kernel radius
    4 sigma); px = RMS of the high-passed translation magnitude, deg = RMS of
    the high-passed angle.

    Padding is reflection about the end point (``np.pad`` reflect, odd type:
    x[-k] = 2 x[0] - x[k]), not the plain mirror (x[-k] = x[k]): a plain mirror
    turns a steady pan into a V at each end, and the smoothing then reports
    roughly 0.8 sigma x speed of "jitter" there (8 px for a 2 px/frame pan at
    sigma 5). Odd reflection keeps any linear (constant-velocity) trajectory
    exactly, so only deviations from a locally straight path count.
    """
    m = np.asarray(motions, float).reshape(-1, 3)
    traj = np.vstack([np.zeros((1, 3)), np.cumsum(m, axis=0)])
    if sigma_frames <= 0:
        raise ValueError(f"jitter sigma must be > 0 frames, got {sigma_frames}")
    return _rms_jitter(traj - smooth_trajectory(traj, sigma_frames))


def smooth_trajectory(traj: np.ndarray, sigma_frames: float) -> np.ndarray:
    """Gaussian smoothing along axis 0 with odd-reflection padding (see :func:`trajectory_jitter`)."""
    if len(traj) <= 1:
        return traj.copy()
    r = max(1, int(4.0 * sigma_frames + 0.5))
    padded = np.pad(traj, ((r, r), (0, 0)), mode="reflect", reflect_type="odd")
    return gaussian_filter1d(padded, sigma_frames, axis=0, mode="nearest", truncate=4.0)[r:-r]


def _rms_jitter(hp: np.ndarray) -> tuple[float, float]:
    px = math.sqrt(float(np.mean(hp[:, 0] ** 2 + hp[:, 1] ** 2)))
    deg = math.sqrt(float(np.mean(hp[:, 2] ** 2)))
    return px, deg

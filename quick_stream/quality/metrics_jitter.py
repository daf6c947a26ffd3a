"""Signal side of the quality metrics: per-pair motion, accumulated path, stability ratios, residual jitter.

docs/method.md section 6 (stability, Liu et al. 2013 / CodingFlow 2017, in the
form of the public DIFRINT / StabNet metric scripts) plus our residual-jitter
measure; the conventions are documented in :mod:`quick_stream.quality.metrics`. Pure
numpy/scipy, so it can score any motion signal or homography sequence (e.g. a
stabiliser's own estimated path) without images.
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

    The per-pair ratio behind ``stability_pairs`` (applied to per-pair motions, not to
    the accumulated path: see :func:`path_low_frequency_ratio` for the published one).
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


def to_pixel_origin(H: np.ndarray, centre: tuple[float, float]) -> np.ndarray:
    """A homography in centred coordinates (pixel minus ``centre``) re-expressed in pixel coordinates.

    ``C H C^-1`` with ``C`` the translation by ``centre``, normalised to ``[2, 2] = 1``
    (what ``cv2.findHomography`` returns for the same points in pixel coordinates).
    Works on one (3, 3) matrix or a stack (..., 3, 3).
    """
    C = np.eye(3)
    C[:2, 2] = centre
    Ci = np.eye(3)
    Ci[:2, 2] = -np.asarray(centre, float)
    out = C @ np.asarray(H, float) @ Ci
    return out / out[..., 2:3, 2:3]


def accumulate_path(pair_homographies: np.ndarray) -> np.ndarray:
    """The accumulated path P_t = P_{t-1} M_t, P_0 = I, for t = 1..L: (L, 3, 3), docs/method.md (15).

    ``pair_homographies`` (L, 3, 3): M_t maps frame t-1 to frame t (as fitted from
    the keypoints of frame t-1 to those of frame t). No renormalisation of the product.
    """
    M = np.asarray(pair_homographies, float).reshape(-1, 3, 3)
    out = np.empty_like(M)
    P = np.eye(3)
    for t in range(len(M)):
        P = P @ M[t]
        out[t] = P
    return out


def path_signals(path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation sqrt(P02^2 + P12^2) (px) and rotation atan2(P10, P00) (deg) of each path element.

    docs/method.md (16).
    """
    P = np.asarray(path, float).reshape(-1, 3, 3)
    return np.hypot(P[:, 0, 2], P[:, 1, 2]), np.degrees(np.arctan2(P[:, 1, 0], P[:, 0, 0]))


def path_low_frequency_ratio(signal: np.ndarray, low_bins: int = 5) -> float:
    """Published stability ratio of one path signal x_1..x_L, docs/method.md (17).

    Power |FFT(x)|^2 (full complex FFT), the DC bin deleted, the first (L-1)//2 of the
    remaining bins kept (bins 1..(L-1)//2: Nyquist excluded for even L), and the
    ratio of the first ``low_bins`` of them (the 2nd to 6th bins for 5) to their sum.
    A signal without any variation scores 1 (the scripts would divide 0 by 0), as
    does one too short to have more than ``low_bins`` bins.
    """
    x = np.asarray(signal, float).ravel()
    if len(x) < 2 or np.ptp(x) < 1e-9:
        return 1.0
    power = np.abs(np.fft.fft(x)) ** 2
    power = power[1:][: (len(x) - 1) // 2]
    total = float(power.sum())
    if total <= 1e-18 * len(x) ** 2:
        return 1.0
    return float(power[:low_bins].sum() / total)


def path_stability(pair_homographies: np.ndarray, centre: tuple[float, float], low_bins: int = 5
                   ) -> tuple[float, float]:
    """(translation, rotation) stability of consecutive-frame homographies, the published way.

    ``pair_homographies`` (L, 3, 3) in centred coordinates are moved to pixel
    coordinates about ``centre`` (the published scripts use OpenCV keypoint
    coordinates), accumulated (:func:`accumulate_path`), reduced to translation and
    rotation signals (:func:`path_signals`) and scored (:func:`path_low_frequency_ratio`).
    docs/method.md (15)-(17). The sequence score is the mean of the two.
    """
    M = to_pixel_origin(np.asarray(pair_homographies, float).reshape(-1, 3, 3), centre)
    t, r = path_signals(accumulate_path(M))
    return path_low_frequency_ratio(t, low_bins), path_low_frequency_ratio(r, low_bins)


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

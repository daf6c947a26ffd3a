"""High-frequency shake of a camera trajectory (ground-truth evaluation of stabilization).

For camera-to-world poses T_t: rotation as rotation vectors log(R_0^T R_t) and
translation t_t, each high-passed by subtracting its Gaussian-smoothed version
(sigma = ``sigma_s`` seconds, reflect padding): what remains is the shake a
viewer sees. Reported as RMS per axis (degrees; mm), with roll = rotation about
the camera's optical axis (z).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation


def high_pass(signal: np.ndarray, sigma_frames: float) -> np.ndarray:
    """signal (N, k) minus its Gaussian low-pass along axis 0."""
    return signal - gaussian_filter1d(signal, sigma_frames, axis=0, mode="reflect")


def shake(poses: np.ndarray, fps: float, sigma_s: float = 0.2, reference: np.ndarray | None = None
          ) -> dict[str, float]:
    """RMS high-frequency rotation (deg, per camera axis) and translation (mm) of a trajectory.

    With ``reference`` (e.g. the synthetic source's shake-free path), the trajectory is
    first expressed relative to it (reference_t^-1 pose_t), so the large slow intended
    motion does not leak through the high-pass filter.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if reference is not None:
        poses = np.linalg.inv(reference) @ poses
    R0 = poses[0, :3, :3]
    # rotation vectors of the camera relative to its first orientation, in camera axes
    rv = Rotation.from_matrix(np.einsum("ji,njk->nik", R0, poses[:, :3, :3])).as_rotvec()
    t = poses[:, :3, 3] @ R0  # translation in the first camera's axes
    s = sigma_s * fps
    hr = np.degrees(high_pass(rv, s))
    ht = high_pass(t, s) * 1000.0
    rms = lambda a: float(np.sqrt(np.mean(a * a)))  # noqa: E731
    return {
        "rot_x_deg": rms(hr[:, 0]), "rot_y_deg": rms(hr[:, 1]), "roll_deg": rms(hr[:, 2]),
        "rot_deg": rms(np.linalg.norm(hr, axis=1)),
        "trans_mm": rms(np.linalg.norm(ht, axis=1)),
    }

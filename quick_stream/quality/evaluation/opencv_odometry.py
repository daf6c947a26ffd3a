"""OpenCV's own RGB-D odometry (``cv2.Odometry``, RGB_DEPTH) as a reference estimator.

Used by ``quick-stream motion --compare-opencv`` on the same frame pairs as ours.
``Odometry.compute`` returns Rt with ``Rt * src = dst`` for points, i.e. the
point motion M_t of our conventions; the camera motion is its inverse.
"""
from __future__ import annotations

import cv2
import numpy as np

from ...core.frame import Intrinsics, RGBDFrame


class OpenCVOdometry:
    """Frame-to-frame camera motion by ``cv2.Odometry`` (type RGB_DEPTH, algorithm COMMON)."""

    def __init__(self, intrinsics: Intrinsics) -> None:
        if not hasattr(cv2, "Odometry"):
            raise RuntimeError("this OpenCV build has no cv2.Odometry (needs OpenCV >= 5)")
        self._K = None
        self._od = None
        self._set(intrinsics)

    def _set(self, K: Intrinsics) -> None:
        if self._K == K:
            return
        settings = cv2.OdometrySettings()
        settings.setCameraMatrix(K.K.astype(np.float32))
        self._od = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
        self._K = K

    def camera_motion(self, f0: RGBDFrame, f1: RGBDFrame) -> np.ndarray | None:
        """Camera motion T_t^-1 T_{t+1} (4x4), or None when OpenCV reports failure."""
        self._set(f0.intrinsics)
        g0 = cv2.cvtColor(f0.color, cv2.COLOR_BGR2GRAY)
        g1 = cv2.cvtColor(f1.color, cv2.COLOR_BGR2GRAY)
        ok, Rt = self._od.compute(f0.depth, g0, f1.depth, g1)
        if not ok or not np.all(np.isfinite(Rt)):
            return None
        return np.linalg.inv(np.asarray(Rt, dtype=np.float64))

"""Relative pose error of our estimators and OpenCV's RGB-D odometry on one clip, in one pass.

Each frame pair's scene flow is computed once and given to every estimator; the
ms per pair of ours is scene flow + that estimator. OpenCV's ``cv2.Odometry``
(RGB_DEPTH) runs on the same pairs. Everything single-threaded.
"""
from __future__ import annotations

import time
from typing import Callable

import cv2
import numpy as np

from ..core.frame import BadFrame
from ..core.motion import MotionEstimator, MotionParams
from ..core.motion_pipeline import true_motion
from ..core.sceneflow import SceneFlow, SceneFlowParams
from ..io.sources import open_source
from ..quality.evaluation.opencv_odometry import OpenCVOdometry
from ..quality.evaluation.rpe import ErrorStats, relative_pose_error


def run(source_spec: str, methods: list[tuple[str, str]] | None = None, opencv: bool = True,
        frames: int | None = None, progress: Callable[[str], None] | None = None) -> dict:
    """``methods``: (group, estimator) pairs; default exact and induced SE(3). ``progress``: told each frame."""
    cv2.setNumThreads(1)
    methods = methods or [("se3", "exact"), ("se3", "induced")]
    src = open_source(source_spec)
    sf = SceneFlow(SceneFlowParams())
    ests = {f"{e} {g}": MotionEstimator(MotionParams(group=g, estimator=e)) for g, e in methods}
    ocv = OpenCVOdometry(src.intrinsics) if opencv else None
    errs: dict[str, list[tuple[float, float]]] = {k: [] for k in ests}
    ms: dict[str, list[float]] = {k: [] for k in ests}
    if ocv:
        errs["opencv rgbd odometry"], ms["opencv rgbd odometry"] = [], []
    invalid = {k: 0 for k in errs}
    prev = None
    try:
        total: int | str = len(src) if frames is None else min(frames, len(src))
    except TypeError:  # a live camera has no length
        total = "?" if frames is None else frames
    for i, fr in enumerate(src):
        if frames is not None and i >= frames:
            break
        if progress:
            progress(f"frame {i + 1}/{total}")
        if isinstance(fr, BadFrame):
            continue
        if prev is not None:
            truth = true_motion(prev, fr)
            t0 = time.perf_counter()
            flow = sf.compute(prev, fr)
            flow_ms = (time.perf_counter() - t0) * 1e3
            for name, est in ests.items():
                t0 = time.perf_counter()
                m = est.estimate(flow)
                ms[name].append(flow_ms + (time.perf_counter() - t0) * 1e3)
                if not m.valid:
                    invalid[name] += 1
                elif truth is not None:
                    errs[name].append(relative_pose_error(m.matrix, truth))
            if ocv:
                t0 = time.perf_counter()
                g = ocv.camera_motion(prev, fr)
                ms["opencv rgbd odometry"].append((time.perf_counter() - t0) * 1e3)
                if g is None:
                    invalid["opencv rgbd odometry"] += 1
                elif truth is not None:
                    errs["opencv rgbd odometry"].append(relative_pose_error(g, truth))
        prev = fr
    out = {}
    for name in errs:
        e = np.asarray(errs[name]).reshape(-1, 2)
        st = ErrorStats.from_errors(e[:, 0], e[:, 1])
        out[name] = {"ms_per_pair": float(np.mean(ms[name])), "invalid": invalid[name], **st.as_dict()}
    return {"source": source_spec, "methods": out}


def format_table(r: dict) -> str:
    lines = [f"relative pose error per frame pair on {r['source']} (rotation deg, translation mm):",
             f"{'method':<22} {'pairs':>5} {'rot med':>8} {'rot mean':>8} {'t med':>7} {'t mean':>7} "
             f"{'ms/pair':>8} {'invalid':>7}"]
    for name, m in r["methods"].items():
        lines.append(f"{name:<22} {m['n']:>5} {m['rot_median']:>8.4f} {m['rot_mean']:>8.4f} "
                     f"{m['trans_median']:>7.2f} {m['trans_mean']:>7.2f} {m['ms_per_pair']:>8.2f} {m['invalid']:>7}")
    return "\n".join(lines)

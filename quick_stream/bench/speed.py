"""Per-stage speed of scene flow + motion on one core (target: <= 10 ms per 640x480 pair).

Frames come from the synthetic source, rendered before timing (the source's own
rate is printed separately). The process is pinned to one CPU and OpenCV to one
thread, as one service runs.
"""
from __future__ import annotations

import os
import time
from typing import Callable

import cv2
import numpy as np

from ..core.motion import MotionEstimator, MotionParams
from ..core.sceneflow import SceneFlow, SceneFlowParams, lift_flow
from ..io.sources.synthetic import SyntheticSource


def pin_one_core() -> str:
    """Pin this process to one CPU and OpenCV to one thread; returns a description."""
    cv2.setNumThreads(1)
    try:
        cpu = sorted(os.sched_getaffinity(0))[-1]
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}, OpenCV threads 1"
    except (AttributeError, OSError):
        return "OpenCV threads 1 (CPU pinning unavailable)"


def run(pairs: int = 100, width: int = 640, height: int = 480, group: str = "se3",
        flow_params: SceneFlowParams | None = None, progress: Callable[[str], None] | None = None) -> dict:
    """``progress``: told each step (rendering the frames, then each pair timed)."""
    say = progress or (lambda _msg: None)
    pinned = pin_one_core()
    say(f"rendering {pairs + 1} synthetic frames")
    src = SyntheticSource(width=width, height=height, frames=pairs + 1)
    t0 = time.perf_counter()
    frames = list(src)
    source_fps = len(frames) / (time.perf_counter() - t0)
    sf = SceneFlow(flow_params)
    me = MotionEstimator(MotionParams(group=group))
    stages: dict[str, list[float]] = {"optical flow (fwd+bwd)": [], "lift + masks + LK": [], "motion": []}
    for i, (a, b) in enumerate(zip(frames[:-1], frames[1:]), 1):
        say(f"pair {i}/{pairs}")
        t0 = time.perf_counter()
        fwd, bwd = sf.optical_flow(a, b)
        t1 = time.perf_counter()
        res = lift_flow(a, b, fwd, bwd, sf.params, sf.refiner(a, b))
        t2 = time.perf_counter()
        me.estimate(res)
        t3 = time.perf_counter()
        stages["optical flow (fwd+bwd)"].append((t1 - t0) * 1e3)
        stages["lift + masks + LK"].append((t2 - t1) * 1e3)
        stages["motion"].append((t3 - t2) * 1e3)
    total = np.sum([np.asarray(v) for v in stages.values()], axis=0)
    stages["total"] = list(total)
    return {
        "setup": pinned,
        "resolution": f"{width}x{height}",
        "pairs": pairs,
        "group": group,
        "source_fps": source_fps,
        "stages_ms": {k: {"mean": float(np.mean(v)), "median": float(np.median(v)),
                          "p95": float(np.percentile(v, 95))} for k, v in stages.items()},
    }


def format_report(r: dict, target_ms: float = 10.0) -> str:
    lines = [f"scene flow + motion, {r['resolution']}, {r['pairs']} pairs, {r['group']}, {r['setup']}",
             f"synthetic source: {r['source_fps']:.0f} frames/s (rendering, not included below)",
             f"{'stage':<24} {'mean':>8} {'median':>8} {'p95':>8}  (ms per frame pair)"]
    for k, s in r["stages_ms"].items():
        lines.append(f"{k:<24} {s['mean']:8.2f} {s['median']:8.2f} {s['p95']:8.2f}")
    mean = r["stages_ms"]["total"]["mean"]
    lines.append(f"target <= {target_ms:.0f} ms per pair: {'met' if mean <= target_ms else 'NOT met'} "
                 f"(mean {mean:.2f} ms)")
    return "\n".join(lines)

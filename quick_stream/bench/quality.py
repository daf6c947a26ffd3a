"""Quality on real footage: ours (four groups x both end-constraint modes) beside FFmpeg's stabilizers.

Every method's output is scored by :mod:`quick_stream.metrics` against the same
input frames: cropping, distortion, stability and residual jitter (px, deg).
Ours runs with ``auto`` framing (border-free), vid.stab and deshake as
:mod:`.ffmpeg_baselines` documents (ffmpeg is installed from Debian if missing).
"""
from __future__ import annotations

from pathlib import Path

import cv2

from .. import evaluate
from ..motion import MotionParams
from ..path.planner import PlannerParams
from ..render import FramingParams
from ..sources.tum import TumSource
from ..stabilizer import StabilizerParams
from . import ffmpeg_baselines

GROUPS = ("se3", "sim3", "sa3", "ga3")
ENDS = ("identity", "smoothed")
COLUMNS = ("cropping", "distortion", "stability", "jitter_px", "jitter_deg", "failed")


def stabilize_and_score(folder: Path, group: str, end: str, frames: int | None, framing: str = "auto",
                        lowpass_sigma: float = PlannerParams.lowpass_sigma) -> dict:
    """Stabilize a TUM clip with these settings and score it (:func:`quick_stream.evaluate.stabilize_and_score`)."""
    src = TumSource(folder, count=frames)
    params = StabilizerParams(motion=MotionParams(group=group),
                              planner=PlannerParams(group=group, end=end, lowpass_sigma=lowpass_sigma),
                              framing=FramingParams(mode=framing))
    return evaluate.stabilize_and_score(src, params, src.fps)


def run(data_root: Path, frames: int | None = None, baselines: bool = True) -> dict:
    cv2.setNumThreads(1)
    folder = data_root / "7scenes_redkitchen"
    out: dict = {"folder": str(folder), "methods": {}}
    for group in GROUPS:
        for end in ENDS:
            out["methods"][f"quick {group} {end}"] = stabilize_and_score(folder, group, end, frames)
    # the paper's own path for reference: full undo between identity end-constraints
    out["methods"]["paper path (se3 identity, no low-pass)"] = stabilize_and_score(
        folder, "se3", "identity", frames, lowpass_sigma=0.0)
    if baselines:
        b = ffmpeg_baselines.run(folder, frames)
        out["ffmpeg"] = b["ffmpeg"]
        out["commands"] = b["commands"]
        for name, m in b["methods"].items():
            out["methods"][name if name != "input" else "input (unstabilized)"] = m
    return out


def format_table(r: dict) -> str:
    lines = [f"{r['folder']}: quality metrics (design note section 6) + residual jitter",
             f"{'method':40s} " + " ".join(f"{c:>11s}" for c in COLUMNS)]
    for name, m in r["methods"].items():
        vals = " ".join(f"{m[c]!s:>11s}" if isinstance(m[c], bool) else f"{m[c]:11.3f}" for c in COLUMNS)
        lines.append(f"{name:40s} {vals}")
    for k, v in r.get("commands", {}).items():
        lines.append(f"  {k}: ffmpeg {v}")
    return "\n".join(lines)

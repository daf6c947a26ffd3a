"""``quick-stream bench speed --versus-vidstab CLIP``: ours and FFmpeg vid.stab on one clip, in one run.

Absolute times on a shared machine drift from run to run, so the two are compared only within
one run, alternating (ours, vid.stab, ours, vid.stab, ... ``repeat`` times) and taking each one's
median:

* **ours**: ``quick-stream stabilize --source CLIP --no-metrics`` as a user runs it (a child
  process; its report gives the stages' compute, ``1000 / fps_compute`` ms per frame, and the
  wall time of the whole job including reading the clip and writing the MP4, ``wall_s``);
* **vid.stab**: the two passes of :mod:`quick_stream.bench.ffmpeg_baselines` (detect, then
  transform) on the same frames, from the same lossless intermediate (made once, not timed), the
  second pass writing an MP4 (``mpeg4``, what OpenCV's ``mp4v`` writer writes for ours). vid.stab's
  work cannot be timed apart from ffmpeg's decoding and encoding, so its one figure, the wall time
  of both passes, is compared with both of ours. Its CPU time (user + system of the ffmpeg
  processes; ffmpeg decodes and encodes on several threads) is printed beside it.
"""
from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from .ffmpeg_baselines import QUIET, BaselineParams, children_cpu, ensure_ffmpeg, load_tum_rgb, run_ffmpeg


def _ours(spec: str, frames: int | None, work: Path) -> dict:
    report = work / "ours.json"
    argv = [sys.executable, "-m", "quick_stream", "stabilize", "--source", spec, "--no-metrics", "--quiet",
            "--output", str(work / "ours.mp4"), "--report", str(report), "--plot", "", "--force"]
    if frames:
        argv += ["--frames", str(frames)]
    r = subprocess.run(argv, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"quick-stream stabilize failed (rc {r.returncode}): {r.stderr[-1500:]}")
    rep = json.loads(report.read_text())
    n = rep["frames_out"]
    return {"frames": n, "compute_ms": 1e3 / rep["fps_compute"], "wall_ms": 1e3 * rep["wall_s"] / n,
            "stages_ms": {k: v["mean"] for k, v in rep["timing_ms"].items()}}


def _vidstab(ffmpeg: str, n: int, work: Path, params: BaselineParams) -> dict:
    vf = params.filters()
    t0, c0 = time.perf_counter(), children_cpu()
    run_ffmpeg([ffmpeg, *QUIET, "-i", "input.mkv", "-vf", vf["vidstabdetect"], "-f", "null", "-"], work)
    run_ffmpeg([ffmpeg, *QUIET, "-i", "input.mkv", "-vf", vf["vidstabtransform"], "-fps_mode", "passthrough",
          "-c:v", "mpeg4", "-q:v", "3", "vidstab.mp4"], work)
    return {"frames": n, "wall_ms": 1e3 * (time.perf_counter() - t0) / n, "cpu_ms": 1e3 * (children_cpu() - c0) / n}


def run(spec: str, frames: int | None = None, repeat: int = 3, work: Path | None = None,
        progress: Callable[[str], None] | None = None) -> dict:
    """Both stabilizers on the TUM clip ``spec`` (``tum:PATH``), alternated ``repeat`` times; medians."""
    say = progress or (lambda _msg: None)
    if not spec.startswith("tum:"):
        raise ValueError(f"the side-by-side clip is a TUM folder, tum:PATH (vid.stab reads its colour images), "
                         f"got {spec!r}")
    ffmpeg = ensure_ffmpeg()
    if work is None:
        with tempfile.TemporaryDirectory(prefix="qs_versus_") as tmp:
            return run(spec, frames, repeat, Path(tmp), progress)
    work.mkdir(parents=True, exist_ok=True)
    say("writing the clip's colour frames as vid.stab's lossless input (not timed)")
    imgs = load_tum_rgb(Path(spec.removeprefix("tum:").split(",")[0]), frames)
    h, w = imgs[0].shape[:2]
    run_ffmpeg([ffmpeg, *QUIET, "-f", "rawvideo", "-pix_fmt", "bgr24", "-s", f"{w}x{h}", "-r", "30", "-i", "-",
          "-c:v", "ffv1", "-level", "3", "-pix_fmt", "bgr0", "input.mkv"], work, b"".join(i.tobytes() for i in imgs))
    ours, theirs = [], []
    for i in range(repeat):
        say(f"round {i + 1}/{repeat}: quick-stream stabilize")
        ours.append(_ours(spec, frames, work))
        say(f"round {i + 1}/{repeat}: vid.stab (2 passes)")
        theirs.append(_vidstab(ffmpeg, len(imgs), work, BaselineParams()))
    med = statistics.median
    o = {k: med(r[k] for r in ours) for k in ("compute_ms", "wall_ms")}
    o["stages_ms"] = {k: med(r["stages_ms"][k] for r in ours) for k in ours[0]["stages_ms"]}
    v = {k: med(r[k] for r in theirs) for k in ("wall_ms", "cpu_ms")}
    return {"clip": spec, "frames": ours[0]["frames"], "size": f"{w}x{h}", "repeat": repeat, "ours": o,
            "vidstab": v, "ratio_compute": o["compute_ms"] / v["wall_ms"], "ratio_wall": o["wall_ms"] / v["wall_ms"],
            "rounds": {"ours": ours, "vidstab": theirs}}


def format_report(r: dict) -> str:
    o, v = r["ours"], r["vidstab"]
    return "\n".join([
        f"side by side on {r['clip']} ({r['frames']} frames, {r['size']}), medians of {r['repeat']} alternated rounds",
        f"{'':34s} {'ms/frame':>9s}",
        f"{'ours: compute (all stages, no I/O)':34s} {o['compute_ms']:9.2f}   "
        + ", ".join(f"{k} {x:.2f}" for k, x in o["stages_ms"].items()),
        f"{'ours: wall (reading, writing MP4)':34s} {o['wall_ms']:9.2f}",
        f"{'vid.stab 2-pass: wall':34s} {v['wall_ms']:9.2f}   (CPU {v['cpu_ms']:.2f} ms/frame, ffmpeg threads)",
        f"ratio compute / vid.stab: {r['ratio_compute']:.2f}x (target <= 0.5x); "
        f"wall / vid.stab: {r['ratio_wall']:.2f}x (target <= 0.7x)"])

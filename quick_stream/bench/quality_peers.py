"""The peers' rows of ``quick-stream bench quality``: FFmpeg vid.stab and deshake, python vidstab,
vidgear's Stabilizer and the LK moving average, each run on the clip's input frames and scored
by :func:`~quick_stream.bench.quality_scoring.score_frames`; a peer that cannot run is a row
saying why (status "not run" or "error"), never a missing row."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from . import ffmpeg_baselines, lk_average, peers
from .quality_scoring import score_frames

Progress = Callable[[str], None]


def _row(status: str = "ok", **kw: object) -> dict:
    return {"status": status, **kw}


def peer_rows(inputs: list[np.ndarray], fps: float, work: Path, progress: Progress | None,
              delay: int | None = None) -> tuple[dict, dict]:
    """Rows of the 2D peers (FFmpeg, vidstab, vidgear, LK) and the FFmpeg commands run. ``delay``: each peer
    set to look that many frames ahead (vid.stab ``smoothing``, vidstab ``smoothing_window``, vidgear
    ``smoothing_radius``, the LK average's radius; deshake, which has no window, left out); None: their
    defaults (:mod:`.latency_curve`)."""
    rows: dict[str, dict] = {}
    commands: dict = {}
    n = len(inputs)
    ffmpeg_rows = (("vidstab", "vid.stab 2-pass (ffmpeg)"),) + ((("deshake", "deshake (ffmpeg)"),) if delay is None else ())
    problem = ffmpeg_baselines.ffmpeg_problem()
    if problem:
        for _, name in ffmpeg_rows:
            rows[name] = _row("not run", reason=problem)
    else:
        if progress:
            progress("ffmpeg vid.stab" + (" + deshake" if delay is None else ""))
        try:
            params = ffmpeg_baselines.BaselineParams() if delay is None else ffmpeg_baselines.BaselineParams(
                smoothing=delay)
            outs = ffmpeg_baselines.run_baselines(inputs, fps, workdir=work, params=params)
            commands = {k: " ".join(v[1:]) for k, v in outs.commands.items()}
            for key, name in ffmpeg_rows:
                frames_out = outs.pop(key)
                row = score_frames(inputs, frames_out, fps)
                del frames_out
                row.update(status="ok", seconds=outs.seconds[key], cpu_seconds=outs.cpu_seconds[key],
                           ms_per_frame=1e3 * outs.seconds[key] / n)
                rows[name] = row
        except (RuntimeError, AssertionError, OSError) as e:
            for _, name in ffmpeg_rows:
                rows.setdefault(name, _row("error", reason=str(e)))
    avail = peers.available()
    windows = {} if delay is None else {"vidstab": {"window": delay}, "vidgear": {"radius": delay}}
    for key, name, runner in (("vidstab", "vidstab (python)", peers.run_vidstab),
                              ("vidgear", "vidgear Stabilizer", peers.run_vidgear)):
        if avail[key]:
            rows[name] = _row("not run", reason=avail[key])
            continue
        if progress:
            progress(name)
        try:
            pr = runner(inputs, **windows.get(key, {}))
        except Exception as e:  # noqa: BLE001 - a peer that crashes is a row, not the end of the benchmark
            rows[name] = _row("error", reason=f"{type(e).__name__}: {e}")
            continue
        row = score_frames(inputs, pr.frames, fps)
        row.update(status="ok", seconds=pr.seconds, ms_per_frame=1e3 * pr.seconds / n, calls=pr.calls,
                   notes=pr.notes)
        rows[name] = row
        del pr
    if progress:
        progress("LK moving average")
    t0 = time.perf_counter()
    lk_params = lk_average.LKParams() if delay is None else lk_average.LKParams(radius=delay)
    lk = lk_average.stabilize(inputs, lk_params)
    t = time.perf_counter() - t0
    row = score_frames(inputs, lk, fps)
    row.update(status="ok", seconds=t, ms_per_frame=1e3 * t / n,
               notes=[f"GFTT + LK + estimateAffinePartial2D, centred moving average +-{lk_params.radius}"])
    rows["LK moving average"] = row
    return rows, commands

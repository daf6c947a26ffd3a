"""Quality benchmark: ours against the 2D stabilisers people use, on real footage, known-shake
clips and degraded sensors.

Clips (TUM layout, read with :class:`~quick_stream.io.sources.tum.TumSource`; ``frames``
shortens every clip to its first N; :mod:`.quality_clips` makes and caches them under
``WORK/clips``):

* real clips ``DATA/NAME`` (``--real``; default ``7scenes_redkitchen`` and ``tum_fr1_rpy``);
* known-shake clips made from any real clip by the external shake tool (:mod:`.shake_clips`):
  per ``[SRC:]SEED:FIRST-LAST`` a shaken clip (RMS pitch/yaw/roll, default 0.6/0.6/0.8 deg) and
  its unshaken reference (same seed, frames and crop, no shake);
* degraded copies of each known-shake clip and of its reference, one per degrade cell
  (``--degrade``, ``--degrade-grid``; :mod:`.degrade_clips`), by the external degrade tool.

Methods, all given the same BGR input frames and all scored by :mod:`quick_stream.quality.metrics`
(:class:`~quick_stream.quality.metrics.MetricsAccumulator`, one scorer for everyone) plus the
border-free cropping of :mod:`quick_stream.quality.metrics_border` (which uses the scorer's
input-output homography to tell dark scene content from uncovered borders):

* ``ours``: the stabiliser at exactly the settings ``quick-stream stabilize`` uses with no flags
  (the stabiliser flags of :mod:`quick_stream.io.stabilizer_flags` parsed from an empty argv, then
  ``stabilizer_params``), and every ``--variant NAME='--flag value ...'`` (the same flags);
* FFmpeg vid.stab (two passes) and deshake (:mod:`.ffmpeg_baselines`);
* python ``vidstab`` and vidgear's ``Stabilizer`` at their defaults, when importable
  (:mod:`.peers`: how their delayed outputs are aligned with the inputs);
* the textbook LK + moving-average stabiliser (:mod:`.lk_average`);
* the unstabilised input.

Every method runs on every clip, degraded copies included. Columns: residual jitter (px, deg),
cropping, border-free cropping, distortion, stability (as ``quick_stream.quality.metrics``
defines it), the method's own wall time per frame (ours: the stabiliser's push/finish, no
reading, no scoring; FFmpeg: its passes on the lossless intermediate, decoding included; peers:
their calls), failure, and for ours and its variants the output frames not corrected
(``uncorrected``: ``correction.valid`` False) with the count of frames by how their motion was
known (``motion_kinds``: ``correction.motion``, "fit" when the motion was fitted; the fallbacks
under each table).

On the known-shake clips, the share of the injected high-frequency rotation ours (and each
variant) removed, per axis: ours' per-frame corrections on the shaken clip and, with the same
settings, on the unshaken reference go to ``WORK/corrections`` and through the tool's
``score_rotation.py`` without and with ``--reference``. With degrade cells, the robustness grid
(:mod:`.quality_robustness`) sums up ours against the best peer per known-shake clip and cell.
"""
from __future__ import annotations

import dataclasses
import platform
import re
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..core.path.planner import Correction
from ..core.stabilizer import Stabilizer
from ..io.sources import SourceError
from ..io.sources.tum import TumSource
from ..quality.evaluate import run_timed
from . import ffmpeg_baselines, latency_curve, peers
from .degrade_clips import DEFAULT_TOOL as DEFAULT_DEGRADE_TOOL, DegradeCell
from .quality_clips import DEFAULT_REAL, Clip, ShakeClip, default_shake_clips, load_frames, prepare_clips
from .quality_peers import peer_rows
from .quality_robustness import robustness_rows
from .quality_scoring import Scorer, score_frames
from .variants import Variant, default_settings
from .shake_clips import DEFAULT_AMPLITUDES, DEFAULT_TOOL, score_rotation, write_corrections

DEFAULT_WORK = Path("out/bench-quality")
Progress = Callable[[str], None]


# ----------------------------------------------------------------------------------------------
# configuration


@dataclass
class QualityConfig:
    data: Path = Path("../shared/data")
    frames: int | None = None  # every clip shortened to its first N frames
    real: list[str] = field(default_factory=lambda: list(DEFAULT_REAL))  # real clips: folders under data
    clips: list[ShakeClip] = field(default_factory=default_shake_clips)
    shake_tool: Path = DEFAULT_TOOL
    degrade: list[DegradeCell] = field(default_factory=list)  # degrade cells (clean: the clip itself)
    degrade_tool: Path = DEFAULT_DEGRADE_TOOL
    work: Path = DEFAULT_WORK
    variants: list[Variant] = field(default_factory=list)
    baselines: bool = True  # FFmpeg, vidstab, vidgear, LK moving average
    notes: list[str] = field(default_factory=list)  # e.g. default clips skipped (no folder)
    lookaheads: list[float] = field(default_factory=list)  # s: the latency curve's points (none: no curve)


# ----------------------------------------------------------------------------------------------
# ours


@dataclass
class CorrectionCounts:
    """Ours' output frames: those not corrected (``valid`` False) and all by ``correction.motion``."""

    uncorrected: int = 0
    motion: Counter = field(default_factory=Counter)

    def add(self, correction: Correction) -> None:
        self.uncorrected += not correction.valid
        # "fit" is the field's default; read so that a planner without the field still counts
        self.motion[getattr(correction, "motion", "fit")] += 1

    def as_dict(self) -> dict:
        """``uncorrected`` and ``motion_kinds`` (kind -> frames, most frames first)."""
        return {"uncorrected": self.uncorrected, "motion_kinds": dict(self.motion.most_common())}


def run_ours(folder: Path, variant: Variant, frames: int | None, inputs: dict[int, np.ndarray] | None,
             fps: float) -> tuple[dict, list[tuple[int, np.ndarray]]]:
    """Stabilise a TUM clip with ``variant``; score against ``inputs`` (seq -> image) unless None.

    Returns (row, [(timestamp_ns, correction g_s)] per output frame).
    """
    src = TumSource(folder, count=frames)
    st = Stabilizer(variant.params)
    scorer = Scorer(fps) if inputs is not None else None
    corrections: list[tuple[int, np.ndarray]] = []
    counts = CorrectionCounts()
    flagged, missing = 0, 0

    def take(batch: list) -> None:
        nonlocal flagged, missing
        for sf in batch:
            corrections.append((sf.timestamp_ns, np.array(sf.correction.matrix, float)))
            counts.add(sf.correction)
            flagged += bool(sf.flags)
            if scorer is not None:
                if sf.seq in inputs:
                    scorer.add(inputs[sf.seq], sf.image)
                else:
                    missing += 1

    t, n_in = run_timed(st, src, take)
    row: dict = scorer.result() if scorer is not None else {}
    row.update(status="ok", ms_per_frame=1e3 * t / max(n_in, 1), seconds=t, frames_in=n_in,
               frames_out=len(corrections), flagged_frames=flagged, bad_frames=len(st.bad_frames),
               segments=st.planner.segment_count, renderer_bordered=st.render.filler.bordered,
               reached_over=st.flow.reached_over, loose_flows=st.flow.loose, **counts.as_dict())
    if inputs is not None and len(corrections) != len(inputs):
        row["notes"] = [f"{len(corrections)} output frames for {len(inputs)} readable inputs"]
    return row, corrections


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", name)


def run_clip(clip: Clip, cfg: QualityConfig, progress: Progress | None = None) -> dict:
    """Every method on one clip; for a shaken clip also ours' share of the shake removed."""
    def say(what: str) -> None:
        if progress:
            progress(f"{clip.name}: {what}")

    seqs, images, _, fps = load_frames(clip.folder, cfg.frames)
    if len(images) < 2:
        raise SourceError(f"{clip.folder}: fewer than 2 readable frames")
    h, w = images[0].shape[:2]
    out: dict = {"name": clip.name, "folder": str(clip.folder), "frames": len(images), "size": f"{w}x{h}",
                 "fps": fps, "methods": {}}
    if clip.spec is not None:
        out.update(shake=dataclasses.asdict(clip.spec), known_shake=clip.label, source=clip.source,
                   reference_folder=str(clip.reference), made=clip.made)
        if clip.cell is not None:
            out["degrade"] = {"cell": clip.cell.name, "argv": clip.cell.argv()}
    inputs = dict(zip(seqs, images))
    ours = [default_settings(), *cfg.variants]
    corr_dir = Path(cfg.work) / "corrections" / (clip.name + (f"_first{cfg.frames}" if cfg.frames else ""))
    shake_scores: dict = {}
    for v in ours:
        label = "ours" if v.name == "ours" else f"ours [{v.name}]"
        say(label)
        row, corr = run_ours(clip.folder, v, cfg.frames, inputs, fps)
        row["settings"] = v.flags
        out["methods"][label] = row
        if clip.spec is None:
            continue
        say(f"{label} on the unshaken reference")
        ref_row, corr_ref = run_ours(clip.reference, v, cfg.frames, None, fps)
        est, ref = corr_dir / f"{_slug(v.name)}.txt", corr_dir / f"{_slug(v.name)}_reference.txt"
        write_corrections(est, corr)
        write_corrections(ref, corr_ref)
        shake = clip.folder / "shake.txt"
        try:
            plain = score_rotation(cfg.shake_tool, shake, est)
            with_ref = score_rotation(cfg.shake_tool, shake, est, ref)
            shake_scores[label] = {"without_reference": plain, "with_reference": with_ref,
                                   "corrections": str(est), "reference_corrections": str(ref),
                                   "reference_run": {k: ref_row[k] for k in ("frames_out", "uncorrected",
                                                                             "motion_kinds", "reached_over",
                                                                             "loose_flows")}}
        except (RuntimeError, ValueError, OSError) as e:
            shake_scores[label] = {"error": str(e)}
    if cfg.baselines:
        rows, commands = peer_rows(images, fps, Path(cfg.work) / "ffmpeg" / clip.name, say)
        out["methods"].update(rows)
        out["ffmpeg_commands"] = commands
    if cfg.lookaheads and (clip.cell is None or clip.cell.is_clean):  # the curve: real and known-shake clips
        out["latency_curve"] = latency_curve.curve(
            images, fps, cfg.lookaheads, lambda v: run_ours(clip.folder, v, cfg.frames, inputs, fps)[0],
            Path(cfg.work) / "ffmpeg" / clip.name / "latency", cfg.baselines, say)
    say("input (unstabilized)")
    row = score_frames(images, images, fps)
    row.update(status="ok", ms_per_frame=0.0)
    out["methods"]["input (unstabilized)"] = row
    if clip.spec is not None:
        out["shake_removed"] = shake_scores
    return out


# ----------------------------------------------------------------------------------------------
# the whole benchmark


def _git() -> dict:
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, timeout=10).stdout
        return {"head": head, "modified_files": [ln for ln in dirty.splitlines() if ln.strip()]}
    except (OSError, subprocess.SubprocessError):
        return {}


def versions() -> dict:
    return {"ffmpeg": ffmpeg_baselines.ffmpeg_version() or None, "vidstab": peers.version("vidstab"), "vidgear": peers.version("vidgear"),
            "imutils": peers.version("imutils"), "opencv": cv2.__version__, "numpy": np.__version__,
            "python": platform.python_version(), "quick-stream git": _git()}


def run(cfg: QualityConfig, progress: Progress | None = None) -> dict:
    """The benchmark (module docstring); a JSON-able dict with every setting, command, version and metric."""
    cv2.setNumThreads(1)
    started = time.time()
    clips = prepare_clips(cfg.data, cfg.real, cfg.clips, cfg.degrade, cfg.work, cfg.shake_tool, cfg.degrade_tool,
                          progress)
    ours = default_settings()
    shakes = [c.shake for c in cfg.clips]
    r: dict = {
        "settings": {"data": str(cfg.data), "frames": cfg.frames, "real": list(cfg.real),
                     "clips": [c.label for c in cfg.clips],
                     "amplitudes_deg": [shakes[0].pitch, shakes[0].yaw, shakes[0].roll]
                     if shakes else list(DEFAULT_AMPLITUDES),
                     "shake_tool": str(cfg.shake_tool), "degrade_tool": str(cfg.degrade_tool),
                     "degrade_cells": {c.name: c.argv() for c in cfg.degrade},
                     "work": str(cfg.work), "baselines": cfg.baselines, "opencv_threads": 1, "notes": list(cfg.notes)},
        "ours": {"argv": [], "flags": ours.flags, "params": dataclasses.asdict(ours.params)},
        "variants": {v.name: {"argv": v.argv, "flags": v.flags, "params": dataclasses.asdict(v.params)}
                     for v in cfg.variants},
        "ffmpeg_params": dataclasses.asdict(ffmpeg_baselines.BaselineParams()),
        "versions": versions(),
        "clips": [],
    }
    for clip in clips:
        r["clips"].append(run_clip(clip, cfg, progress))
    if any(c.cell is not None and not c.cell.is_clean for c in clips):
        r["robustness"] = robustness_rows(r)
    if cfg.lookaheads:
        r["settings"]["lookaheads_s"] = list(cfg.lookaheads)
        plot = Path(cfg.work) / "latency_curve.png"
        latency_curve.plot(r["clips"], plot)
        r["latency_plot"] = str(plot)
    r["seconds"] = time.time() - started
    return r


def progress_to_stderr(t0: float | None = None) -> Progress:
    start = time.perf_counter() if t0 is None else t0

    def say(msg: str) -> None:
        print(f"[{time.perf_counter() - start:7.1f} s] {msg}", file=sys.stderr, flush=True)

    return say

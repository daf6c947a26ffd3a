"""Quality benchmark: ours against the 2D stabilisers people use, on real and known-shake clips.

Clips (TUM layout, read with :class:`~quick_stream.io.sources.tum.TumSource`):

* ``DATA/7scenes_redkitchen``, every frame (``frames`` shortens every clip to its first N);
* known-shake clips made from it by the external shake tool (:mod:`.shake_clips`): per
  ``SEED:FIRST-LAST`` a shaken clip (RMS pitch/yaw/roll, default 0.6/0.6/0.8 deg) and its
  unshaken reference (same seed, frames and crop, no shake), cached under ``WORK/clips``.

Methods, all given the same BGR input frames and all scored by :mod:`quick_stream.quality.metrics`
(:class:`~quick_stream.quality.metrics.MetricsAccumulator`, one scorer for everyone) plus the
border-free cropping of :mod:`quick_stream.quality.metrics_border`:

* ``ours``: the stabiliser at exactly the settings ``quick-stream stabilize`` uses with no flags
  (the stabiliser flags of :mod:`quick_stream.io.stabilizer_flags` parsed from an empty argv, then
  ``stabilizer_params``), and every ``--variant NAME='--flag value ...'`` (the same flags);
* FFmpeg vid.stab (two passes) and deshake (:mod:`.ffmpeg_baselines`);
* python ``vidstab`` and vidgear's ``Stabilizer`` at their defaults, when importable
  (:mod:`.peers`: how their delayed outputs are aligned with the inputs);
* the textbook LK + moving-average stabiliser (:mod:`.lk_average`);
* the unstabilised input.

Columns: residual jitter (px, deg), cropping, border-free cropping, distortion, stability (as
``quick_stream.quality.metrics`` defines it), the method's own wall time per frame (ours: the
stabiliser's push/finish, no reading, no scoring; FFmpeg: its passes on the lossless
intermediate, decoding included; peers: their calls), and failure.

On the known-shake clips, the share of the injected high-frequency rotation ours (and each
variant) removed, per axis: ours' per-frame corrections on the shaken clip and, with the same
settings, on the unshaken reference go to ``WORK/corrections`` and through the tool's
``score_rotation.py`` without and with ``--reference``.
"""
from __future__ import annotations

import dataclasses
import platform
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np

from ..core.frame import BadFrame
from ..core.stabilizer import Stabilizer
from ..io.sources import SourceError
from ..io.sources.tum import TumSource
from ..quality.evaluate import run_timed
from ..quality.metrics import MetricsAccumulator
from ..quality.metrics_border import BorderFreeAccumulator, border_free_cropping
from . import ffmpeg_baselines, lk_average, peers
from .variants import Variant, default_settings
from .shake_clips import DEFAULT_AMPLITUDES, DEFAULT_TOOL, ShakeSpec, make_clip, score_rotation, write_corrections

REAL_CLIP = "7scenes_redkitchen"
DEFAULT_CLIPS = ("7:0-149", "11:100-249")
DEFAULT_WORK = Path("out/bench-quality")
COLUMNS = (("jitter_px", "jitter px", "{:10.3f}"), ("jitter_deg", "jitter deg", "{:10.4f}"),
           ("cropping", "cropping", "{:10.3f}"), ("border_free_cropping", "bf crop", "{:10.3f}"),
           ("distortion", "distortion", "{:10.3f}"), ("stability", "stability", "{:10.3f}"),
           ("ms_per_frame", "ms/frame", "{:10.1f}"), ("failed", "failed", "{!s:>10}"))
AXES = ("pitch", "yaw", "roll", "total")

Progress = Callable[[str], None]


# ----------------------------------------------------------------------------------------------
# configuration and clips


@dataclass
class QualityConfig:
    data: Path = Path("../shared/data")
    frames: int | None = None  # every clip shortened to its first N frames
    clips: list[ShakeSpec] = field(default_factory=lambda: [ShakeSpec.parse(c) for c in DEFAULT_CLIPS])
    shake_tool: Path = DEFAULT_TOOL
    work: Path = DEFAULT_WORK
    variants: list[Variant] = field(default_factory=list)
    baselines: bool = True  # FFmpeg, vidstab, vidgear, LK moving average


@dataclass
class Clip:
    name: str
    folder: Path
    spec: ShakeSpec | None = None  # shaken clips only
    reference: Path | None = None  # the unshaken reference clip's folder
    made: dict = field(default_factory=dict)  # "shaken"/"reference" -> inject command, or "cached"


def source_folder(data: Path) -> Path:
    folder = Path(data) / REAL_CLIP
    if not folder.is_dir():
        raise SourceError(f"TUM folder not found: {folder}")
    return folder


def prepare_clips(cfg: QualityConfig, progress: Progress | None = None) -> list[Clip]:
    """The real clip and the shaken clips with their references (made or taken from the cache)."""
    src = source_folder(cfg.data)
    clips = [Clip(REAL_CLIP, src)]
    for spec in cfg.clips:
        made = {}
        folders = {}
        for kind, s in (("shaken", spec), ("reference", spec.reference())):
            if progress:
                progress(f"clip {s.folder_name(src)}")
            folders[kind], cmd = make_clip(src, s, Path(cfg.work) / "clips", cfg.shake_tool)
            made[kind] = "cached" if cmd is None else cmd
        clips.append(Clip(folders["shaken"].name, folders["shaken"], spec, folders["reference"], made))
    return clips


def load_frames(folder: Path, frames: int | None) -> tuple[list[int], list[np.ndarray], list[int], float]:
    """(seqs, BGR images, timestamps ns, fps) of the readable frames of a TUM clip (first ``frames``)."""
    src = TumSource(folder, count=frames)
    seqs, images, stamps = [], [], []
    for fr in src:
        if isinstance(fr, BadFrame):
            continue
        seqs.append(fr.seq)
        images.append(fr.color)
        stamps.append(fr.timestamp_ns)
    return seqs, images, stamps, src.fps


# ----------------------------------------------------------------------------------------------
# scoring


class Scorer:
    """The one scorer: quality metrics and border-free cropping, frame pair by frame pair."""

    def __init__(self, fps: float) -> None:
        self.metrics = MetricsAccumulator(fps)
        self.border = BorderFreeAccumulator()
        self.seconds = 0.0

    def add(self, input_frame: np.ndarray, output_frame: np.ndarray) -> None:
        t0 = time.perf_counter()
        self.metrics.add(input_frame, output_frame)
        self.border.add(output_frame)
        self.seconds += time.perf_counter() - t0

    def result(self) -> dict:
        m = self.metrics.result().as_dict()
        m.update(self.border.as_dict())
        m["border_free_cropping"] = border_free_cropping(m["cropping"], self.border.scale)
        m["scorer_seconds"] = self.seconds
        return m


def score_frames(inputs: list[np.ndarray], outputs: Iterable[np.ndarray], fps: float) -> dict:
    """Metrics of ``outputs`` (aligned with ``inputs``, same count) with :class:`Scorer`."""
    sc = Scorer(fps)
    n = 0
    for a, b in zip(inputs, outputs):
        sc.add(a, b)
        n += 1
    if n != len(inputs):
        raise ValueError(f"{n} output frames for {len(inputs)} inputs")
    return sc.result()


def _row(status: str = "ok", **kw: object) -> dict:
    return {"status": status, **kw}


# ----------------------------------------------------------------------------------------------
# methods


def run_ours(folder: Path, variant: Variant, frames: int | None, inputs: dict[int, np.ndarray] | None,
             fps: float) -> tuple[dict, list[tuple[int, np.ndarray]]]:
    """Stabilise a TUM clip with ``variant``; score against ``inputs`` (seq -> image) unless None.

    Returns (row, [(timestamp_ns, correction g_s)] per output frame).
    """
    src = TumSource(folder, count=frames)
    st = Stabilizer(variant.params)
    scorer = Scorer(fps) if inputs is not None else None
    corrections: list[tuple[int, np.ndarray]] = []
    flagged, missing = 0, 0

    def take(batch: list) -> None:
        nonlocal flagged, missing
        for sf in batch:
            corrections.append((sf.timestamp_ns, np.array(sf.correction.matrix, float)))
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
               segments=len(st.planner.segments))
    if inputs is not None and len(corrections) != len(inputs):
        row["notes"] = [f"{len(corrections)} output frames for {len(inputs)} readable inputs"]
    return row, corrections


def _peer_rows(inputs: list[np.ndarray], fps: float, work: Path, progress: Progress | None) -> tuple[dict, dict]:
    """Rows of the 2D peers (FFmpeg, vidstab, vidgear, LK) and the FFmpeg commands run."""
    rows: dict[str, dict] = {}
    commands: dict = {}
    n = len(inputs)
    problem = ffmpeg_baselines.ffmpeg_problem()
    if problem:
        rows["vid.stab 2-pass (ffmpeg)"] = rows["deshake (ffmpeg)"] = _row("not run", reason=problem)
    else:
        if progress:
            progress("ffmpeg vid.stab + deshake")
        try:
            outs = ffmpeg_baselines.run_baselines(inputs, fps, workdir=work)
            commands = {k: " ".join(v[1:]) for k, v in outs.commands.items()}
            for key, name in (("vidstab", "vid.stab 2-pass (ffmpeg)"), ("deshake", "deshake (ffmpeg)")):
                frames_out = outs.pop(key)
                row = score_frames(inputs, frames_out, fps)
                del frames_out
                row.update(status="ok", seconds=outs.seconds[key], cpu_seconds=outs.cpu_seconds[key],
                           ms_per_frame=1e3 * outs.seconds[key] / n)
                rows[name] = row
        except (RuntimeError, AssertionError, OSError) as e:
            rows.setdefault("vid.stab 2-pass (ffmpeg)", _row("error", reason=str(e)))
            rows.setdefault("deshake (ffmpeg)", _row("error", reason=str(e)))
    avail = peers.available()
    for key, name, runner in (("vidstab", "vidstab (python)", peers.run_vidstab),
                              ("vidgear", "vidgear Stabilizer", peers.run_vidgear)):
        if avail[key]:
            rows[name] = _row("not run", reason=avail[key])
            continue
        if progress:
            progress(name)
        try:
            pr = runner(inputs)
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
    lk = lk_average.stabilize(inputs)
    t = time.perf_counter() - t0
    row = score_frames(inputs, lk, fps)
    row.update(status="ok", seconds=t, ms_per_frame=1e3 * t / n,
               notes=[f"GFTT + LK + estimateAffinePartial2D, centred moving average +-{lk_average.LKParams.radius}"])
    rows["LK moving average"] = row
    return rows, commands


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
        out.update(shake=dataclasses.asdict(clip.spec), reference_folder=str(clip.reference), made=clip.made)
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
        _, corr_ref = run_ours(clip.reference, v, cfg.frames, None, fps)
        est, ref = corr_dir / f"{_slug(v.name)}.txt", corr_dir / f"{_slug(v.name)}_reference.txt"
        write_corrections(est, corr)
        write_corrections(ref, corr_ref)
        shake = clip.folder / "shake.txt"
        try:
            plain = score_rotation(cfg.shake_tool, shake, est)
            with_ref = score_rotation(cfg.shake_tool, shake, est, ref)
            shake_scores[label] = {"without_reference": plain, "with_reference": with_ref,
                                   "corrections": str(est), "reference_corrections": str(ref)}
        except (RuntimeError, ValueError, OSError) as e:
            shake_scores[label] = {"error": str(e)}
    if cfg.baselines:
        rows, commands = _peer_rows(images, fps, Path(cfg.work) / "ffmpeg" / clip.name, say)
        out["methods"].update(rows)
        out["ffmpeg_commands"] = commands
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
    clips = prepare_clips(cfg, progress)
    ours = default_settings()
    r: dict = {
        "settings": {"data": str(cfg.data), "frames": cfg.frames, "clips": [f"{c.seed}:{c.frames}" for c in cfg.clips],
                     "amplitudes_deg": [cfg.clips[0].pitch, cfg.clips[0].yaw, cfg.clips[0].roll]
                     if cfg.clips else list(DEFAULT_AMPLITUDES),
                     "shake_tool": str(cfg.shake_tool), "work": str(cfg.work), "baselines": cfg.baselines,
                     "opencv_threads": 1},
        "ours": {"argv": [], "flags": ours.flags, "params": dataclasses.asdict(ours.params)},
        "variants": {v.name: {"argv": v.argv, "flags": v.flags, "params": dataclasses.asdict(v.params)}
                     for v in cfg.variants},
        "ffmpeg_params": ffmpeg_baselines.BaselineParams.describe(),
        "versions": versions(),
        "clips": [],
    }
    for clip in clips:
        r["clips"].append(run_clip(clip, cfg, progress))
    r["seconds"] = time.time() - started
    return r


def progress_to_stderr(t0: float | None = None) -> Progress:
    start = time.perf_counter() if t0 is None else t0

    def say(msg: str) -> None:
        print(f"[{time.perf_counter() - start:7.1f} s] {msg}", file=sys.stderr, flush=True)

    return say

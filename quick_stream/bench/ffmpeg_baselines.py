"""FFmpeg baselines: two-pass vid.stab and ``deshake``, run on BGR frames, scored with the same metrics.

The comparison with other stabilisers. Debian's ffmpeg
(``sudo apt-get install ffmpeg``) is built with libvidstab; nothing here installs it:
:func:`ensure_ffmpeg` says what is missing and prints that command. The exact command lines
(``W``x``H``, ``FPS`` and file names filled in; :func:`run_baselines` returns
them as run):

0. frames -> lossless intermediate (FFV1, RGB ``bgr0``, in Matroska), raw BGR on stdin::

     ffmpeg -hide_banner -loglevel error -y -f rawvideo -pix_fmt bgr24 -s WxH -r FPS -i -
            -c:v ffv1 -level 3 -pix_fmt bgr0 input.mkv

1. vid.stab pass 1 (detect; these are the filter's defaults, spelled out)::

     ffmpeg -hide_banner -loglevel error -y -i input.mkv
            -vf format=yuv444p,vidstabdetect=shakiness=5:accuracy=15:result=transforms.trf -f null -

2. vid.stab pass 2 (transform), decoded straight to raw BGR on stdout::

     ffmpeg -hide_banner -loglevel error -y -i input.mkv
            -vf format=yuv444p,vidstabtransform=input=transforms.trf:smoothing=10:optalgo=gauss:optzoom=1:zoom=0:crop=keep:interpol=bilinear
            -fps_mode passthrough -f rawvideo -pix_fmt bgr24 -

   ``smoothing=10`` (a 21-frame window, 0.7 s at 30 fps) is the value the
   vid.stab README documents as default; Debian's ffmpeg 5.1 build defaults to
   15, so it is given explicitly. The README's "smooth even more" example uses
   30, which on 30-frame evaluation clips amounts to a near-tripod; pass
   ``smoothing=30`` to :class:`BaselineParams` for that. ``optzoom=1`` (default)
   zooms in by one static factor chosen from the whole clip so that borders are
   rare, ``crop=keep`` (default) fills any remaining border from the previous
   frame, so the output is border-free as a typical user would get it. The
   README also recommends ``unsharp=5:5:0.8:3:3:0.4`` after the transform; it
   is NOT applied (it would change the image, not the motion).

3. deshake (single pass, defaults spelled out)::

     ffmpeg -hide_banner -loglevel error -y -i input.mkv
            -vf format=yuv444p,deshake=rx=16:ry=16:edge=mirror:blocksize=8:contrast=125
            -fps_mode passthrough -f rawvideo -pix_fmt bgr24 -

   ``edge=mirror`` (the default) fills uncovered borders with the mirrored
   image, so there are no black borders; deshake does not zoom, so its
   cropping is ~1 and its borders are mirrored content instead.

``format=yuv444p`` comes first in every chain: libvidstab 1.1 (Debian 12)
aborts on the packed RGB that ffmpeg would otherwise negotiate from the RGB
intermediate (``vsFrameAllocate: Assertion fi->planes==1``), and 4:4:4 avoids
chroma subsampling; the outputs are converted back to BGR. (Deshake's
``edge=blank`` zeroes the YUV planes, i.e. paints borders green, not black.)
``-fps_mode passthrough`` keeps one output frame per input frame, which is
asserted. Options not listed (vid.stab ``relative``, ``maxshift``, ``maxangle``,
``stepsize``, ``mincontrast``; deshake's search strategy) stay at ffmpeg's
defaults.

``python -m quick_stream.bench.ffmpeg_baselines [FOLDER] [--frames N]`` runs
both baselines on a TUM-layout folder and prints the metrics table.
"""
from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..quality.metrics import MetricParams, evaluate_sequence

REQUIRED_FILTERS = ("vidstabdetect", "vidstabtransform", "deshake")
QUIET = ["-hide_banner", "-loglevel", "error", "-y"]
INSTALL_COMMAND = "sudo apt-get install ffmpeg"  # Debian/Ubuntu; their ffmpeg has libvidstab


@dataclass
class BaselineParams:
    """Filter options of the FFmpeg baselines (module docstring: why these values)."""

    shakiness: int = 5  # vidstabdetect: 1 (little) .. 10 (strong)
    accuracy: int = 15  # vidstabdetect: 1 .. 15
    smoothing: int = 10  # vidstabtransform: window of 2 * smoothing + 1 frames
    optzoom: int = 1  # vidstabtransform: 0 none, 1 static optimal zoom, 2 adaptive zoom
    zoom: float = 0.0  # vidstabtransform: extra zoom in percent
    crop: str = "keep"  # vidstabtransform: keep (fill borders from previous frame) | black
    deshake_edge: str = "mirror"  # deshake: blank | original | clamp | mirror
    deshake_rx: int = 16  # deshake: search range in px (max 64)
    deshake_ry: int = 16

    def filters(self) -> dict[str, str]:
        """The -vf strings: vidstab detect, vidstab transform, deshake."""
        return {
            "vidstabdetect": f"format=yuv444p,vidstabdetect=shakiness={self.shakiness}:accuracy={self.accuracy}"
                             f":result=transforms.trf",
            "vidstabtransform": f"format=yuv444p,vidstabtransform=input=transforms.trf:smoothing={self.smoothing}:optalgo=gauss"
                                f":optzoom={self.optzoom}:zoom={self.zoom:g}:crop={self.crop}:interpol=bilinear",
            "deshake": f"format=yuv444p,deshake=rx={self.deshake_rx}:ry={self.deshake_ry}:edge={self.deshake_edge}"
                       f":blocksize=8:contrast=125",
        }


class BaselineOutputs(dict):
    """``{"vidstab": frames, "deshake": frames}`` plus the command lines run and their wall times."""

    def __init__(self) -> None:
        super().__init__()
        self.commands: dict[str, list[str]] = {}  # step name -> argv
        self.seconds: dict[str, float] = {}  # method -> wall time of its ffmpeg passes
        self.cpu_seconds: dict[str, float] = {}  # method -> CPU time (user + system) of its ffmpeg passes
        self.ffmpeg_version: str = ""


def _filters_present(ffmpeg: str) -> set[str]:
    out = subprocess.run([ffmpeg, "-hide_banner", "-filters"], capture_output=True, text=True, check=True).stdout
    return {ln.split()[1] for ln in out.splitlines() if len(ln.split()) >= 3 and ln.split()[1] in REQUIRED_FILTERS}


def ffmpeg_problem() -> str:
    """Why the FFmpeg baselines cannot run here, with the command that fixes it; "" when they can."""
    try:
        ensure_ffmpeg()
    except RuntimeError as e:
        return str(e)
    return ""


def ensure_ffmpeg() -> str:
    """``ffmpeg`` with vidstabdetect, vidstabtransform and deshake, else RuntimeError saying how to install it.

    Nothing is installed here: the message names the command (:data:`INSTALL_COMMAND`, Debian's
    ffmpeg, which is built with libvidstab).
    """
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg is None:
        raise RuntimeError(f"ffmpeg is not on PATH; install it with: {INSTALL_COMMAND}")
    try:
        present = _filters_present(ffmpeg)
    except (OSError, subprocess.CalledProcessError) as e:
        raise RuntimeError(f"cannot list the filters of {ffmpeg}: {e}") from e
    missing = sorted(set(REQUIRED_FILTERS) - present)
    if missing:
        raise RuntimeError(f"{ffmpeg} lacks the filter(s) {missing} (needs a build with --enable-libvidstab, "
                           f"e.g. Debian's: {INSTALL_COMMAND})")
    return ffmpeg


def ffmpeg_version(ffmpeg: str | None = None) -> str:
    """The first line of ``ffmpeg -version`` of ``ffmpeg`` (default: the one :func:`ensure_ffmpeg`
    finds); "" when there is no usable ffmpeg (nothing is installed)."""
    try:
        ffmpeg = ffmpeg or ensure_ffmpeg()
        return subprocess.run([ffmpeg, "-version"], capture_output=True, text=True).stdout.split("\n")[0]
    except (RuntimeError, OSError):
        return ""


def run_ffmpeg(argv: list[str], cwd: Path, stdin: bytes | None = None) -> bytes:
    r = subprocess.run(argv, cwd=cwd, input=stdin, capture_output=True)
    if r.returncode != 0:
        raise RuntimeError(f"ffmpeg failed (rc {r.returncode}): {' '.join(argv)}\n{r.stderr.decode()[-1500:]}")
    return r.stdout


def _decode(raw: bytes, n: int, h: int, w: int, what: str) -> list[np.ndarray]:
    size = h * w * 3
    if len(raw) != n * size:
        raise AssertionError(f"{what}: got {len(raw) / size:g} frames of {w}x{h}, expected {n}")
    arr = np.frombuffer(raw, np.uint8).reshape(n, h, w, 3)
    return [arr[i].copy() for i in range(n)]


def run_baselines(frames: list[np.ndarray], fps: float = 30.0, workdir: Path | None = None,
                  params: BaselineParams | None = None, ffmpeg: str | None = None) -> BaselineOutputs:
    """Stabilise BGR ``frames`` with vid.stab (two passes) and deshake; same frame count and size out.

    ``workdir`` holds input.mkv and transforms.trf (a temporary folder when None).
    ``ffmpeg`` defaults to :func:`ensure_ffmpeg` (RuntimeError with the install command when missing).
    """
    if not frames:
        raise ValueError("no frames")
    h, w = frames[0].shape[:2]
    if any(f.shape != (h, w, 3) or f.dtype != np.uint8 for f in frames):
        raise ValueError("frames must all be uint8 BGR of one size")
    params = params or BaselineParams()
    ffmpeg = ffmpeg or ensure_ffmpeg()
    if workdir is None:
        with tempfile.TemporaryDirectory(prefix="qs_ffmpeg_") as tmp:
            return run_baselines(frames, fps, Path(tmp), params, ffmpeg)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    vf = params.filters()
    n = len(frames)
    out = BaselineOutputs()
    out.ffmpeg_version = ffmpeg_version(ffmpeg)
    to_raw = ["-fps_mode", "passthrough", "-f", "rawvideo", "-pix_fmt", "bgr24", "-"]
    steps = {
        "encode": [ffmpeg, *QUIET, "-f", "rawvideo", "-pix_fmt", "bgr24", "-s", f"{w}x{h}", "-r", f"{fps:g}",
                   "-i", "-", "-c:v", "ffv1", "-level", "3", "-pix_fmt", "bgr0", "input.mkv"],
        "vidstab pass 1": [ffmpeg, *QUIET, "-i", "input.mkv", "-vf", vf["vidstabdetect"], "-f", "null", "-"],
        "vidstab pass 2": [ffmpeg, *QUIET, "-i", "input.mkv", "-vf", vf["vidstabtransform"], *to_raw],
        "deshake": [ffmpeg, *QUIET, "-i", "input.mkv", "-vf", vf["deshake"], *to_raw],
    }
    out.commands = steps
    run_ffmpeg(steps["encode"], workdir, b"".join(np.ascontiguousarray(f).tobytes() for f in frames))
    t0, c0 = time.perf_counter(), children_cpu()
    run_ffmpeg(steps["vidstab pass 1"], workdir)
    out["vidstab"] = _decode(run_ffmpeg(steps["vidstab pass 2"], workdir), n, h, w, "vidstab")
    out.seconds["vidstab"], out.cpu_seconds["vidstab"] = time.perf_counter() - t0, children_cpu() - c0
    t0, c0 = time.perf_counter(), children_cpu()
    out["deshake"] = _decode(run_ffmpeg(steps["deshake"], workdir), n, h, w, "deshake")
    out.seconds["deshake"], out.cpu_seconds["deshake"] = time.perf_counter() - t0, children_cpu() - c0
    return out


def children_cpu() -> float:
    """User + system CPU seconds of this process's finished children (the ffmpeg runs)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def load_tum_rgb(folder: Path, frames: int | None = None) -> list[np.ndarray]:
    """The colour images listed in ``folder/rgb.txt`` (TUM layout), in order, as BGR."""
    folder = Path(folder)
    names = [ln.split()[1] for ln in (folder / "rgb.txt").read_text().splitlines()
             if ln.strip() and not ln.startswith("#")]
    imgs = []
    for name in names[:frames]:
        im = cv2.imread(str(folder / name), cv2.IMREAD_COLOR)
        if im is None:
            raise FileNotFoundError(folder / name)
        imgs.append(im)
    return imgs


def run(folder: Path, frames: int | None = 60, fps: float = 30.0, params: BaselineParams | None = None,
        metric_params: MetricParams | None = None) -> dict:
    """Input (identity), vid.stab and deshake on one TUM-layout clip, each scored with ``evaluate_sequence``."""
    cv2.setNumThreads(1)
    ffmpeg = ensure_ffmpeg()
    inputs = load_tum_rgb(folder, frames)
    outs = run_baselines(inputs, fps, params=params, ffmpeg=ffmpeg)
    result = {"folder": str(folder), "frames": len(inputs), "ffmpeg": outs.ffmpeg_version,
              "commands": {k: " ".join(v[1:]) for k, v in outs.commands.items()},
              "ffmpeg_seconds": outs.seconds, "methods": {}}
    for name, frames_out in (("input", inputs), ("vidstab", outs["vidstab"]), ("deshake", outs["deshake"])):
        m = evaluate_sequence(inputs, frames_out, fps, metric_params)
        result["methods"][name] = m.as_dict()
        result["methods"][name]["ms_per_frame"] = 1e3 * m.seconds / len(inputs)
    return result


def format_table(r: dict) -> str:
    cols = ("cropping", "distortion", "stability", "stability_translation", "stability_rotation",
            "jitter_px", "jitter_deg", "failed")
    lines = [f"{r['folder']}: {r['frames']} frames; {r['ffmpeg']}",
             f"{'method':10s} " + " ".join(f"{c[:12]:>12s}" for c in cols) + f" {'metric ms/f':>12s}"]
    for name, m in r["methods"].items():
        vals = " ".join(f"{m[c]!s:>12s}" if isinstance(m[c], bool) else f"{m[c]:12.3f}" for c in cols)
        lines.append(f"{name:10s} {vals} {m['ms_per_frame']:12.1f}")
    lines.append("input jitter: {:.3f} px, {:.3f} deg".format(
        r["methods"]["input"]["input_jitter_px"], r["methods"]["input"]["input_jitter_deg"]))
    lines += [f"  {k}: ffmpeg {v}" for k, v in r["commands"].items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="vid.stab and deshake baselines scored with quick_stream.quality.metrics")
    ap.add_argument("folder", type=Path, nargs="?", default=Path("../shared/data/7scenes_redkitchen"))
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--smoothing", type=int, default=BaselineParams.smoothing)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    try:
        r = run(a.folder, a.frames, params=BaselineParams(smoothing=a.smoothing))
    except RuntimeError as e:
        print(f"ffmpeg baselines: {e}")
        return 2
    print(json.dumps(r, indent=2, default=float) if a.json else format_table(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

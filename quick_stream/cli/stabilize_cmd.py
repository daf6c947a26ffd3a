"""``quick-stream stabilize``: a source to a stabilized MP4 and/or PNG frames, with a JSON report and a path plot.

Runs the whole stabilizer in this process (scene flow, motion, keyframes and the
optimal path, content-preserving warp, framing), the same library objects the
streaming services use. Prints a progress bar with frames/s on stderr and a
summary on stdout (frames are read ahead, and the video written, in worker threads); the JSON
report holds per-stage ms, segments, failures, the
per-frame stabilizing transformations and, for sources with ground truth, the
camera shake before and after.
"""
from __future__ import annotations

import argparse
import itertools
from collections import Counter
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from ..core.motion import integrate_path
from ..core.path.planner import CORRECTION_MOTIONS
from ..core.stabilizer import StabilizedFrame, Stabilizer
from ..io.plot import path_components, plot_paths
from ..io.files import write_file
from ..io.sinks import VIDEO_CODECS, BackgroundSink, VideoSink, check_video
from ..core.settings import settings_dict, settings_digest
from ..io.sources import SourceError, open_source, source_settings
from ..io.sources.prefetch import Prefetch
from ..quality.evaluation.shake import shake
from ..quality.metrics import MetricsAccumulator
from ..stream import argtypes as at
from ..io.stabilizer_flags import add_stabilizer_args, path_label, stabilizer_params


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stabilize", help="stabilize a source into a video", description=at.plain_text(__doc__),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", default="synthetic", metavar="SPEC",
                   help="synthetic[:k=v,...], tum:PATH or mcap:FILE (default: synthetic)")
    p.add_argument("--frames", type=at.positive_int, default=None,
                   help="stabilize at most this many frames (default: all)")
    add_stabilizer_args(p)
    g = p.add_argument_group("outputs", "Never overwritten: a default name gets the next free number, the same\n"
                             "for the video, report and plot of one run (out/stabilized-1.mp4,\n"
                             "out/report-1.json, out/path-1.png); a named file that exists is refused\n"
                             "unless --force.")
    g.add_argument("--output", type=at.output_file("--output", at.VIDEO_SUFFIXES, "video"), metavar="FILE",
                   default=at.default_name("out/stabilized.mp4"), help="MP4 file, '' for none (default: %(default)s)")
    g.add_argument("--video-codec", choices=VIDEO_CODECS, default="mp4v",
                   help="--output's codec: mp4v (MPEG-4 Part 2) or mjpeg (JPEG quality 90: 3x the file size, "
                   "8 dB closer to the render, 1.5 against 2.5 ms a 640x480 frame to encode; default mp4v)")
    g.add_argument("--png", type=at.output_dir("--png", files="*.png"), default=None, metavar="DIR",
                   help="also write every stabilized frame as PNG here (default: none)")
    g.add_argument("--report", type=at.output_file("--report"), default=at.default_name("out/report.json"),
                   metavar="FILE", help="JSON report file, '' for none (default: %(default)s)")
    g.add_argument("--plot", type=at.image_file("--plot"), default=at.default_name("out/path.png"), metavar="FILE",
                   help="PNG plot of the camera path, '' for none (default: %(default)s)")
    g.add_argument("--force", action="store_true", help=at.FORCE_HELP)
    p.add_argument("--no-metrics", action="store_true",
                   help="skip the quality metrics (cropping, distortion, stability, jitter; ~65 ms per frame)")
    p.add_argument("--threads", type=at.positive_int, default=None,
                   help="OpenCV threads (default: one per core this process may use; the output is the same "
                        "bit for bit with any number)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


class Progress:
    def __init__(self, total: int | None, enabled: bool) -> None:
        self.total, self.enabled, self.t0, self.n = total, enabled, time.perf_counter(), 0

    def update(self, n: int) -> None:
        self.n += n
        if not self.enabled or n == 0:
            return
        dt = time.perf_counter() - self.t0
        fps = self.n / dt if dt > 0 else 0.0
        if self.total:
            done = int(30 * self.n / self.total)
            bar = "#" * done + "-" * (30 - done)
            sys.stderr.write(f"\r[{bar}] {self.n}/{self.total} frames {fps:6.1f} fps")
        else:
            sys.stderr.write(f"\r{self.n} frames {fps:6.1f} fps")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except OSError as e:  # an output that went bad after the checks (a full disk, a codec refusing the file)
        text = f"{e.filename}: {e.strerror}" if e.filename and e.strerror else str(e)
        flag = next((flag for flag, v in (("--output", args.output), ("--png", args.png), ("--report", args.report),
                                          ("--plot", args.plot)) if v and str(v) in text), None)
        print(f"\nquick-stream stabilize: {flag + ': ' if flag else ''}{text}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    cv2.setNumThreads(args.threads or len(os.sched_getaffinity(0)))
    try:
        check_video(args.output, args.video_codec)
        source = open_source(args.source)
        params = stabilizer_params(args, recorded=source_settings(args.source))
        stab = Stabilizer(params, keep_inputs=not args.no_metrics, keep_motions=True)
    except (SourceError, ValueError) as e:
        print(f"quick-stream stabilize: {e}", file=sys.stderr)
        return 2
    total = len(source) if args.frames is None else min(args.frames, len(source))
    # the next frames are read, and the output written, on the second core while this one stabilizes
    frames = Prefetch(source if args.frames is None else itertools.islice(source, args.frames))
    sink = BackgroundSink(VideoSink(args.output or None, args.png, source.fps, args.video_codec))
    records: list[dict] = []
    out_ms: list[float] = []
    progress = Progress(total, not args.quiet)
    metrics = None if args.no_metrics else MetricsAccumulator(source.fps)
    metrics_ms = 0.0
    true_poses: dict[int, np.ndarray] = {}

    def emit(batch: list[StabilizedFrame]) -> None:
        nonlocal metrics_ms
        if metrics is not None:
            t0 = time.perf_counter()
            for sf in batch:
                metrics.add(sf.input_image, sf.image)
                sf.input_image = None
            metrics_ms += (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        for sf in batch:
            sink.write(sf.seq, sf.image)
            c = sf.correction
            records.append({"seq": sf.seq, "timestamp_ns": sf.timestamp_ns, "segment": c.segment,
                            "keyframe": c.keyframe, "valid": c.valid and sf.mesh.ok, "flags": sf.flags,
                            "motion": c.motion, "uncorrected": not c.valid,
                            "zoom": sf.zoom, "correction": c.matrix.round(9).tolist()})
        out_ms.append((time.perf_counter() - t0) * 1e3)
        progress.update(len(batch))

    t_start = time.perf_counter()
    read_ms: list[float] = []
    it = iter(frames)
    try:
        while True:
            t0 = time.perf_counter()
            fr = next(it, None)
            read_ms.append((time.perf_counter() - t0) * 1e3)
            if fr is None:
                break
            if getattr(fr, "pose", None) is not None:
                true_poses[fr.seq] = fr.pose
            emit(stab.push(fr))
        emit(stab.finish())
    finally:
        frames.close()
        sink.close()
        progress.close()
    wall = time.perf_counter() - t_start

    timing = stab.timer.summary()
    compute_ms = sum(s["mean"] for k, s in timing.items())
    report: dict = {
        "source": args.source,
        "settings": settings_dict(stab.params),
        "settings_digest": settings_digest(stab.params),
        "frames_in": total, "frames_out": len(records),
        "wall_s": wall,
        "fps_wall": len(records) / wall if wall > 0 else 0.0,
        "fps_compute": 1e3 / compute_ms if compute_ms > 0 else 0.0,
        "timing_ms": timing,
        "io_ms": {"read": float(np.mean(read_ms)) if read_ms else 0.0,
                  "write_per_segment": float(np.mean(out_ms)) if out_ms else 0.0},
        "metrics": metrics.result().as_dict() if metrics is not None and records else None,
        "metrics_ms_per_frame": metrics_ms / max(len(records), 1),
        "segments": [s.__dict__ for s in stab.planner.segments],
        "bad_frames": stab.bad_frames,
        "flagged_frames": [{"seq": r["seq"], "flags": r["flags"]} for r in records if r["flags"]],
        "uncorrected_frames": sum(r["uncorrected"] for r in records),
        "bordered_frames": stab.render.filler.bordered,  # output pixels no source reached (the renderer's own count)
        "frames_by_motion": {k: n for k in CORRECTION_MOTIONS if (n := sum(r["motion"] == k for r in records))},
        "frames_reached_over": stab.flow.reached_over,  # their own flow starved: the motion across them split
        "flows_lifted_loose": stab.flow.loose,  # the strict tests kept too few pairs (motion blur): docs/method.md (1c)
        "frames": records,
    }
    seqs = [r["seq"] for r in records]
    gs = np.array([r["correction"] for r in records]) if records else np.zeros((0, 4, 4))
    motions = {m.seq_next: m.matrix for m in stab.motions}
    if records:
        est = integrate_path([motions.get(s, np.eye(4)) for s in seqs[1:]])
        if args.plot:
            Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
            plot_paths({"before": path_components(est), "after": path_components(est @ gs)}, source.fps, args.plot)
            report["plot"] = args.plot
        # Shake against ground truth needs the shake-free path as reference (the synthetic
        # source has it); without one the high-pass would count intended motion as shake.
        if len(true_poses) == len(seqs) and len(seqs) > 10 and hasattr(source, "intended_poses"):
            T = np.array([true_poses[s] for s in seqs])
            ref = source.intended_poses()[seqs]
            report["shake"] = {"input": shake(T, source.fps, reference=ref),
                               "stabilized": shake(T @ gs, source.fps, reference=ref),
                               "reference": "intended (shake-free) path"}
    if args.report:
        Path(args.report).parent.mkdir(parents=True, exist_ok=True)
        write_file(args.report, json.dumps(report, indent=1, default=float).encode())

    print(f"stabilized {len(records)} of {total} frames from {args.source} "
          f"({params.motion.group}, {path_label(params.planner)}, {params.framing.mode} framing) in {wall:.1f} s")
    print(f"stabilizer: {report['fps_compute']:.1f} frames/s (all stages, no I/O); overall {report['fps_wall']:.1f} "
          f"frames/s including reading, writing"
          + (f" and quality metrics ({report['metrics_ms_per_frame']:.0f} ms/frame; --no-metrics skips them)"
             if report["metrics"] else ""))
    print("ms per frame by stage: " + ", ".join(f"{k} {s['mean']:.2f}" for k, s in timing.items()))
    if report["metrics"]:
        m = report["metrics"]
        print(f"quality: cropping {m['cropping']:.3f}, distortion {m['distortion']:.3f}, stability "
              f"{m['stability']:.3f}, residual jitter {m['jitter_px']:.2f} px / {m['jitter_deg']:.3f} deg "
              f"(input {m['input_jitter_px']:.2f} px / {m['input_jitter_deg']:.3f} deg)"
              + (f"; FAILED: {m['failure_reason']}" if m["failed"] else ""))
    print(f"segments: {len(report['segments'])}, bad frames: {len(stab.bad_frames)}, "
          f"flagged frames: {len(report['flagged_frames'])}, uncorrected frames: {report['uncorrected_frames']}, "
          f"frames with a border: {report['bordered_frames']}")
    print("frames by how their motion was known (docs/method.md 2.4): "
          + ", ".join(f"{k} {n}" for k, n in report["frames_by_motion"].items())
          + f"; frames reached over (their own flow starved) {report['frames_reached_over']}"
          + f"; flows lifted loose (motion blur) {report['flows_lifted_loose']}")
    if "shake" in report:
        a, b = report["shake"]["input"], report["shake"]["stabilized"]
        print(f"high-frequency shake (vs ground truth): rotation {a['rot_deg']:.3f} -> {b['rot_deg']:.4f} deg "
              f"({a['rot_deg'] / max(b['rot_deg'], 1e-12):.1f}x), roll {a['roll_deg']:.3f} -> {b['roll_deg']:.4f} deg, "
              f"translation {a['trans_mm']:.2f} -> {b['trans_mm']:.3f} mm "
              f"({a['trans_mm'] / max(b['trans_mm'], 1e-12):.1f}x)")
    # only what is on disk and complete: the sink checked the video when it closed it
    outputs = [x for x, done in ((args.output, sink.written), (args.png, sink.written), (args.report, True),
                                 (args.plot, "plot" in report)) if x and done]
    if outputs:
        print("wrote " + ", ".join(outputs))
    if not records:
        print(f"quick-stream stabilize: {nothing_stabilized(total, stab.bad_frames)}", file=sys.stderr)
        return 1
    return 0


def nothing_stabilized(total: int, bad_frames: list[dict]) -> str:
    """One line saying why no frame of ``total`` came out: the frames' errors, most frequent first,
    each without its file (``<file>: depth image not found`` -> ``depth image not found``), and the
    first bad frame's whole error."""
    if total == 0:
        return "0 frames stabilized: the source has no frames"
    if not bad_frames:
        return f"0 of {total} frames stabilized"
    why = Counter(str(b["error"]).rsplit(": ", 1)[-1] for b in bad_frames).most_common()
    first = bad_frames[0]
    text = (f"{why[0][0]} for every frame" if len(why) == 1 and len(bad_frames) == total
            else ", ".join(f"{k} ({n} frames)" for k, n in why[:3]) + (", ..." if len(why) > 3 else ""))
    return f"0 of {total} frames stabilized: {text} (first: frame {first['seq']}: {first['error']})"

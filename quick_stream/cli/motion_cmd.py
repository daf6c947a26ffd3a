"""``quick-stream motion``: camera motion from a source, timed per stage, checked against ground truth.

Runs a source through scene flow and the chosen group/estimator; prints ms per
frame per stage and, where the source has ground-truth poses, the relative pose
error per frame pair (rotation deg, translation mm: median, mean, RMSE).
``--compare-opencv`` runs ``cv2.Odometry`` (RGB_DEPTH) on the same pairs. Progress
goes to stderr; ``--json FILE`` (``-``: standard output) writes the report as JSON.
"""
from __future__ import annotations

import argparse
import itertools
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from ..core.frame import RGBDFrame
from ..core.lie import GROUPS
from ..core.motion import ESTIMATORS, KINDS, MotionParams, integrate_path
from ..core.motion_pipeline import MotionPipeline, run_motion, true_motion
from ..core.sceneflow import DIS_PRESETS, SceneFlowParams
from ..core.params import STABILIZER_TRANSLATION_PRIOR_MM
from ..io.sources import SourceError, open_source
from ..io.sources.trajectory import write_tum_trajectory
from ..quality.evaluation.opencv_odometry import OpenCVOdometry
from ..quality.evaluation.rpe import ErrorStats, pair_error_stats, relative_pose_error
from ..stream import argtypes as at
from .jsonout import add_json, text_out, write_json
from .progress import Progress

log = logging.getLogger("quick_stream.core.motion")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "motion",
        help="estimate camera motion from a source and evaluate it",
        description=at.plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--source", default="synthetic", metavar="SPEC",
                   help="synthetic[:key=value,...], tum:PATH[,key=value,...] or mcap:FILE (default: synthetic)")
    p.add_argument("--frames", type=at.positive_int, default=None,
                   help="process at most this many frames (default: all)")
    p.add_argument("--group", choices=sorted(GROUPS), default="se3", help="Lie group (default: se3)")
    p.add_argument("--estimator", choices=ESTIMATORS, default="exact", help="motion estimator (default: exact)")
    p.add_argument("--preset", choices=sorted(DIS_PRESETS), default=SceneFlowParams.preset,
                   help=f"DIS optical-flow preset (default: {SceneFlowParams.preset})")
    p.add_argument("--flow-scale", type=at.float_in(0.1, 1.0), default=SceneFlowParams.flow_scale,
                   help="compute optical flow on images scaled by this factor, 0.1-1 (default: 1) ...")
    p.add_argument("--flow-max-side", type=at.nonneg_int, default=SceneFlowParams.flow_max_side, metavar="PX",
                   help="... or less, so that their longer side is at most PX (0: no limit; default "
                   f"{SceneFlowParams.flow_max_side}: 1280x720 flows at 0.5)")
    p.add_argument("--no-fb-check", action="store_true", help="skip the forward-backward occlusion test")
    p.add_argument("--max-points", type=at.int_in(3), default=SceneFlowParams.max_points,
                   help=f"scene-flow pairs kept per frame pair (default: {SceneFlowParams.max_points})")
    p.add_argument("--translation-prior", type=at.float_in(0.0, 1e3), default=STABILIZER_TRANSLATION_PRIOR_MM,
                   metavar="MM", help="the fit's translation prior, std per frame step in mm (docs/method.md (3n); "
                   f"default {STABILIZER_TRANSLATION_PRIOR_MM:g}, the stabilizer's; 0: the free fit)")
    p.add_argument("--threads", type=at.positive_int, default=1,
                   help="OpenCV threads (default: 1, one core, as each service runs)")
    p.add_argument("--compare-opencv", action="store_true",
                   help="also run OpenCV RGB-D odometry (cv2.Odometry, RGB_DEPTH) on the same pairs")
    add_json(p, "the report")
    p.add_argument("--trajectory", type=at.output_file("--trajectory"), metavar="FILE", default=None, nargs="?",
                   const=at.default_name("out/trajectory.txt"),
                   help="write the estimated camera path in TUM format, anchored at the first ground-truth pose "
                        "when the source has one; without FILE to out/trajectory.txt (then -1, ...: never "
                        "overwritten), like stabilize's outputs (default: none)")
    at.add_force(p)
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")


def _fmt_stats(name: str, s: ErrorStats, ms: float) -> str:
    return (f"{name:<24} {s.n:>5} {s.rot_median:>8.4f} {s.rot_mean:>8.4f} {s.rot_rmse:>8.4f} "
            f"{s.trans_median:>8.2f} {s.trans_mean:>8.2f} {s.trans_rmse:>8.2f} {ms:>9.2f}")


DISPLACEMENT_BINS = (0, 5, 10, 20, 30, 45, float("inf"))  # px a pair: fr1/rpy moves up to ~60


def flow_consistency(pairs: list) -> list[dict]:
    """The scene flow's consistency against the image motion (docs/method.md (1a)): per bin of a pair's
    median displacement, the share of its candidates with valid depth that the forward-backward test and
    the Lucas-Kanade refinement rejected, the share kept, and the median rotation error (ground truth)."""
    out = []
    for lo, hi in zip(DISPLACEMENT_BINS, DISPLACEMENT_BINS[1:]):
        sel = [p for p in pairs if lo <= p.displacement_px < hi]
        if not sel:
            continue
        share = {k: [] for k in ("fb_inconsistent", "lk_rejected", "kept")}
        for p in sel:
            c = p.counts
            cand = max(c.get("sampled", 0) - c.get("invalid_depth", 0) - c.get("depth_edge", 0), 1)
            for k in share:
                share[k].append(c.get(k, 0) / cand)
        errs = [relative_pose_error(p.motion.matrix, p.truth)[0] for p in sel if p.truth is not None and p.motion.valid]
        out.append({"bin": f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">={lo:g}", "pairs": len(sel),
                    "fb_rejected": float(np.mean(share["fb_inconsistent"])), "lk_rejected": float(np.mean(share["lk_rejected"])),
                    "kept": float(np.mean(share["kept"])), "rot_median_deg": float(np.median(errs)) if errs else float("nan")})
    return out


def run(args: argparse.Namespace) -> int:
    cv2.setNumThreads(max(1, args.threads))
    try:
        source = open_source(args.source)
        flow_params = SceneFlowParams(
            preset=args.preset, flow_scale=args.flow_scale, flow_max_side=args.flow_max_side,
            fb_check=not args.no_fb_check,
            max_points=args.max_points,
        )
        flow_params.validate()
        motion_params = MotionParams(group=args.group, estimator=args.estimator,
                                     translation_prior_mm=args.translation_prior)
        pipeline = MotionPipeline(flow_params, motion_params)
    except (SourceError, ValueError) as e:
        print(f"quick-stream motion: {e}", file=sys.stderr)
        return 2
    frames = source if args.frames is None else itertools.islice(source, args.frames)
    try:
        total: int | str = len(source) if args.frames is None else min(args.frames, len(source))
    except TypeError:  # a live camera has no length
        total = "?" if args.frames is None else args.frames
    progress = Progress("quick-stream motion", enabled=not args.quiet)

    def counted(items):
        for i, item in enumerate(items, 1):
            yield item
            progress(f"{i}/{total} frames")

    ocv_errors: list[tuple[float, float]] = []
    ocv_ms: list[float] = []
    ocv_failed = 0
    ocv = OpenCVOdometry(source.intrinsics) if args.compare_opencv else None

    def compare(a: RGBDFrame, b: RGBDFrame) -> None:
        nonlocal ocv_failed
        t0 = time.perf_counter()
        g = ocv.camera_motion(a, b)
        ocv_ms.append((time.perf_counter() - t0) * 1e3)
        truth = true_motion(a, b)
        if g is None:
            ocv_failed += 1
        elif truth is not None:
            ocv_errors.append(relative_pose_error(g, truth))

    def on_failure(rec: dict) -> None:
        log.warning("skipping frame %s (%s): %s", rec["seq"], rec["origin"], rec["error"])

    t_start = time.perf_counter()
    with progress:
        result = run_motion(counted(frames), pipeline, on_failure=on_failure, extra=compare if ocv else None)
    wall = time.perf_counter() - t_start

    timing = result.timer.summary()
    ours_ms = float(np.mean([p.flow_ms + p.motion_ms for p in result.pairs])) if result.pairs else float("nan")
    name = f"{args.estimator} {args.group}"
    stats = pair_error_stats(result.pairs)
    invalid = [
        {"seq": p.motion.seq, "seq_next": p.motion.seq_next, "reason": p.motion.reason}
        for p in result.pairs if not p.motion.valid
    ]
    consistency = flow_consistency(result.pairs)
    by_kind = {k: pair_error_stats(p for p in result.pairs if p.motion.kind == k)
               for k in KINDS if k != "none" and any(p.motion.kind == k for p in result.pairs)}
    kinds = {k: sum(p.motion.kind == k for p in result.pairs) for k in KINDS}
    reached = [p for p in result.pairs if p.span is not None]  # parts of a flow that reached over frames
    if reached:
        by_kind["reached over"] = pair_error_stats(reached)
    loose = [p for p in result.pairs if p.counts.get("loose")]  # motions of flows lifted loose (motion blur)
    if loose:
        by_kind["lifted loose"] = pair_error_stats(loose)
    report: dict = {
        "source": args.source,
        "group": args.group,
        "estimator": args.estimator,
        "sceneflow": flow_params.__dict__,
        "frames": len(result.timestamps_ns) + len(result.failures),
        "pairs": len(result.pairs),
        "valid_pairs": len(result.pairs) - len(invalid),
        "wall_s": wall,
        "timing_ms": timing,
        "methods": {name: {"ms_per_pair": ours_ms, **stats.as_dict()}},
        "motions_by_kind": kinds,
        "flow_consistency": consistency,
        "errors_by_kind": {k: s.as_dict() for k, s in by_kind.items()},
        "reached_over": pipeline.flow.reached_over,
        "loose_flows": pipeline.flow.loose,
        "fallbacks": [{"seq": p.motion.seq, "seq_next": p.motion.seq_next, "kind": p.motion.kind,
                       "reason": p.motion.reason} for p in result.pairs
                      if p.motion.kind in ("rotation", "bridge") or p.span is not None],
        "bad_frames": result.failures,
        "invalid_motions": invalid,
    }
    if ocv is not None:
        o = ErrorStats.from_errors([e[0] for e in ocv_errors], [e[1] for e in ocv_errors])
        report["methods"]["opencv rgbd odometry"] = {
            "ms_per_pair": float(np.mean(ocv_ms)) if ocv_ms else float("nan"),
            "failed": ocv_failed,
            **o.as_dict(),
        }

    if args.trajectory:
        path = integrate_path(result.camera_motions)
        if result.first_pose is not None:
            path = result.first_pose @ path
        Path(args.trajectory).parent.mkdir(parents=True, exist_ok=True)
        write_tum_trajectory(args.trajectory, np.asarray(result.timestamps_ns) / 1e9, path)
        report["trajectory"] = args.trajectory

    if args.json:
        write_json(args.json, report)
    out = text_out(args)

    def say(*a: object) -> None:  # the text report: stdout, or stderr when the JSON takes stdout
        print(*a, file=out)

    say(f"source {args.source}: {report['frames']} frames, {report['pairs']} pairs "
        f"({report['valid_pairs']} valid), {len(result.failures)} bad frames, {wall:.1f} s")
    say("\nms per frame, by stage (mean / median / p95):")
    for stage, s in timing.items():
        say(f"  {stage:<8} {s['mean']:8.2f} {s['median']:8.2f} {s['p95']:8.2f}")
    if ocv_ms:
        say(f"  {'opencv':<8} {np.mean(ocv_ms):8.2f} {np.median(ocv_ms):8.2f} {np.percentile(ocv_ms, 95):8.2f}")
    say("\nrelative pose error per frame pair" + ("" if stats.n else " (no ground truth)") + ":")
    say(f"{'method':<24} {'pairs':>5} {'rot med':>8} {'rot mean':>8} {'rot rms':>8} "
        f"{'t med mm':>8} {'t mean':>8} {'t rms':>8} {'ms/pair':>9}")
    for mname, m in report["methods"].items():
        s = ErrorStats(**{k: m[k] for k in ErrorStats.__dataclass_fields__})
        say(_fmt_stats(mname, s, m["ms_per_pair"]))
        if mname == name and len(by_kind) > 1:  # ours by how each motion was known (docs/method.md 2.4)
            for k, ks in by_kind.items():
                say(_fmt_stats(f"  by {k}", ks, float("nan")))
    say("\nscene flow against the image motion (median px a pair): candidates with valid depth the "
        "forward-backward test and Lucas-Kanade rejected, samples kept, rotation error:")
    say(f"{'px':>9} {'pairs':>6} {'fb rej':>7} {'lk rej':>7} {'kept':>7} {'rot med':>8}")
    for row in consistency:
        say(f"{row['bin']:>9} {row['pairs']:>6} {row['fb_rejected']:>7.3f} {row['lk_rejected']:>7.3f} "
            f"{row['kept']:>7.3f} {row['rot_median_deg']:>8.4f}")
    say("\nmotions by how they were known (docs/method.md 2.4): "
        + ", ".join(f"{k} {n}" for k, n in kinds.items())
        + f"; frames reached over {report['reached_over']} ({len(reached)} motions a part of a flow across them)"
        + f"; flows lifted loose {report['loose_flows']} (docs/method.md (1c))")
    for rec in report["fallbacks"][:10]:
        say(f"{rec['kind']} {rec['seq']}->{rec['seq_next']}: {rec['reason']}")
    if len(report["fallbacks"]) > 10:
        say(f"... {len(report['fallbacks']) - 10} more fallbacks")
    for rec in invalid[:10]:
        say(f"invalid motion {rec['seq']}->{rec['seq_next']}: {rec['reason']}")
    if len(invalid) > 10:
        say(f"... {len(invalid) - 10} more invalid motions")
    if args.trajectory:
        say(f"wrote {args.trajectory}")
    return 0

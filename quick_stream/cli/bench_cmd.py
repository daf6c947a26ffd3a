"""``quick-stream bench NAME``: benchmarks that print numbers (speed, accuracy, robustness).

Each prints its table on standard output and its progress on stderr; ``--json FILE``
(``-``: standard output, the table then going to stderr) writes the numbers as JSON.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..core.lie import GROUPS
from ..core.params import LATENCY_NAMES, LATENCY_PRESETS, latency_preset
from ..io.sources import SourceError
from ..stream import argtypes as at
from . import bench_quality_cmd
from .jsonout import add_json, text_out, write_json
from .progress import Progress

if TYPE_CHECKING:
    from ..bench.shake_clips import ShakeSpec

DEFAULT_DATA = Path("../shared/data")


def _bench(b: argparse._SubParsersAction, name: str, help: str,
           description: str | None = None) -> argparse.ArgumentParser:
    """A benchmark's parser; its description is its help, as a sentence, unless given."""
    return b.add_parser(name, help=help, description=description or help[:1].upper() + help[1:] + ".")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark and print its numbers", description=at.plain_text(__doc__),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    b = p.add_subparsers(dest="bench", required=True, metavar="NAME")
    s = _bench(b, "speed", "scene flow + motion ms per stage on one core (synthetic frames)")
    s.add_argument("--pairs", type=at.positive_int, default=100, help="frame pairs timed (default: 100)")
    s.add_argument("--width", type=at.int_in(16, 8192), default=640, help="frame width, 16-8192 (default: 640)")
    s.add_argument("--height", type=at.int_in(16, 8192), default=480, help="frame height, 16-8192 (default: 480)")
    s.add_argument("--group", choices=sorted(GROUPS), default="se3", help="Lie group of the motion (default: se3)")
    s.add_argument("--versus-vidstab", default=None, metavar="tum:PATH",
                   help="instead: this clip through 'quick-stream stabilize --no-metrics' and FFmpeg vid.stab (2 passes) "
                        "side by side, alternated, with the ratios (e.g. tum:../shared/data/7scenes_redkitchen; "
                        "default: none)")
    s.add_argument("--frames", type=at.positive_int, default=None,
                   help="--versus-vidstab: the clip's first N frames (default: all)")
    s.add_argument("--repeat", type=at.positive_int, default=3,
                   help="--versus-vidstab: alternated rounds, medians reported (default: 3)")
    o = _bench(b, "odometry", "relative pose error of exact/induced vs OpenCV odometry")
    o.add_argument("--source", default=f"tum:{DEFAULT_DATA / '7scenes_redkitchen'}", metavar="SPEC",
                   help="the clip, any source spec with ground truth (default: %(default)s)")
    o.add_argument("--frames", type=at.positive_int, default=None, help="use the first N frames (default: all)")
    o.add_argument("--groups", type=at.choice_list(GROUPS), default=("se3",), metavar="G[,G...]",
                   help="comma-separated groups to run exact and induced for (default: se3)")
    o.add_argument("--no-opencv", action="store_true", help="skip OpenCV's RGB-D odometry")
    m = _bench(b, "moving-objects", "robust vs mean estimators on jointvosf_pairs (people moving)")
    m.add_argument("--data", type=Path, default=DEFAULT_DATA, metavar="DIR",
                   help=f"folder holding jointvosf_pairs (default: {DEFAULT_DATA})")
    q = _bench(b, "quality", bench_quality_cmd.HELP, description=bench_quality_cmd.DESCRIPTION)
    bench_quality_cmd.add_arguments(q)
    ra = _bench(b, "rotation", "known-shake clips: which part of the pipeline leaves injected rotation "
                "(motion noise, path, warp; single changes to the defaults)")
    ra.add_argument("--data", type=Path, default=DEFAULT_DATA, metavar="DIR", help=f"folder holding 7scenes_redkitchen "
                    f"(default: {DEFAULT_DATA})")
    ra.add_argument("--clip", dest="clips", action="append", type=at.checked(_clip, "clip"), default=None,
                    metavar="SEED:FIRST-LAST", help="a known-shake clip; repeatable (default: 7:0-149 and 11:100-249)")
    ra.add_argument("--shake-tool", type=Path, default=Path("../shared/tools/shake"), metavar="DIR",
                    help="folder of the shake tool (default: ../shared/tools/shake)")
    ra.add_argument("--work", type=at.output_dir("--work"), default="out/bench-quality", metavar="DIR",
                    help="made clips are cached in DIR/clips (default: out/bench-quality)")
    ps = _bench(b, "path", "optimal-path solver ms per frame for every group (--shake: large-motion "
                "stress: failed segments, iterations, residuals)")
    ps.add_argument("--shake", type=at.checked(_shake, "shake"), default=None, metavar="DEG,M",
                    help="stress mode: random per-frame rotations of DEG degrees and translations of M metres "
                    "(rms) on a smooth path, seeded, e.g. 4,0.05 (default: no stress, the synthetic path)")
    ps.add_argument("--segments", type=at.positive_int, default=None,
                    help="30-frame segments per group (default: 20; with --shake 100)")
    ps.add_argument("--seed", type=at.nonneg_int, default=0, help="--shake: seed of the stress segments (default: 0)")
    for q in (s, o, m, ps, ra):
        add_json(q, "the numbers")
        at.add_force(q)
    pl = _bench(b, "pipeline", "the services under load: latency, throughput, drops, CPU and memory")
    pl.add_argument("--fps", type=at.rates, default=[30.0], metavar="RATE[,RATE...]",
                    help="comma-separated capture rates; 'fast' = as fast as possible (default: 30)")
    pl.add_argument("--seconds", type=at.positive_float, default=120.0,
                    help="measured seconds per rate (default: 120)")
    pl.add_argument("--no-record", action="store_true", help="run without the recorder")
    pl.add_argument("--streams", type=at.int_in(1, 16), default=1,
                    help="cameras side by side, each with its own capture, flow, motion and render (default: 1)")
    pl.add_argument("--size", type=at.frame_size, default="640x480", help="frame size WxH (default: 640x480)")
    pl.add_argument("--replay", action="store_true",
                    help="capture replays a pre-encoded recording (camera-like cost) instead of rendering live")
    pl.add_argument("--out", type=at.output_dir("--out"), default="out/bench-pipeline", metavar="DIR",
                    help="folder for the logs, and the recordings and videos while it runs (default: "
                    "out/bench-pipeline)")
    pl.add_argument("--keep", action="store_true",
                    help="keep the recordings and videos (about 1 GB a 120 s run at 640x480; default: deleted once "
                    "measured, the logs kept; the last line says where and how much)")
    pl.add_argument("--profile", action="store_true",
                    help="also where the CPU goes: each process's by thread, and each service's main thread under "
                    "cProfile on its CPU clock, its functions by own time per stabilized frame (slows the services "
                    "by about half; the profiles in DIR/fps-RATE/profile)")
    pl.add_argument("--latency", type=at.checked(_presets, "latency"), default=None, metavar="PRESET[,PRESET...]",
                    help="run each rate with each of these --latency presets of the motion service (%s) and end "
                    "with a table of each one's delay from capture to publication (default: the default "
                    "preset only)" % ", ".join(LATENCY_PRESETS))
    add_json(pl, "the reports")
    at.add_force(pl)


def _presets(text: str) -> list[str]:
    """``--latency`` for ``bench pipeline``: comma-separated preset names, each a known one."""
    names = [x.strip() for x in text.split(",") if x.strip()]
    if not names:
        raise ValueError(f"expected PRESET[,PRESET...], got {text!r}; known: {list(LATENCY_NAMES)}")
    for n in names:
        latency_preset(n)  # ValueError naming an unknown one
    return names


def _shake(text: str) -> tuple[float, float]:
    """``DEG,M`` for ``bench path --shake``: per-frame shake rotation (deg) and translation (m), rms."""
    parts = text.split(",")
    try:
        deg, m = (float(x) for x in parts) if len(parts) == 2 else (float("nan"),) * 2
    except ValueError:
        deg = m = float("nan")
    if not (0.0 <= deg <= 45.0 and 0.0 <= m <= 1.0):
        raise ValueError(f"must be DEG,M with 0 <= DEG <= 45 and 0 <= M <= 1, got {text!r}")
    return deg, m


def _clip(text: str) -> "ShakeSpec":
    from ..bench.shake_clips import ShakeSpec

    return ShakeSpec.parse(text)


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except SourceError as e:  # a benchmark's clip or --source cannot be opened
        print(f"quick-stream bench {args.bench}: {e}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    progress = Progress(f"quick-stream bench {args.bench}")
    if args.bench == "pipeline":
        from ..bench import pipeline

        with progress:
            return pipeline.main(args.fps, args.seconds, args.out, args.json, record=not args.no_record,
                                 streams=args.streams, size=args.size, replay=args.replay, progress=progress,
                                 keep=args.keep, profile=args.profile, presets=args.latency)
    if args.bench == "quality":
        return bench_quality_cmd.run(args)
    with progress:
        if args.bench == "speed" and args.versus_vidstab:
            from ..bench import speed_versus

            try:
                r = speed_versus.run(args.versus_vidstab, args.frames, args.repeat,
                                     progress=lambda msg: progress(msg, force=True))
            except (RuntimeError, ValueError) as e:
                print(f"quick-stream bench speed: {e}", file=sys.stderr)
                return 2
            text = speed_versus.format_report(r)
        elif args.bench == "speed":
            from ..bench import speed

            r = speed.run(args.pairs, args.width, args.height, args.group, progress=progress)
            text = speed.format_report(r)
        elif args.bench == "odometry":
            from ..bench import odometry

            methods = [(g, e) for g in args.groups for e in ("exact", "induced")]
            r = odometry.run(args.source, methods, opencv=not args.no_opencv, frames=args.frames, progress=progress)
            text = odometry.format_table(r)
        elif args.bench == "rotation":
            from ..bench import rotation_ablation
            from ..bench.shake_clips import ShakeSpec, check_tool

            try:
                check_tool(args.shake_tool)
            except FileNotFoundError as e:
                print(f"quick-stream bench rotation: {e}", file=sys.stderr)
                return 2
            specs = args.clips or [ShakeSpec.parse(c) for c in rotation_ablation.DEFAULT_CLIPS]
            r = rotation_ablation.run(args.data, specs, Path(args.work) / "clips", args.shake_tool,
                                      progress=lambda msg: progress(msg, force=True))
            text = rotation_ablation.format_table(r)
        elif args.bench == "path":
            from ..bench import path_speed

            if args.shake is None:
                r = path_speed.run(args.segments or 20, progress=progress)
                text = path_speed.format_table(r)
            else:
                r = path_speed.run_stress(*args.shake, segments=args.segments or 100, seed=args.seed,
                                          progress=progress)
                text = path_speed.format_stress_table(r, *args.shake)
        else:
            from ..bench import moving_objects

            r = moving_objects.run(args.data, progress=lambda msg: progress(msg, force=True))
            text = moving_objects.format_table(r)
    if args.json:
        write_json(args.json, r)
    print(text, file=text_out(args))
    return 0

"""``quick-stream bench NAME``: benchmarks that print numbers (speed, accuracy, robustness)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

DEFAULT_DATA = Path("../shared/data")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark and print its numbers", description=__doc__)
    b = p.add_subparsers(dest="bench", required=True, metavar="NAME")
    s = b.add_parser("speed", help="scene flow + motion ms per stage on one core (synthetic frames)")
    s.add_argument("--pairs", type=int, default=100)
    s.add_argument("--width", type=int, default=640)
    s.add_argument("--height", type=int, default=480)
    s.add_argument("--group", default="se3")
    o = b.add_parser("odometry", help="relative pose error of exact/induced vs OpenCV odometry")
    o.add_argument("--source", default=f"tum:{DEFAULT_DATA / '7scenes_redkitchen'}")
    o.add_argument("--frames", type=int, default=None)
    o.add_argument("--groups", default="se3", help="comma-separated groups to run exact and induced for")
    o.add_argument("--no-opencv", action="store_true")
    m = b.add_parser("moving-objects", help="robust vs mean estimators on jointvosf_pairs (people moving)")
    m.add_argument("--data", type=Path, default=DEFAULT_DATA)
    q = b.add_parser("quality", help="ours (4 groups x 2 end modes) vs FFmpeg vid.stab/deshake on 7scenes_redkitchen")
    q.add_argument("--data", type=Path, default=DEFAULT_DATA)
    q.add_argument("--frames", type=int, default=None)
    q.add_argument("--no-baselines", action="store_true", help="skip FFmpeg (no install)")
    ps = b.add_parser("path", help="optimal-path solver ms per frame for every group")
    for q in (s, o, m, q, ps):
        q.add_argument("--json", action="store_true", help="print one JSON object")
    fz = b.add_parser("fuzz", help="the wire decoder against mutated messages (crashes, hangs)")
    fz.add_argument("--n", type=int, default=100_000, help="inputs (default 100000)")
    fz.add_argument("--seed", type=int, default=0)
    fl = b.add_parser("faults", help="SIGKILL services of a running `up` mid-stream: restart, resume, losses")
    fl.add_argument("--cases", default="all", help="comma-separated: a service (flow), repeated (render*3), "
                    "together (router+flow); default all (every service, flow*3, render*3, router+flow)")
    fl.add_argument("--frames", type=int, default=240, help="synthetic frames per case (default 240)")
    fl.add_argument("--fps", type=float, default=30.0)
    fl.add_argument("--size", default="320x240", help="frame size WxH (default 320x240)")
    fl.add_argument("--kill-after", type=int, default=60, help="frames sent before the first kill (default 60)")
    fl.add_argument("--out", default="out/bench-faults", help="folder for each case's recordings and logs")
    fl.add_argument("--json", default=None, metavar="FILE", help="also write the reports as JSON here")
    pl = b.add_parser("pipeline", help="the services under load: latency, throughput, drops, CPU and memory")
    pl.add_argument("--fps", default="30", help="comma-separated capture rates; 'fast' = as fast as possible")
    pl.add_argument("--seconds", type=float, default=120.0, help="measured seconds per rate (default 120)")
    pl.add_argument("--no-record", action="store_true", help="run without the recorder")
    pl.add_argument("--replay", action="store_true",
                    help="capture replays a pre-encoded recording (camera-like cost) instead of rendering live")
    pl.add_argument("--out", default="out/bench-pipeline", help="folder for recordings and logs")
    pl.add_argument("--json", default=None, metavar="FILE", help="also write the reports as JSON here")


def run(args: argparse.Namespace) -> int:
    if args.bench == "pipeline":
        from ..bench import pipeline

        rates = [None if x.strip() == "fast" else float(x) for x in args.fps.split(",")]
        return pipeline.main(rates, args.seconds, args.out, args.json, record=not args.no_record,
                             replay=args.replay)
    if args.bench == "faults":
        from ..bench import faults

        cases = list(faults.CASES) if args.cases == "all" else args.cases.split(",")
        return faults.main(cases, args.out, args.json, frames=args.frames, fps=args.fps, size=args.size,
                           kill_after=args.kill_after)
    if args.bench == "fuzz":
        from ..bench import fuzz

        r = fuzz.run(args.n, args.seed)
        print(fuzz.format_report(r))
        return 1 if r.crashes or r.hangs else 0
    if args.bench == "speed":
        from ..bench import speed

        r = speed.run(args.pairs, args.width, args.height, args.group)
        text = speed.format_report(r)
    elif args.bench == "odometry":
        from ..bench import odometry

        methods = [(g, e) for g in args.groups.split(",") for e in ("exact", "induced")]
        r = odometry.run(args.source, methods, opencv=not args.no_opencv, frames=args.frames)
        text = odometry.format_table(r)
    elif args.bench == "path":
        from ..bench import path_speed

        r = path_speed.run()
        text = path_speed.format_table(r)
    elif args.bench == "quality":
        from ..bench import quality

        r = quality.run(args.data, args.frames, baselines=not args.no_baselines)
        text = quality.format_table(r)
    else:
        from ..bench import moving_objects

        r = moving_objects.run(args.data)
        text = moving_objects.format_table(r)
    print(json.dumps(r, indent=2, default=float) if args.json else text)
    return 0

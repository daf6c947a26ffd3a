"""``quick-stream evaluate``: the paper's protocol (K random L-frame subsequences, all groups) on a TUM folder."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2

from ..core.path.constraints import END_MODES
from ..io.sources import SourceError
from ..quality.evaluate import EvaluateParams, GROUPS, evaluate, markdown
from ..stream import argtypes as at


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="the paper's evaluation protocol on a TUM-layout folder",
                       description=__doc__)
    p.add_argument("folder", type=Path, help="TUM-layout folder (rgb.txt, depth.txt, intrinsics.json)")
    p.add_argument("-k", "--subsequences", type=at.positive_int, default=20, help="subsequences K (default 20)")
    p.add_argument("-l", "--length", type=at.int_in(3), default=30, help="frames per subsequence L, >= 3 (default 30)")
    p.add_argument("--seed", type=at.nonneg_int, default=0)
    p.add_argument("--groups", default=",".join(GROUPS))
    p.add_argument("--end", choices=END_MODES, default="smoothed")
    p.add_argument("--framing", choices=("black", "crop", "auto"), default="auto")
    p.add_argument("--json", type=at.output_file("--json"), metavar="FILE",
                   help="write the full result (per subsequence too) as JSON")
    p.add_argument("--markdown", type=at.output_file("--markdown"), metavar="FILE",
                   help="also write the table as Markdown to FILE")


def run(args: argparse.Namespace) -> int:
    cv2.setNumThreads(1)
    groups = tuple(g.strip() for g in args.groups.split(",") if g.strip())
    bad = [g for g in groups if g not in GROUPS]
    if bad or not groups:
        print(f"quick-stream evaluate: --groups: expected a comma-separated list of {', '.join(GROUPS)}, "
              f"got {args.groups!r}", file=sys.stderr)
        return 2
    p = EvaluateParams(args.subsequences, args.length, args.seed, groups, args.end, args.framing)

    def progress(done: int, total: int) -> None:
        sys.stderr.write(f"\r{done}/{total} subsequence runs")
        sys.stderr.flush()

    try:
        r = evaluate(args.folder, p, progress)
    except (SourceError, ValueError, OSError) as e:
        print(f"\nquick-stream evaluate: {e}", file=sys.stderr)
        return 2
    sys.stderr.write("\n")
    md = markdown(r)
    print(md)
    if args.markdown:
        Path(args.markdown).write_text(md + "\n")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=1, default=float))
    return 0

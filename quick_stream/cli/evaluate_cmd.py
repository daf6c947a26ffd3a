"""``quick-stream evaluate CLIP``: the paper's protocol (K random L-frame subsequences, all groups) on a TUM clip.

CLIP is ``tum:PATH``, as every command reads a clip (a bare TUM-layout folder is taken too).
Prints a Markdown table of the metrics per group; progress on stderr.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

from ..core.path.constraints import END_MODES
from ..io.sources import SourceError
from ..quality.evaluate import EvaluateParams, GROUPS, evaluate, markdown
from ..stream import argtypes as at
from .jsonout import add_json, text_out, write_json
from .progress import Progress

OTHER_KINDS = ("synthetic", "mcap", "depthai")  # clips without the TUM layout the protocol reads


def tum_clip(text: str) -> Path:
    """``tum:PATH`` (or a bare folder) -> the folder; other source kinds and options are refused."""
    kind, sep, rest = text.partition(":")
    if sep and kind.strip().lower() == "tum":
        if "," in rest:
            raise ValueError(f"takes tum:PATH without options (the protocol reads the whole clip), got {text!r}")
        text = rest
    elif sep and kind.strip().lower() in OTHER_KINDS:
        raise ValueError(f"needs a TUM clip with ground truth, tum:PATH, got {text!r}")
    if not text:
        raise ValueError("expected tum:PATH, got an empty path")
    return Path(text)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="the paper's evaluation protocol on a TUM clip",
                       description=at.plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("clip", type=at.checked(tum_clip, "clip"), metavar="CLIP",
                   help="tum:PATH, a TUM-layout folder (rgb.txt, depth.txt, intrinsics.json); the bare PATH works too")
    p.add_argument("-k", "--subsequences", type=at.positive_int, default=20, help="subsequences K (default: 20)")
    p.add_argument("-l", "--length", type=at.int_in(3), default=30,
                   help="frames per subsequence L, >= 3 (default: 30)")
    p.add_argument("--seed", type=at.nonneg_int, default=0, help="seed of the subsequences' starts (default: 0)")
    p.add_argument("--groups", default=",".join(GROUPS), metavar="G[,G...]",
                   help="comma-separated Lie groups to run (default: %(default)s)")
    p.add_argument("--end", choices=END_MODES, default="smoothed",
                   help="end-constraint mode of the path (default: smoothed)")
    p.add_argument("--framing", choices=("black", "crop", "auto"), default="auto",
                   help="framing of the rendered output (default: auto)")
    add_json(p, "the full result (per subsequence too)")
    p.add_argument("--markdown", type=at.output_file("--markdown"), metavar="FILE", default=None,
                   help="also write the table as Markdown to FILE (default: none)")
    at.add_force(p)


def run(args: argparse.Namespace) -> int:
    cv2.setNumThreads(1)
    groups = tuple(g.strip() for g in args.groups.split(",") if g.strip())
    bad = [g for g in groups if g not in GROUPS]
    if bad or not groups:
        print(f"quick-stream evaluate: --groups: expected a comma-separated list of {', '.join(GROUPS)}, "
              f"got {args.groups!r}", file=sys.stderr)
        return 2
    p = EvaluateParams(args.subsequences, args.length, args.seed, groups, args.end, args.framing)
    progress = Progress("quick-stream evaluate")

    try:
        with progress:
            r = evaluate(args.clip, p, lambda done, total: progress(f"{done}/{total} subsequence runs"))
    except (SourceError, ValueError, OSError) as e:
        print(f"quick-stream evaluate: {e}", file=sys.stderr)
        return 2
    md = markdown(r)
    print(md, file=text_out(args))
    if args.markdown:
        Path(args.markdown).write_text(md + "\n")
    if args.json:
        write_json(args.json, r)
    return 0

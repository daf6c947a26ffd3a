"""``quick-stream recover SRC [DST]``: repair an MCAP recording left without a footer (writer killed).

Copies every readable message of SRC into a new, indexed file: DST, by default SRC with
.recovered.mcap, numbered when that exists (rec.recovered-1.mcap, ...). A DST that exists is
refused unless --force. Nothing is left behind when the recording cannot be repaired: the
output appears only once it is complete.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..io.recording import RecordingError, recover
from ..stream import argtypes as at
from .progress import heartbeat


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("recover", help="repair an MCAP recording whose writer was killed",
                       description=at.plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src", type=Path, metavar="SRC", help="the damaged MCAP recording")
    p.add_argument("dst", type=at.output_file("DST"), nargs="?", default=None, metavar="DST",
                   help="output file (default: SRC with .recovered.mcap, numbered if that exists)")
    at.add_force(p)


def default_output(src: Path) -> at.OutputPath:
    """SRC.recovered.mcap, or the first free SRC.recovered-N.mcap."""
    base = src.with_suffix(".recovered.mcap")
    return at.OutputPath(at.numbered_path(base, at.first_free([base])), "output")


def run(args: argparse.Namespace) -> int:
    dst = args.dst or default_output(args.src)
    try:
        if not args.dst:
            at.check_output(dst)  # DST given: checked with the others before run (cli.main)
        with heartbeat("quick-stream recover", f"copying {args.src}"):
            r = recover(args.src, Path(dst), overwrite=args.force)
    except (RecordingError, ValueError, OSError) as e:
        print(f"quick-stream recover: {e}", file=sys.stderr)
        return 2
    state = "intact" if r.complete else f"damaged ({r.stopped_at or 'no footer'})"
    print(f"{r.source}: {state}; wrote {r.messages} messages on {r.channels} channels to {r.output}")
    for topic, n in sorted(r.topics.items()):
        print(f"  {topic}: {n}")
    return 0

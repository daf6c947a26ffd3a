"""``quick-stream recover SRC [DST]``: repair an MCAP recording left without a footer (writer killed)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..io.recording import RecordingError, recover
from ..stream.argtypes import OutputPath, check_output


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("recover", help="repair an MCAP recording whose writer was killed", description=__doc__)
    p.add_argument("src", type=Path)
    p.add_argument("dst", type=Path, nargs="?", help="output file (default SRC with .recovered.mcap)")


def run(args: argparse.Namespace) -> int:
    dst = args.dst or args.src.with_suffix(".recovered.mcap")
    try:
        check_output(OutputPath(str(dst), "DST" if args.dst else "output"))
        r = recover(args.src, dst)
    except (RecordingError, ValueError, OSError) as e:
        print(f"quick-stream recover: {e}", file=sys.stderr)
        return 2
    state = "intact" if r.complete else f"damaged ({r.stopped_at or 'no footer'})"
    print(f"{r.source}: {state}; wrote {r.messages} messages on {r.channels} channels to {r.output}")
    for topic, n in sorted(r.topics.items()):
        print(f"  {topic}: {n}")
    return 0

"""``quick-stream recording-stats FILE...``: per-channel byte rates of MCAP recordings.

For each channel: messages, MB of message data, share, MB per second of log time, kB per
message and per recorded frame; then all message data and the file itself. ``--fps F``
adds each channel's rate at F frames per second (per stream), from its size per frame:
what compares recordings whose capture shed a different number of frames
(docs/recording.md). ``--json FILE`` (``-``: standard output) writes the numbers as JSON
(a list, one object per file).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..io.recording import RecordingError
from ..io.recording_stats import recording_stats, report
from ..stream import argtypes as at
from .jsonout import add_json, text_out, write_json
from .progress import heartbeat


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("recording-stats", help="per-channel byte rates of MCAP recordings",
                       description=at.plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recordings", type=Path, nargs="+", metavar="FILE", help="MCAP recording(s)")
    p.add_argument("--fps", type=at.positive_float, default=None,
                   help="also give each channel's rate at this many frames per second per stream (default: none)")
    add_json(p, "the numbers (a list, one object per file)")
    at.add_force(p)


def run(args: argparse.Namespace) -> int:
    stats, code = [], 0
    for path in args.recordings:
        try:
            with heartbeat("quick-stream recording-stats", f"reading {path}"):
                stats.append(recording_stats(path))
        except RecordingError as e:
            print(f"quick-stream recording-stats: {e}", file=sys.stderr)
            code = 2
    try:
        if args.json:
            write_json(args.json, [s.as_dict(args.fps) for s in stats], default=None)
        if stats:
            print("\n\n".join(report(s, args.fps) for s in stats), file=text_out(args))
    except BrokenPipeError:  # the reader (head, less) stopped reading
        sys.stderr.close()
    return code

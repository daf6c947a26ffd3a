"""``quick-stream recording-stats FILE...``: per-channel byte rates of MCAP recordings.

For each channel: messages, MB of message data, share, MB per second of log time, kB per
message and per recorded frame; then all message data and the file itself. ``--fps F``
adds each channel's rate at F frames per second (per stream), from its size per frame:
what compares recordings whose capture shed a different number of frames
(docs/recording.md). ``--json`` prints the numbers as JSON instead.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..io.recording import RecordingError
from ..io.recording_stats import recording_stats, report
from ..stream.argtypes import positive_float


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("recording-stats", help="per-channel byte rates of MCAP recordings", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recordings", type=Path, nargs="+", metavar="FILE", help="MCAP recording(s)")
    p.add_argument("--fps", type=positive_float, default=None,
                   help="also give each channel's rate at this many frames per second per stream")
    p.add_argument("--json", action="store_true", help="print JSON (one object per file, in a list)")


def run(args: argparse.Namespace) -> int:
    out, code = [], 0
    for path in args.recordings:
        try:
            s = recording_stats(path)
        except RecordingError as e:
            print(f"quick-stream recording-stats: {e}", file=sys.stderr)
            code = 2
            continue
        out.append(s.as_dict(args.fps) if args.json else report(s, args.fps))
    try:
        if args.json:
            print(json.dumps(out, indent=1))
        elif out:
            print("\n\n".join(out))
    except BrokenPipeError:  # the reader (head, less) stopped reading
        sys.stderr.close()
    return code

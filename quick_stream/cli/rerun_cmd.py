"""``quick-stream rerun STAGE RECORDING``: re-run one stage from a recording's logged inputs.

Runs the ``flow``, ``motion`` or ``render`` stage offline on the inputs the
recorder logged (``frame``; ``flow``; ``frame`` + ``correction``) with the settings
the recording was made with (its settings record; --settings and the flags change
them, e.g. to see what other settings would have made) and compares what it makes
with the logged outputs (see :mod:`quick_stream.quality.rerun`). Prints a report; exit
code 0 when every logged output is reproduced identically, 1 when any differs,
2 when the stage cannot be re-run (missing file, no logged inputs, bad flags). Progress
(the time it has been working) goes to stderr.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

from ..io.recording import RecordingError
from ..io.settings_file import recording_settings
from ..quality.rerun import RerunError, RerunResult, STAGES, rerun_stage
from ..stream.argtypes import plain_text, stream_id
from ..io.stabilizer_flags import add_stabilizer_args, stabilizer_params
from .progress import heartbeat

SHOWN = 10  # mismatches listed in the report


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rerun", help="re-run one stage from a recording and compare with its logged outputs",
                       description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stage", choices=STAGES, help="the stage to re-run")
    p.add_argument("recording", type=Path, metavar="FILE", help="MCAP recording (the recorder service's)")
    p.add_argument("--stream", type=stream_id, default=None, help="stream id (default: the recording's only stream)")
    add_stabilizer_args(p)


def report(r: RerunResult, shown: int = SHOWN) -> str:
    """The human-readable report of one rerun."""
    lines = [f"rerun {r.stage} of stream {r.stream!r} from {r.path}"]
    lines += [f"  input  {topic}: {n} messages" for topic, n in r.inputs.items()]
    for t in r.outputs:
        extra = f", {t.extra} never logged" if t.extra else ""
        lines.append(f"  output {t.topic}: {t.logged} logged, {t.identical} reproduced identically{extra}")
    if r.mismatches:
        lines.append(f"  mismatches (first {min(shown, len(r.mismatches))} of {len(r.mismatches)}):")
        lines += [f"    {m}" for m in r.mismatches[:shown]]
    lines += [f"  note: {n}" for n in r.notes]
    if r.ok:
        lines.append(f"OK: all {r.logged} logged outputs reproduced identically")
    else:
        lines.append(f"DIFFERENT: {r.logged - r.identical} of {r.logged} logged outputs not reproduced identically"
                     + (f", {sum(t.extra for t in r.outputs)} outputs never logged" if any(t.extra for t in r.outputs)
                        else ""))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    cv2.setNumThreads(1)  # as the services run OpenCV: bit-exact results
    try:
        params = stabilizer_params(args, recorded=recording_settings(args.recording)
                                   if args.recording.is_file() else None)
        with heartbeat("quick-stream rerun", f"re-running the {args.stage} stage on {args.recording}"):
            result = rerun_stage(args.recording, args.stage, args.stream, params)
    except (RerunError, RecordingError, ValueError) as e:
        print(f"quick-stream rerun: {e}", file=sys.stderr)
        return 2
    print(report(result))
    return 0 if result.ok else 1

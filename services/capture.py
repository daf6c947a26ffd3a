"""``capture``: a frame source onto ``quick/@v1/<stream>/frame``.

Any source spec (``synthetic[:...]``, ``tum:PATH``, ``mcap:FILE``, ``depthai[:...]``) is read,
paced at its own timestamps (``--pace realtime``, ``--speed`` to scale; frames the pipeline
cannot take are shed) or sent as fast as the pipeline takes them (``--pace fast``), encoded as
``frame`` messages (JPEG or raw colour, raw or zstd depth at the source's own depth scale) and
published. A frame the source cannot deliver is logged with its reason and counted; the stream
goes on. A recording (``mcap:``) is replayed exactly: each frame message is sent as recorded
(only re-addressed to ``--stream`` and re-stamped), unless ``--reencode``. At the end an ``end``
message follows the last frame. ``--wait-for`` holds the first frame until the named services
are up, so a run loses nothing at start-up. All of it is :class:`quick_stream.stream.capture.Capture`.
"""
from __future__ import annotations

import argparse
import sys

import zenoh

from quick_stream.io.sources import SourceError, open_source
from quick_stream.io.sources.base import LiveSource, ReplaySource, open_live
from quick_stream.io.sources.oak_device import print_devices
from quick_stream.stream import argtypes as at
from quick_stream.stream.capture import Capture, CaptureOptions, log
from quick_stream.stream.process import service_main, service_parser
from quick_stream.stream.runtime import ServiceRuntime


def build_parser() -> argparse.ArgumentParser:
    D = CaptureOptions  # the defaults
    p = service_parser("capture", __doc__)
    p.add_argument("--source", default="synthetic",
                   help="synthetic[:k=v,...] (default), tum:PATH, mcap:FILE or depthai[:DEVICE_ID][,width=W,height=H,fps=F]")
    p.add_argument("--list-devices", action="store_true", help="list the OAK (depthai) devices visible and exit")
    p.add_argument("--frames", type=at.positive_int, default=None, help="send at most this many frames (default: all the source has)")
    p.add_argument("--pace", choices=("realtime", "fast"), default=D.pace,
                   help="realtime: at the frames' own timestamps (default); fast: as fast as the pipeline "
                        "takes them (at most --window frames ahead of the last stabilized one)")
    p.add_argument("--window", type=at.nonneg_int, default=D.window,
                   help=f"fast pace: frames in flight before waiting for stabilized output (default {D.window}; "
                        "a third of it for the motion stage; 0: no limit)")
    p.add_argument("--shed", choices=("on", "off"), default=D.shed,
                   help="realtime pace: frames offered faster than the pipeline takes them are shed (skipped "
                        "before encoding, evenly spaced, counted in 'shed'; default on; docs/reliability.md)")
    p.add_argument("--speed", type=at.positive_float, default=D.speed, help="realtime pacing speed factor (default 1)")
    p.add_argument("--fps", type=at.positive_float, default=None,
                   help="override the pacing rate (frames/s; realtime only; default: the source's rate)")
    p.add_argument("--color", choices=("jpeg", "raw"), default=D.color, help=f"colour encoding (default {D.color})")
    p.add_argument("--quality", type=at.quality, default=D.quality, help=f"JPEG quality, 1-100 (default {D.quality})")
    p.add_argument("--depth", choices=("raw", "zstd"), default=D.depth, help=f"depth encoding (default {D.depth})")
    p.add_argument("--reencode", action="store_true",
                   help="mcap sources: re-encode frames with --color/--depth instead of sending the recorded bytes")
    p.add_argument("--history", type=at.int_in(0), default=150,
                   help="frames kept for a restarted flow or render service to take over from (default 150, "
                        "5 s at 30 fps, what render holds at most by default; at least 150 are kept for receivers to recover "
                        "what their link dropped)")
    p.add_argument("--wait-for", type=at.service_names, default="", metavar="S1,S2",
                   help="services (of this stream) to wait for before the first frame, e.g. flow,motion,render (default: none)")
    p.add_argument("--wait-timeout", type=at.nonneg_float, default=D.wait_timeout,
                   help=f"seconds to wait for them (default {D.wait_timeout:g})")
    p.add_argument("--start-wait", type=at.nonneg_float, default=D.start_wait,
                   help="with --wait-for: seconds to wait until the receivers of frames among them (flow, render, "
                        f"recorder) have the first frame before sending the next (default {D.start_wait:g})")
    p.add_argument("--end-wait", type=at.nonneg_float, default=D.end_wait,
                   help="at the end, seconds to wait until every consumer has received the last frame before "
                        "sending the end marker, and again until they have the end marker before closing "
                        f"(default {D.end_wait:g}; stopped by a signal: 2 s at most each, a second signal ends them)")
    return p


def run(args: argparse.Namespace, conf: zenoh.Config) -> int:
    try:
        source = open_source(args.source)
    except SourceError as e:
        log.error("%s", e)
        return 2
    if (code := open_live(source, args.source)) is not None:
        return code
    with ServiceRuntime("capture", args.stream, conf) as rt:
        if isinstance(source, LiveSource):
            source.stop = rt.stop  # reconnection retries end when the service is asked to stop
        pub = rt.publisher("frame", cache=args.history)  # lossless: lost only where counted (inboxes)
        rt.ready()
        capture = Capture(rt, pub, CaptureOptions.from_flags(args), depth_scale=float(source.depth_scale))
        if (code := capture.start()) is not None:
            return code
        # an exact replay sends the recorded bytes: their pixels are decoded (and checked) by the receivers
        exact = isinstance(source, ReplaySource) and not args.reencode
        items = source.iter_with_messages(pixels=False) if exact else ((f, None) for f in source)
        reason = capture.send_all(items)
        capture.end(reason)
    return 1 if reason.startswith("source failed") else 0


def main(argv: list[str] | None = None) -> int:
    return service_main("capture", build_parser(), run, argv, early=lambda a: print_devices() if a.list_devices else None)


if __name__ == "__main__":
    sys.exit(main())

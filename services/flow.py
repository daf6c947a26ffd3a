"""``flow``: scene flow of consecutive frames, ``frame`` -> ``flow``.

Reads frames through a drop-oldest inbox (``--queue``, default 30: if this stage
falls that far behind, the oldest frames are dropped and counted, and the next
flow spans the gap), runs :class:`quick_stream.core.stages.FlowDriver` and publishes
each pair's ``flow`` message (lossless: the motion stage needs every pair it can
get; a receiver whose link dropped flows fetches them back from the publisher's
cache, and no subscriber can make the put wait). Undecodable or out-of-order frames
are logged and counted; a stream whose numbering restarts lower is followed once a
run of frames confirms it (an empty flow naming the renumbering: the path restarts
there; ``renumberings``). The ``end`` marker is forwarded once the last flow is out.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time

import zenoh

from quick_stream.core.settings import settings_digest
from quick_stream.core.stages import FlowDriver
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.meters import RateMeter
from quick_stream.stream.process import add_queue_args, service_main, service_parser
from quick_stream.stream.runtime import Input, ServiceRuntime
from quick_stream.io.stabilizer_flags import add_stabilizer_args, stabilizer_params
from quick_stream.stream.wire import Decoded, encode_end, encode_flow

log = logging.getLogger("flow")


def build_parser() -> argparse.ArgumentParser:
    p = service_parser("flow", __doc__)
    add_stabilizer_args(p)
    add_queue_args(p, queue=30, queue_help="frames held before the oldest is dropped (default 30, 1 s at 30 fps)",
                   history=150, history_help="flows kept for a restarted motion service to take over from and for "
                   "receivers to recover what their link dropped (default 150; at least 150 are kept)")
    p.add_argument("--catch-up", type=at.positive_int, default=150,
                   help="frames held while a restarted flow works through the frames' history (default 150, "
                        "the capture's history)")
    return p


def run(args: argparse.Namespace, conf: zenoh.Config) -> int:
    params = stabilizer_params(args)
    driver = FlowDriver(params.flow, params.continuity, log=log)
    with ServiceRuntime("flow", args.stream, conf, settings=settings_digest(params)) as rt:
        resume_after = rt.stream_cursor("flow")  # not None: a restarted flow; take over after the last flow out
        if resume_after is not None:
            log.warning("stream %s under way (flows out up to frame %d): taking over from the frames' history",
                        args.stream, resume_after)
        taking_over = resume_after is not None
        inbox = rt.inbox(keys.key(args.stream, "frame"), args.queue, history=taking_over, publisher="capture",
                         skip_through=resume_after, catch_up=args.catch_up if taking_over else 0)
        pub = rt.publisher("flow", lossless=True, cache=args.history)
        rt.serve_cursor()
        rt.ready()
        meter = RateMeter()

        def on_frame(msg: Decoded) -> None:
            t0 = time.perf_counter()
            if (flow := driver.push(msg.obj, msg.extra.get("pub_ns"))) is not None:
                pub.put(encode_flow(flow, args.stream))
                meter.add((time.perf_counter() - t0) * 1e3)

        def on_end(msg: Decoded) -> None:
            pub.put(encode_end(msg.obj, args.stream))
            log.info("end of stream after frame %d", msg.obj.seq)
            driver.restart()  # a new stream may follow

        # taken over: frames whose flow was out before the restart, skipped by the inbox (a replay of the
        # capture's history; a frame published after those queued is live, a renumbered stream)
        # a JPEG frame decodes to its grey only: the scene flow reads nothing else (~60 % of the colour decode)
        rt.serve([Input(inbox, {"frame": on_frame, "end": on_end}, color="luma")],
                 lambda: {"taken_over": inbox.skipped, **driver.stats(), **meter.take("flow")})
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("flow", build_parser(), run, argv, check=stabilizer_params)


if __name__ == "__main__":
    sys.exit(main())

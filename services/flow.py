"""``flow``: scene flow of consecutive frames, ``frame`` -> ``flow``.

Takes the pipeline's one shedding decision before decoding a frame
(:class:`quick_stream.core.admission.FlowAdmission`, fed by :class:`quick_stream.stream.gate.FrameGate`):
a frame that arrives beyond the pace at which flow, the motion stage and the stabilized output keep
up (while no capture of ours is up: it paces or sheds itself), one taken from the inbox with more than ``--queue`` frames (default 30) waiting behind it, or one
the inbox (twice ``--queue``) drops for room is shed (``shed``; the next flow spans the gap) and
named in the next flow's ``shed`` (or the ``end``'s), so that motion and render let it go too. It runs
:class:`quick_stream.core.flow_stage.FlowDriver` and publishes each pair's ``flow`` message (lossless: the motion stage needs every pair it can
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

from quick_stream.core.admission import MAX_NAMED, FlowAdmission, split_named
from quick_stream.core.settings import settings_digest
from quick_stream.core.flow_stage import FlowDriver
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.gate import FrameGate
from quick_stream.stream.meters import RateMeter
from quick_stream.stream.process import add_queue_args, service_main, service_parser
from quick_stream.stream.runtime import Input, ServiceRuntime
from quick_stream.io.stabilizer_flags import add_stabilizer_args, stabilizer_params
from quick_stream.stream.wire import Decoded, EndOfStream, encode_end, encode_flow

log = logging.getLogger("flow")


def build_parser() -> argparse.ArgumentParser:
    p = service_parser("flow", __doc__)
    add_stabilizer_args(p)
    add_queue_args(p, queue=30, queue_help="frames waiting before the oldest is shed (default 30, 1 s at 30 fps)",
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
        resume_after = rt.take_over("flow", "frames", log)  # not None: a restarted flow
        taking_over = resume_after is not None
        # each frame's depth is decompressed once: by the check on arrival, kept for its decode (24 MB: 40
        # frames waiting at 640x480; beyond them the decode decompresses it again)
        inbox = rt.inbox(keys.key(args.stream, "frame"), 2 * args.queue, history=taking_over, publisher="capture",
                         skip_through=resume_after, catch_up=args.catch_up if taking_over else 0, keep_depth_mb=24)
        pub = rt.publisher("flow", cache=args.history)
        gate = FrameGate(rt, args.stream, inbox, FlowAdmission(args.queue, max_jump=params.continuity.max_jump))
        rt.serve_cursor()
        rt.ready()
        meter = RateMeter()
        shed: list[int] = []  # shed and not yet named: each named in the next flow that ends after it

        def on_frame(msg: Decoded) -> None:
            t0 = time.perf_counter()
            shed.extend(gate.take_shed())
            del shed[:-MAX_NAMED]  # what one message names at most (no flow for that long: the oldest unnamed)
            flows = driver.push(msg.obj, msg.pub_ns, shed)
            if driver.taken is not None:
                gate.taken(driver.taken)
            publish(flows)
            if flows:
                meter.add((time.perf_counter() - t0) * 1e3)

        def publish(flows: list) -> None:
            for flow in flows:  # each names the frames shed before its end; those shed on arrival after it wait
                named, shed[:], dropped = split_named(shed, flow.seq, flow.seq_next)
                if dropped:
                    log.warning("%d frames shed after frame %d go unnamed: the numbering restarts at %d (render "
                                "flags them)", dropped, flow.seq, flow.seq_next)
                pub.put(encode_flow(flow, args.stream, named))

        def on_end(msg: Decoded) -> None:
            end = msg.obj
            shed.extend(gate.take_shed())
            del shed[:-MAX_NAMED]
            publish(driver.finish())  # frames being reached over: the flow held for them, before the end
            pub.put(encode_end(EndOfStream(end.seq, end.reason, tuple(s for s in shed if s <= end.seq)), args.stream))
            log.info("end of stream after frame %d", end.seq)
            shed.clear()
            gate.restart()
            driver.restart()  # a new stream may follow

        # taken over: frames whose flow was out before the restart, skipped by the inbox (a replay of the
        # capture's history; a frame published after those queued is live, a renumbered stream)
        # a JPEG frame decodes to its grey only: the scene flow reads nothing else (~60 % of the colour decode)
        rt.serve([Input(inbox, {"frame": on_frame, "end": on_end}, color="luma", admit=gate.admit)],
                 lambda: {"taken_over": inbox.skipped, **driver.stats(), **gate.stats(), **meter.take("flow")})
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("flow", build_parser(), run, argv, check=stabilizer_params)


if __name__ == "__main__":
    sys.exit(main())

"""``motion``: camera motion, keyframes and the optimal path, ``flow`` -> ``motion`` + ``correction``.

Runs :class:`quick_stream.core.stages.MotionDriver` on every flow (lossless inbox and
publishers: a lost correction would leave frames unrendered). Publishes each
pair's ``motion`` and, one segment late, the ``correction`` of every frame of a
closed segment, tagged with its planner release (``Tag``) so the renderer
frames each release as a whole. A flow that skips frames (upstream drops or a
restarted flow service) becomes an invalid motion: the path restarts there and
those frames are flagged. The frames a flow names as shed by the flow stage go out on the
correction of the frame it ends at (``shed``), so that render lets them go. The flow stage's break to a new numbering (a stream renumbered
lower) restarts the path at its first frame (``renumberings``); the old numbering's
corrections and the new one's go out in separate releases. On ``end`` the last segment is
closed and released, then ``end`` is forwarded on ``correction``.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time

import zenoh

from quick_stream.core.release_tags import Tag
from quick_stream.core.path.planner import Correction
from quick_stream.core.settings import settings_digest
from quick_stream.core.stages import MotionDriver
from quick_stream.stream import keys
from quick_stream.stream.meters import RateMeter
from quick_stream.stream.process import add_queue_args, service_main, service_parser
from quick_stream.stream.runtime import Input, ServiceRuntime
from quick_stream.io.stabilizer_flags import add_stabilizer_args, stabilizer_params
from quick_stream.stream.wire import Decoded, encode_correction, encode_end, encode_motion

KEEP_SEGMENTS = 64  # segment accounts kept (the stats count them all): a live stream is endless

log = logging.getLogger("motion")


def build_parser() -> argparse.ArgumentParser:
    p = service_parser("motion", __doc__)
    add_queue_args(p, queue=100_000, queue_help="flow messages held (lossless; default 100000)",
                   history=300, history_help="corrections kept for a restarted render service to take over from "
                   "(default 300; at least 150 are kept for receivers to recover what their link dropped)")
    add_stabilizer_args(p)
    return p


def run(args: argparse.Namespace, conf: zenoh.Config) -> int:
    params = stabilizer_params(args)
    with ServiceRuntime("motion", args.stream, conf, settings=settings_digest(params)) as rt:
        resume_after = rt.take_over("correction", "flows", log)  # not None: a restarted motion (the path restarts)
        driver = MotionDriver(params.motion, params.planner, params.warp, resume_after=resume_after, log=log,
                              keep_segments=KEEP_SEGMENTS)
        inbox = rt.inbox(keys.key(args.stream, "flow"), args.queue, history=resume_after is not None,
                         publisher="flow", skip_through=resume_after)
        motion_pub = rt.publisher("motion")
        corr_pub = rt.publisher("correction", cache=args.history)
        rt.serve_cursor()
        rt.ready()
        meter = RateMeter()

        def release(corrections: list[tuple[Correction, Tag]]) -> None:
            for c, tag in corrections:
                corr_pub.put(encode_correction(c, args.stream, tag=tag))

        def on_flow(msg: Decoded) -> None:
            t0 = time.perf_counter()
            out = driver.push(msg.obj, msg.shed)  # frames flow shed: named on the correction
            if driver.resume_after is None:
                inbox.skip_through = None  # a new numbering: the predecessor's cursor says nothing of it
            if out is not None:
                for m in out[0]:
                    motion_pub.put(encode_motion(m, args.stream))
                release(out[1])
                meter.add((time.perf_counter() - t0) * 1e3)

        def on_end(msg: Decoded) -> None:
            release(driver.finish())
            corr_pub.put(encode_end(msg.obj, args.stream))
            driver.restart()  # a new stream may follow

        rt.serve([Input(inbox, {"flow": on_flow, "end": on_end}, label=lambda m: f"flow {m.seq}->{m.obj.seq_next}")],
                 lambda: {**driver.stats(), **meter.take("motion")})
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("motion", build_parser(), run, argv, check=stabilizer_params)


if __name__ == "__main__":
    sys.exit(main())

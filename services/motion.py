"""``motion``: camera motion, keyframes and the optimal path, ``flow`` -> ``motion`` + ``correction``.

Runs :class:`quick_stream.core.stages.MotionStage` on every flow (lossless inbox and
publishers: a lost correction would leave frames unrendered). Publishes each
pair's ``motion`` and, one segment late, the ``correction`` of every frame of a
closed segment, tagged with its planner release (``batch``) so the renderer
frames each release as a whole. A flow that skips frames (upstream drops or a
restarted flow service) becomes an invalid motion: the path restarts there and
those frames are flagged. The flow stage's break to a new numbering (a stream renumbered
lower) restarts the path at its first frame (``renumberings``); the old numbering's
corrections and the new one's go out in separate releases. On ``end`` the last segment is
closed and released, then ``end`` is forwarded on ``correction``.
"""
from __future__ import annotations

import logging
import sys
import time

import zenoh

from quick_stream.core.path.planner import Correction
from quick_stream.core.stages import MotionStage
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.meters import RateMeter
from quick_stream.stream.runtime import ServiceRuntime, TimedPublisher, service_main, service_parser
from quick_stream.stream.stabilizer_flags import add_stabilizer_args, stabilizer_params
from quick_stream.stream.wire import encode_correction, encode_end, encode_motion

log = logging.getLogger("motion")


def build_parser():
    p = service_parser("motion", __doc__)
    p.add_argument("--queue", type=at.positive_int, default=100_000,
                   help="flow messages held (lossless; default 100000)")
    p.add_argument("--history", type=at.int_in(0), default=300,
                   help="corrections kept for a restarted render service to take over from (default 300; at least 150 "
                        "are kept for receivers to recover what their link dropped)")
    add_stabilizer_args(p)
    return p


class Releaser:
    """Publishes correction batches with their release id."""

    def __init__(self, pub: TimedPublisher, stream: str) -> None:
        self.pub, self.stream, self.release, self.sent = pub, stream, 0, 0

    def __call__(self, batches: list[list[Correction]]) -> None:
        for b in batches:
            for i, c in enumerate(b):
                self.pub.put(encode_correction(c, self.stream, batch=(self.release, i, len(b))))
                self.sent += 1
            self.release += 1


def run(args, conf: zenoh.Config) -> int:
    params = stabilizer_params(args)
    stage = MotionStage(params.motion, params.planner, params.warp)
    with ServiceRuntime("motion", args.stream, conf) as rt:
        resume_after = rt.stream_cursor("correction")  # not None: a restarted motion; take over after it
        if resume_after is not None:
            log.warning("stream %s under way (corrections out up to frame %d): the path restarts after it, "
                        "from the flows' history", args.stream, resume_after)
        inbox = rt.inbox(keys.key(args.stream, "flow"), args.queue, history=resume_after is not None,
                         publisher="flow", skip_through=resume_after)
        motion_pub = rt.publisher("motion", lossless=True)
        release = Releaser(rt.publisher("correction", lossless=True, cache=args.history), args.stream)
        rt.serve_cursor()
        rt.ready()
        meter = RateMeter()
        errors = {"decode_errors": 0, "refused_flows": 0, "invalid_motions": 0, "internal_errors": 0,
                  "taken_over": 0}
        done = {"renumberings": 0}  # of streams already ended

        def stats():
            return {"state": "running", **errors, "gaps": stage.gaps, "segments": len(stage.planner.segments),
                    "corrections": release.sent, "renumberings": done["renumberings"] + stage.renumberings,
                    **meter.take("motion")}

        def take(flow) -> None:
            nonlocal resume_after
            if resume_after is not None and flow.seq <= resume_after:  # its frames were corrected before the restart
                errors["taken_over"] += 1
                return
            t0 = time.perf_counter()
            try:
                motions, batches = stage.push(flow)
            except ValueError as e:
                errors["refused_flows"] += 1
                log.error("flow %d->%d refused: %s", flow.seq, flow.seq_next, e)
                return
            if flow.seq_next <= flow.seq and resume_after is not None:
                # a new numbering: the predecessor's cursor says nothing of it
                resume_after = inbox.skip_through = None
            for m in motions:
                if not m.valid:
                    errors["invalid_motions"] += 1
                    log.warning("motion %d->%d invalid: %s", m.seq, m.seq_next, m.reason)
                motion_pub.put(encode_motion(m, args.stream))
            release(batches)
            meter.add((time.perf_counter() - t0) * 1e3)

        for msg in rt.receive(inbox, "flow", errors, stats):
            if msg.type == "end":
                release(stage.finish())
                release.pub.put(encode_end(msg.obj, args.stream))
                log.info("end of stream: %d segments, %d corrections", len(stage.planner.segments), release.sent)
                done["renumberings"] += stage.renumberings
                stage = MotionStage(params.motion, params.planner, params.warp)  # a new stream may follow
                resume_after = inbox.skip_through = None
                continue
            with rt.contained(f"flow {msg.seq}->{msg.obj.seq_next}", errors):
                take(msg.obj)
        rt.publish_stats({**stats(), "state": "stopped"})
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("motion", build_parser(), run, argv, check=stabilizer_params)


if __name__ == "__main__":
    sys.exit(main())

"""``motion``: camera motion, keyframes and the optimal path, ``flow`` -> ``motion`` + ``correction``.

Runs :class:`quick_stream.stages.MotionStage` on every flow (lossless inbox and
publishers: a lost correction would leave frames unrendered). Publishes each
pair's ``motion`` and, one segment late, the ``correction`` of every frame of a
closed segment, tagged with its planner release (``batch``) so the renderer
frames each release as a whole. A flow that skips frames (upstream drops or a
restarted flow service) becomes an invalid motion: the path restarts there and
those frames are flagged. On ``end`` the last segment is closed and released,
then ``end`` is forwarded on ``correction``.
"""
from __future__ import annotations

import logging
import sys
import time

import zenoh

from quick_stream import keys
from quick_stream.cli.settings import add_stabilizer_args, stabilizer_params
from quick_stream.path.planner import Correction
from quick_stream.runtime import RateMeter, ServiceRuntime, service_main, service_parser
from quick_stream.stages import MotionStage
from quick_stream.wire import encode_correction, encode_end, encode_motion

log = logging.getLogger("motion")


def build_parser():
    p = service_parser("motion", __doc__)
    p.add_argument("--queue", type=int, default=100_000, help="flow messages held (lossless; default 100000)")
    add_stabilizer_args(p)
    return p


class Releaser:
    """Publishes correction batches with their release id."""

    def __init__(self, pub: zenoh.Publisher, stream: str) -> None:
        self.pub, self.stream, self.release, self.sent = pub, stream, 0, 0

    def __call__(self, batches: list[list[Correction]]) -> None:
        for b in batches:
            for i, c in enumerate(b):
                self.pub.put(encode_correction(c, self.stream, batch=(self.release, i, len(b))))
                self.sent += 1
            self.release += 1


def run(args, conf: zenoh.Config) -> int:
    params = stabilizer_params(args)
    stage = MotionStage(params.motion, params.planner)
    with ServiceRuntime("motion", args.stream, conf) as rt:
        inbox = rt.inbox(keys.key(args.stream, "flow"), args.queue)
        motion_pub = rt.publisher("motion", lossless=True)
        release = Releaser(rt.publisher("correction", lossless=True), args.stream)
        rt.ready()
        meter = RateMeter()
        errors = {"decode_errors": 0, "refused_flows": 0, "invalid_motions": 0, "internal_errors": 0}

        def stats():
            return {"state": "running", **errors, "gaps": stage.gaps, "segments": len(stage.planner.segments),
                    "corrections": release.sent, **meter.take("motion")}

        def take(flow) -> None:
            t0 = time.perf_counter()
            try:
                motions, batches = stage.push(flow)
            except ValueError as e:
                errors["refused_flows"] += 1
                log.error("flow %d->%d refused: %s", flow.seq, flow.seq_next, e)
                return
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
                stage = MotionStage(params.motion, params.planner)  # a new stream may follow
                continue
            with rt.contained(f"flow {msg.seq}->{msg.obj.seq_next}", errors):
                take(msg.obj)
        rt.publish_stats({**stats(), "state": "stopped"})
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("motion", build_parser(), run, argv, check=stabilizer_params)


if __name__ == "__main__":
    sys.exit(main())

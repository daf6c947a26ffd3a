"""``render``: stabilized frames, ``frame`` + ``correction`` -> ``stabilized`` (+ MP4/PNG).

Frames are decoded as they arrive and held until their correction arrives, one segment later; corrections are collected per planner
release and each release is warped, framed and rendered as a whole by
:class:`quick_stream.core.render_stage.RenderStage`. A release is rendered once all its
frames are here, or a newer frame has arrived (a missing one is lost: counted),
or after ``--frame-wait`` seconds. Frames that no correction will reach (skipped
upstream) are rendered uncorrected and flagged. A stream whose numbering restarts lower is
followed once a run of frames confirms it (``renumberings``): the old numbering's frames
still held are rendered with the old numbering's corrections, what none reaches uncorrected
and flagged, then the new numbering's. ``--max-frames`` bounds what is
held: beyond it the oldest frame is dropped and counted. Each stabilized frame
is published as soon as it is rendered (the batch's warps and zoom track are
solved first), with its latency stamps (docs/wire-format.md); ``--output``/``--png``
also write it to disk from a worker thread. On ``end`` (on ``correction``) everything left is
rendered, the file closed, and ``end`` forwarded on ``stabilized``.
"""
from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable

import zenoh

from quick_stream.core.release import ReleaseGroups
from quick_stream.core.render_stage import RenderStage, StabilizedFrame
from quick_stream.io.sinks import BackgroundSink, VideoSink
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.meters import Percentiles, RateMeter
from quick_stream.stream.runtime import ServiceRuntime, service_main, service_parser
from quick_stream.stream.stabilizer_flags import add_stabilizer_args, stabilizer_params
from quick_stream.stream.wire import StabilizedImage, encode_end, encode_stabilized

log = logging.getLogger("render")


def build_parser():
    p = service_parser("render", __doc__)
    p.add_argument("--output", type=at.output_file("--output", at.VIDEO_SUFFIXES, "video"), default="",
                   help="also write an MP4 here")
    p.add_argument("--png", type=at.output_dir("--png"), default="", metavar="DIR",
                   help="also write every frame as PNG here")
    p.add_argument("--fps", type=at.positive_float, default=30.0, help="MP4 frame rate (default 30)")
    p.add_argument("--color", choices=("jpeg", "raw"), default="jpeg", help="published image encoding")
    p.add_argument("--quality", type=at.quality, default=90, help="JPEG quality, 1-100 (default 90)")
    p.add_argument("--max-frames", type=at.positive_int, default=150,
                   help="frames held for corrections (default 150, 5 s at 30 fps)")
    p.add_argument("--frame-wait", type=at.nonneg_float, default=1.0,
                   help="seconds a complete release waits for missing frames (default 1)")
    add_stabilizer_args(p)
    return p


def run(args, conf: zenoh.Config) -> int:
    params = stabilizer_params(args)
    stage = RenderStage(params.warp, params.framing, max_frames=args.max_frames)
    with ServiceRuntime("render", args.stream, conf) as rt, \
            BackgroundSink(VideoSink(args.output, args.png, args.fps)) as sink:
        resume_after = rt.stream_cursor("stabilized")  # not None: a restarted render; take over after it
        if resume_after is not None:
            log.warning("stream %s under way (stabilized out up to frame %d): taking over from the frames' and "
                        "corrections' history", args.stream, resume_after)
        taking_over = resume_after is not None
        frames_in = rt.inbox(keys.key(args.stream, "frame"), 256, history=taking_over, publisher="capture")
        corr_in = rt.inbox(keys.key(args.stream, "correction"), 100_000, history=taking_over, publisher="motion")
        pub = rt.publisher("stabilized")
        releases = ReleaseGroups()
        pub_ns: dict[tuple[int, int], int] = {}  # (numbering, seq) -> when the capture published the frame
        rt.serve_cursor()
        rt.ready()
        meter = RateMeter()
        errors = {"decode_errors": 0, "refused_frames": 0, "internal_errors": 0, "taken_over": 0}
        flagged = 0
        ended_streams = 0
        done = {"dropped": 0, "missing": 0, "orphans": 0, "bad": 0,  # counts of streams already ended
                "filled": 0, "fill_raised": 0, "renumberings": 0}
        lat_proc, lat_total = Percentiles(), Percentiles()

        def stats():
            return {"state": "running", **errors, "buffered": stage.buffered,
                    "dropped": done["dropped"] + stage.dropped, "missing": done["missing"] + stage.missing,
                    "orphans": done["orphans"] + stage.orphans, "bad_frames": done["bad"] + len(stage.bad),
                    "flagged": flagged, "pending_releases": len(releases.ready), "ended": ended_streams,
                    "abandoned_releases": releases.abandoned, "resized_frames": sink.resized,
                    "filled": done["filled"] + stage.filled, "fill_raised": done["fill_raised"] + stage.fill_raised,
                    "renumberings": done["renumberings"] + stage.renumberings,
                    **meter.take("render"), **lat_proc.take("lat_proc_ms"), **lat_total.take("lat_total_ms")}

        def publish(out: Iterable[StabilizedFrame], ready: tuple[int, int] | None) -> None:
            """Publish (and write) rendered frames; ``ready``: (numbering, seq) of the frame whose
            arrival closed their release (latency stamps)."""
            nonlocal flagged
            for sf in out:
                t0 = time.perf_counter()
                src = pub_ns.pop((sf.numbering, sf.seq), None)
                ready_ns = pub_ns.get(ready, src) if ready is not None else src
                pub.put(encode_stabilized(StabilizedImage(sf.seq, sf.timestamp_ns, sf.image, sf.zoom, sf.flags),
                                          args.stream, color=args.color, quality=args.quality,
                                          src_pub_ns=src, ready_pub_ns=ready_ns))
                now = time.time_ns()
                sink.write(sf.seq, sf.image)
                flagged += bool(sf.flags)
                if ready_ns:
                    lat_proc.add((now - ready_ns) / 1e6)
                if src:
                    lat_total.add((now - src) / 1e6)
                meter.add((time.perf_counter() - t0) * 1e3)
                rt.maybe_stats(stats)

        def take_frame(key_expr: str, data: bytes) -> None:
            nonlocal resume_after
            msg = rt.decode(key_expr, data, ("frame", "end"), errors)  # now, not in the burst of a segment's corrections
            if msg is None or msg.type == "end":
                return
            published = msg.extra.get("pub_ns")
            if resume_after is not None and msg.seq <= resume_after and (stage.newest is None
                                                                         or not stage.fresh(published)):
                # rendered before the restart (the frames' history); once frames are taken, one published
                # after them is live: a stream renumbered below the cursor, for the stage to confirm
                errors["taken_over"] += 1
                return
            renumberings = stage.renumberings
            try:
                stage.add_frame(msg.seq, msg.obj, published)
            except ValueError as e:
                errors["refused_frames"] += 1
                log.error("frame %d: %s", msg.seq, e)
                return
            if stage.renumberings > renumberings:
                log.warning("frame %d: the stream's numbering restarts (confirmed by %d frames in a row); %d frames "
                            "of the old numbering held for their corrections", msg.seq, stage.jumps.resync,
                            stage.buffered - 1)
                resume_after = None  # the predecessor's cursor says nothing of the new numbering
            pub_ns[(stage.numbering, msg.seq)] = published or 0
            while len(pub_ns) > args.max_frames + 64:
                pub_ns.pop(next(iter(pub_ns)))

        def drain_frames(limit: int | None = None) -> None:
            """Take what arrived (while a batch renders, frames keep coming: hold or drop them now); at
            most ``limit`` frames, so frames arriving faster than they decode never starve the rest."""
            n = 0
            while (limit is None or n < limit) and (item := frames_in.pop()) is not None:
                n += 1
                with rt.contained("frame message", errors):
                    take_frame(item[0], item[1])

        def render_ready(force: bool) -> None:
            while releases.ready:
                rel, batch, t_done, _ = releases.ready[0]
                seqs = [c.seq for c in batch]
                if not (force or stage.can_render(batch) or time.monotonic() - t_done > args.frame_wait):
                    return
                releases.ready.pop(0)
                nbad = len(stage.bad)
                out = stage.iter_batch(batch)
                with rt.contained(f"release {rel} (frames {seqs[0]}..{seqs[-1]})", errors):
                    publish(out, (stage.numbering_of(batch), max(seqs)))
                for b in stage.bad[nbad:]:
                    log.error("frame %d cannot be rendered: %s", b["seq"], b["error"])

        ended = False
        while not rt.stop.is_set():
            rt.maybe_stats(stats)
            # Every pending correction first (cheap, and what releases frames), then the frames that had
            # arrived by now: under overload frames keep coming faster than they decode, and taking
            # one correction per pass of an endless frame drain starved the corrections (no output).
            got = False
            while not ended and (item := corr_in.pop()) is not None:
                got = True
                msg = rt.decode(item[0], item[1], ("correction", "end"), errors)
                if msg is not None and msg.type == "correction":
                    if resume_after is None or msg.seq > resume_after:
                        releases.add(msg.obj, msg.extra.get("batch"))
                elif msg is not None and msg.type == "end":
                    ended = True
            pending = len(frames_in)
            got = got or pending > 0
            drain_frames(pending)
            render_ready(force=False)
            if ended:
                drain_frames()
                n = releases.flush_incomplete()
                if n:
                    log.warning("end of stream with %d incomplete releases", n)
                # the corrections' end can overtake frames still on their way (a frame a congested link
                # dropped comes back later, from its publisher's cache): they get --frame-wait, as in a release
                render_ready(force=False)
                deadline = time.monotonic() + args.frame_wait
                while releases.ready and time.monotonic() < deadline and not rt.stop.is_set():
                    rt.wait(0.02)
                    drain_frames()
                    render_ready(force=False)
                render_ready(force=True)
                publish(stage.flush(), None)
                sink.drain()  # the frames reported written below are on disk when the end is announced
                pub.put(encode_end(msg.obj, args.stream))
                log.info("end of stream: %d frames written, %d flagged, %d orphans, %d missing",
                         sink.frames, flagged, stage.orphans, stage.missing)
                ended = False
                resume_after = None
                ended_streams += 1
                rt.publish_stats(stats())
                for k, v in (("dropped", stage.dropped), ("missing", stage.missing), ("orphans", stage.orphans),
                             ("bad", len(stage.bad)), ("filled", stage.filled), ("fill_raised", stage.fill_raised),
                             ("renumberings", stage.renumberings)):
                    done[k] += v
                stage = RenderStage(params.warp, params.framing, max_frames=args.max_frames)  # a new stream may follow
                continue
            if not got:
                rt.wait(0.05)
        rt.publish_stats({**stats(), "state": "stopped"})
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("render", build_parser(), run, argv, check=stabilizer_params)


if __name__ == "__main__":
    sys.exit(main())

"""``render``: stabilized frames, ``frame`` + ``correction`` -> ``stabilized`` (+ MP4/PNG).

Frames are held as they arrived (checked, not decoded) until their correction arrives, one
segment later, and decoded then; each planner release is warped, framed and rendered as a whole
once all its frames are here, a newer frame has arrived (a missing one is lost: counted) or
``--frame-wait`` seconds passed, one release a pass (the frames arriving meanwhile are taken
between releases). Frames the flow stage shed, named by the corrections, are let go undecoded
(``shed_upstream``: the flow stage's decision, counted there); frames no correction will reach for
another reason (refused upstream) are rendered uncorrected and flagged; a stream renumbered lower
is followed once a run of frames confirms it (``renumberings``). ``--max-frames`` and
``--max-held-mb`` bound what is held (the oldest dropped, counted). Each stabilized frame is
published as soon as it is rendered, with its latency stamps (docs/wire-format.md);
``--output``/``--png`` also write it to disk from a worker thread. On ``end`` (on ``correction``)
everything left is rendered and ``end`` forwarded on ``stabilized``; the video is closed, and
checked on disk, when the service stops. A write that fails (a full disk, a file-size limit, a
video left incomplete) stops the service as the recorder's does: logged with the file and the
frame, the stats' ``state`` ``error`` and ``error`` (the message), exit 2 (not restarted); the
stats' ``frames_written`` counts the frames on disk. The policy is
:class:`quick_stream.core.release.RenderDriver`'s.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable, Iterable, Iterator

import zenoh

from quick_stream.core.frame import RGBDFrame
from quick_stream.core.release import RenderDriver, Rendered
from quick_stream.core.settings import StabilizerParams, settings_digest
from quick_stream.io.sinks import VIDEO_CODECS, BackgroundSink, FileOutput, VideoSink, check_video
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.meters import Latency, RateMeter
from quick_stream.stream.process import service_main, service_parser
from quick_stream.stream.runtime import Input, ServiceRuntime
from quick_stream.io.stabilizer_flags import add_stabilizer_args, stabilizer_params
from quick_stream.stream.wire import StabilizedImage, decode, encode_end, encode_image, encode_stabilized

log = logging.getLogger("render")


def build_parser() -> argparse.ArgumentParser:
    p = service_parser("render", __doc__)
    p.add_argument("--output", type=at.output_file("--output", at.VIDEO_SUFFIXES, "video"), default="",
                   help="also write an MP4 here (default: none)")
    p.add_argument("--png", type=at.output_dir("--png"), default="", metavar="DIR",
                   help="also write every frame as PNG here (default: none)")
    p.add_argument("--fps", type=at.positive_float, default=30.0, help="MP4 frame rate (default 30)")
    p.add_argument("--color", choices=("jpeg", "raw"), default="jpeg", help="published image encoding (default jpeg)")
    p.add_argument("--quality", type=at.quality, default=90, help="JPEG quality, 1-100 (default 90)")
    p.add_argument("--video-codec", choices=VIDEO_CODECS, default="mjpeg",
                   help="--output's codec: mjpeg stores the JPEGs published, with no second encode; mp4v encodes "
                   "each frame again (~2.5 ms a 640x480 frame), files a third of the size (default mjpeg)")
    p.add_argument("--max-frames", type=at.positive_int, default=3600,
                   help="frames held for corrections (default 3600, 30 s at 120 fps)")
    p.add_argument("--max-held-mb", type=at.positive_float, default=256.0,
                   help="MB of frames held for corrections, as they arrived (default 256: 2,700 640x480 frames "
                   "of JPEG colour and zstd depth, 22 s at 120 fps)")
    p.add_argument("--frame-wait", type=at.nonneg_float, default=1.0,
                   help="seconds a complete release waits for missing frames (default 1)")
    add_stabilizer_args(p)
    return p


def run(args: argparse.Namespace, conf: zenoh.Config) -> int:
    params = stabilizer_params(args)
    with ServiceRuntime("render", args.stream, conf, settings=settings_digest(params)) as rt:
        files = FileOutput(BackgroundSink(VideoSink(args.output, args.png, args.fps, args.video_codec, args.quality)),
                           rt.stop, log)
        try:
            serve(args, params, rt, files)
        finally:
            files.close()
    return 2 if files.error is not None else 0  # 2: not restarted (a full disk stops the run)


def serve(args: argparse.Namespace, params: StabilizerParams, rt: ServiceRuntime, sink: FileOutput) -> None:
    resume_after = rt.take_over("stabilized", "frames' and corrections", log)  # not None: a restarted render
    driver = RenderDriver(params.warp, params.framing, max_frames=args.max_frames, frame_wait=args.frame_wait,
                          resume_after=resume_after, log=log, max_bytes=int(args.max_held_mb * 2**20))
    # frames wait there as their messages while a release renders (8 s at 120 frames/s, not 2)
    frames_in = rt.inbox(keys.key(args.stream, "frame"), 1024, history=resume_after is not None, publisher="capture")
    corr_in = rt.inbox(keys.key(args.stream, "correction"), 100_000, history=resume_after is not None,
                       publisher="motion")
    pub = rt.publisher("stabilized")  # lossless (stream/topology.py): the recorder recovers what its link dropped
    rt.serve_cursor()
    rt.ready()
    meter, latency = RateMeter(), Latency()

    def publish(groups: Iterable[tuple[str, Iterator[Rendered]]]) -> None:
        for label, frames in groups:
            with rt.contained(label):
                for r in frames:
                    t0, sf = time.perf_counter(), r.frame
                    image = encode_image(sf.image, args.color, args.quality)  # published, and the video's JPEG
                    pub.put(encode_stabilized(StabilizedImage(sf.seq, sf.timestamp_ns, sf.image, sf.zoom, sf.flags),
                                              args.stream, src_pub_ns=r.src_pub_ns, ready_pub_ns=r.ready_pub_ns,
                                              image=image))
                    latency.add(r.src_pub_ns, r.ready_pub_ns)
                    sink.write(sf.seq, sf.image, image["data"] if image["enc"] == "jpeg" else None)
                    meter.add((time.perf_counter() - t0) * 1e3)
                    rt.maybe_stats()

    def tick(stopping: bool = False) -> None:
        for rel in driver.due():  # one a pass: the frames arriving meanwhile are taken between releases
            publish([(rel.label, driver.render(rel))])
            break
        if driver.end_due(stopping):
            publish(driver.finish())
            sink.drain()  # the frames reported written below are on disk when the end is announced
            pub.put(encode_end(driver.end_marker, args.stream))
            log.log(logging.ERROR if sink.error else logging.INFO,
                    "end of stream: %d frames written%s, %d flagged, %d orphans, %d missing", sink.frames,
                    " (the file FAILED, see above)" if sink.error else "", driver.flagged,
                    driver.stage.orphans, driver.stage.missing)
            driver.restart()  # a new stream may follow
            rt.publish_stats()

    def take_frame(m) -> bool:
        return driver.add_frame(m.seq, held(m.payload), m.pub_ns, len(m.payload))

    # all pending corrections, then the frames pending by then (RenderDriver.takes_corrections)
    rt.serve([Input(corr_in, {"correction": lambda m: driver.add_correction(m.obj, m.tag),
                              "end": lambda m: driver.end(m.obj)}, take="all",
                    paused=lambda: not driver.takes_corrections),
              Input(frames_in, {"frame": take_frame, "end": None}, take="pending", lazy=True)],
             lambda: {**driver.stats(), **sink.stats(), **meter.take("render"), **latency.take()},
             tick=tick, idle_s=lambda: 0.0 if driver.has_due else driver.idle_s,
             on_stop=lambda: stopping(driver, tick, sink),
             final_state=lambda: "error" if sink.error is not None else "stopped")


def stopping(driver: RenderDriver, tick: Callable[..., None], sink: FileOutput) -> None:
    """Stopped: what an ending stream still holds rendered, then the video closed and checked on disk
    (before the last stats, which carry its error)."""
    try:
        if driver.ending:
            tick(stopping=True)
    finally:
        sink.close()


def held(data: bytes) -> Callable[[], RGBDFrame]:
    """A frame as render holds it: its message, decoded when its correction comes."""
    return lambda: decode(data).obj


def main(argv: list[str] | None = None) -> int:
    def check(args: argparse.Namespace) -> None:
        check_video(args.output, args.video_codec)
        stabilizer_params(args)

    return service_main("render", build_parser(), run, argv, check=check)


if __name__ == "__main__":
    sys.exit(main())

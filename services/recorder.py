"""``recorder``: every stage's messages of a stream (or of all streams) into one MCAP file.

Subscribes ``quick/@v1/<stream>/*`` (``--all-streams``: ``quick/@v1/*/*``) and
logs each message's exact bytes on a msgpack channel named after its key (exact
replay: ``capture --source mcap:FILE``, ``quick-stream rerun``), plus the
Foxglove-viewable channels derived from them (images, calibration, camera and
stabilized poses; :mod:`quick_stream.foxglove_view`). The file's open chunk is
written out every ``--flush`` seconds (default 1), so a killed recorder loses at
most about that much; ``quick-stream recover`` repairs the footer-less file, and a
restarted recorder writes to ``<name>-1.mcap`` (``-2``, ...) instead of overwriting it.
"""
from __future__ import annotations

import logging
import sys
import time

import zenoh

from quick_stream import foxglove, keys
from quick_stream.cli import argtypes as at
from quick_stream.foxglove_view import FoxgloveView
from quick_stream.recording import Recorder, fresh_path
from quick_stream.runtime import RateMeter, ServiceRuntime, lower_priority, service_main, service_parser
from quick_stream.wire import WireError

log = logging.getLogger("recorder")


def build_parser():
    p = service_parser("recorder", __doc__)
    p.add_argument("--output", type=at.output_file("--output"), default="out/recording.mcap",
                   help="MCAP file (default out/recording.mcap)")
    p.add_argument("--all-streams", action="store_true", help="record every stream, not only --stream")
    p.add_argument("--flush", type=at.positive_float, default=1.0, help="seconds between chunk flushes (default 1)")
    p.add_argument("--no-foxglove", action="store_true", help="msgpack channels only")
    p.add_argument("--queue", type=at.positive_int, default=4096, help="messages held before the oldest is dropped")
    p.add_argument("--nice", type=at.int_in(0, 19), default=10,
                   help="lower this process's CPU priority by this much, 0-19 (default 10: the live path goes first)")
    p.add_argument("--compression", choices=("none", "zstd", "lz4"), default="none",
                   help="MCAP chunk compression (default none: images do not compress; zstd saves ~25%% "
                        "on flow and base64 image channels for CPU)")
    return p


def run(args, conf: zenoh.Config) -> int:
    lower_priority(args.nice)
    out = fresh_path(args.output)
    if str(out) != args.output:
        log.warning("%s exists (a previous run or a killed recorder): recording to %s", args.output, out)
    views: dict[str, FoxgloveView] = {}
    with ServiceRuntime("recorder", args.stream, conf) as rt, Recorder(out, flush_s=args.flush, compression=args.compression) as rec:
        sub_key = f"{keys.PREFIX}/*/*" if args.all_streams else keys.stream_keys(args.stream)
        inbox = rt.inbox(sub_key, args.queue)
        rt.serve_cursor(args.all_streams)  # the newest seq of every stage: how far a restarted service's predecessor got
        rt.ready()
        meter = RateMeter()
        errors = {"bad_keys": 0, "view_errors": 0, "internal_errors": 0}
        logged_bytes = 0

        def stats():
            return {"state": "running", "messages": rec.messages, "bytes": logged_bytes, **errors,
                    **meter.take("log")}

        def log_one(key_expr: str, payload: bytes) -> None:
            nonlocal logged_bytes
            try:
                stream, stage = keys.parse(key_expr)
            except ValueError as e:
                errors["bad_keys"] += 1
                log.error("%s", e)
                return
            t0 = time.perf_counter()
            now = time.time_ns()
            rec.write(key_expr, payload, log_time_ns=now)
            logged_bytes += len(payload)
            if not args.no_foxglove:
                view = views.get(stream)
                if view is None:
                    view = views[stream] = FoxgloveView(stream)
                    foxglove.register_channels(rec, stream)
                try:
                    for topic, data in view.convert(stage, payload):
                        rec.write(topic, data, log_time_ns=now)
                except WireError as e:
                    errors["view_errors"] += 1
                    log.error("%s: no Foxglove view: %s", key_expr, e)
            meter.add((time.perf_counter() - t0) * 1e3)

        while not rt.stop.is_set():
            rt.maybe_stats(stats)
            rec.maybe_flush()
            item = inbox.pop()
            if item is None:
                rt.wait(0.2)
                continue
            with rt.contained(f"message on {item[0]}", errors):
                log_one(*item)
        # stopping: what was already received is still written (accepted data is never lost)
        while (item := inbox.pop()) is not None:
            log_one(*item)
        rt.publish_stats({**stats(), "state": "stopped"})
    log.info("closed %s: %d messages", out, rec.messages)
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("recorder", build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())

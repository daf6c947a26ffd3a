"""``recorder``: every stage's messages of a stream (or of all streams) into one MCAP file.

Subscribes ``quick/@v1/<stream>/*`` (``--all-streams``: ``quick/@v1/*/*``) and
logs each message's exact bytes on a msgpack channel named after its key (exact
replay: ``capture --source mcap:FILE``, ``quick-stream rerun``), plus the
Foxglove-viewable channels derived from them (images, calibration, camera and
stabilized poses; :mod:`quick_stream.foxglove_view`).

Nothing accepted is lost to a kill: each message's wire bytes go into the file's open
chunk as it arrives (in zenoh's thread, not behind a queue), and the chunk is written out
at least every ``--flush`` seconds (default 0.5), so a SIGKILL loses at most what arrived
in the last ``--flush`` seconds. The Foxglove channels are derived in the main loop from
a drop-oldest queue (``--queue``; drops counted as ``inbox0_dropped``): under CPU
pressure they may thin out, the wire channels never. ``quick-stream recover`` repairs
the footer-less file, and a restarted recorder writes to ``<name>-1.mcap`` (``-2``, ...)
instead of overwriting it.
"""
from __future__ import annotations

import logging
import sys
import threading
import time

import zenoh

from quick_stream import foxglove, keys
from quick_stream.cli import argtypes as at
from quick_stream.foxglove_view import FoxgloveView
from quick_stream.recording import Recorder, fresh_path
from quick_stream.meters import RateMeter
from quick_stream.runtime import ServiceRuntime, lower_priority, service_main, service_parser
from quick_stream.wire import WireError

log = logging.getLogger("recorder")


def build_parser():
    p = service_parser("recorder", __doc__)
    p.add_argument("--output", type=at.output_file("--output"), default="out/recording.mcap",
                   help="MCAP file (default out/recording.mcap)")
    p.add_argument("--all-streams", action="store_true", help="record every stream, not only --stream")
    p.add_argument("--flush", type=at.positive_float, default=0.5,
                   help="seconds between chunk flushes: what a killed recorder can lose (default 0.5)")
    p.add_argument("--no-foxglove", action="store_true", help="msgpack channels only")
    p.add_argument("--queue", type=at.positive_int, default=4096,
                   help="messages waiting for their Foxglove view before the oldest is dropped (default 4096)")
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
    lock = threading.Lock()  # the writer is shared by zenoh's thread (wire bytes), the flusher and the views
    # the session closes before the file: nothing arrives once the file is finished
    # 4 MiB chunks: the writer keeps an index entry per chunk for the footer (memory grows with
    # their number: ~14 per second with 1 MiB chunks at 640x480 and 30 fps); flushes still close
    # a chunk every --flush seconds
    with Recorder(out, flush_s=args.flush, compression=args.compression, chunk_size=4 << 20) as rec, \
            ServiceRuntime("recorder", args.stream, conf) as rt:
        meter = RateMeter()
        errors = {"bad_keys": 0, "view_errors": 0, "internal_errors": 0}
        logged = {"bytes": 0}

        def stats():
            with lock:
                return {"state": "running", "messages": rec.messages, "bytes": logged["bytes"], **errors,
                        **meter.take("log")}

        def accept(key_expr: str, payload: bytes, t_ns: int) -> None:
            """Zenoh's thread, on arrival: the exact wire bytes into the file's open chunk at once, so
            what arrived is on disk within ``--flush`` seconds however far the views lag behind."""
            try:
                keys.parse(key_expr)
            except ValueError as e:
                errors["bad_keys"] += 1
                log.error("%s", e)
                return
            t0 = time.perf_counter()
            with lock:
                if rec.closed:
                    return
                rec.write(key_expr, payload, log_time_ns=t_ns)
                logged["bytes"] += len(payload)
                meter.add((time.perf_counter() - t0) * 1e3)

        def view_one(key_expr: str, payload: bytes, t_ns: int) -> None:
            """The Foxglove channels derived from one message (same log time as its wire bytes)."""
            try:
                stream, stage = keys.parse(key_expr)
            except ValueError:
                return  # counted in accept
            view = views.get(stream)
            if view is None:
                view = views[stream] = FoxgloveView(stream)
                with lock:
                    foxglove.register_channels(rec, stream)
            try:
                converted = list(view.convert(stage, payload))
            except WireError as e:
                errors["view_errors"] += 1
                log.error("%s: no Foxglove view: %s", key_expr, e)
                return
            with lock:
                for topic, data in converted:
                    rec.write(topic, data, log_time_ns=t_ns)

        def flusher() -> None:
            while not rt.stop.wait(min(0.1, args.flush / 4)):
                with lock:
                    rec.maybe_flush()

        sub_key = f"{keys.PREFIX}/*/*" if args.all_streams else keys.stream_keys(args.stream)
        inbox = rt.inbox(sub_key, args.queue, on_arrival=accept)  # the queue feeds the views only
        rt.serve_cursor(args.all_streams)  # the newest seq of every stage: how far a restarted service's predecessor got
        threading.Thread(target=flusher, name="recorder-flush", daemon=True).start()
        rt.ready()
        while not rt.stop.is_set():
            rt.maybe_stats(stats)
            item = inbox.pop()
            if item is None:
                rt.wait(0.2)
                continue
            if not args.no_foxglove:
                with rt.contained(f"Foxglove view of a message on {item[0]}", errors):
                    view_one(*item)
        if not args.no_foxglove:  # stopping: the views of what was already received
            while (item := inbox.pop()) is not None:
                view_one(*item)
        rt.publish_stats({**stats(), "state": "stopped"})
    log.info("closed %s: %d messages", out, rec.messages)
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("recorder", build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())

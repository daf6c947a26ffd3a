"""``recorder``: every stage's messages of a stream (or of all streams) into an MCAP file.

Subscribes ``quick/@v1/<stream>/*`` (``--all-streams``: ``quick/@v1/*/*``) and
logs each message on a msgpack channel named after its key (exact replay: ``capture
--source mcap:FILE``, ``quick-stream rerun``), plus the Foxglove-viewable protobuf
channels (images, calibration, camera and stabilized poses and transforms;
:mod:`quick_stream.io.foxglove`, docs/recording.md).

Images are stored once: the JPEG of a frame's colour and of a stabilized image goes into
its ``foxglove.CompressedImage`` record, and the msgpack record holds the wire message
referencing it; readers put it back byte for byte (:mod:`quick_stream.io.recording_images`).
``--no-foxglove``: msgpack channels only, each message whole.

Nothing accepted is lost to a kill: each message (with its image record) goes into the
file's open chunk as it arrives (in zenoh's thread, not behind a queue), and the chunk is
written out at least every ``--flush`` seconds (default 0.5), so a SIGKILL loses at most
what arrived in the last ``--flush`` seconds. The other Foxglove channels are derived in
the main loop from a drop-oldest queue (``--queue``; drops counted as ``inbox0_dropped``):
under CPU pressure they may thin out, the wire and image channels never. ``quick-stream recover`` repairs
the footer-less file, and a restarted recorder writes to ``<name>-1.mcap`` (``-2``, ...)
instead of overwriting it.

Long runs are split (``--split-mb``, default 4096; ``--split-minutes``): the file is finished
(footer, indexes) and the next free ``<name>-N.mcap`` starts, with the same channels; no
message is lost or doubled at the seam. This bounds each file and the writer's in-memory
index (one entry per chunk, kept for the footer: about 1 MB a minute at 640x480, 30 frames/s).

No loss upstream is silent: the seqs of each stage that never arrived (dropped by a stage,
lost in transport) are logged and counted in the stats (``unreceived``, per stage
``unreceived_<stage>``; :mod:`quick_stream.stream.arrivals`).
"""
from __future__ import annotations

import logging
import sys
import threading
import time

import zenoh

from quick_stream.io import foxglove
from quick_stream.io.foxglove_view import FoxgloveView
from quick_stream.io.recording_images import write_message
from quick_stream.io.recording import SplitRecorder, fresh_path, load_recorded, recorded_path, save_recorded
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.arrivals import Gap
from quick_stream.stream.meters import RateMeter
from quick_stream.stream.runtime import ServiceRuntime, lower_priority, service_main, service_parser
from quick_stream.stream.wire import WireError
from quick_stream.stream.wire.codec import peek

log = logging.getLogger("recorder")


def build_parser():
    p = service_parser("recorder", __doc__)
    p.add_argument("--output", type=at.output_file("--output"), default="out/recording.mcap",
                   help="MCAP file (default out/recording.mcap)")
    p.add_argument("--all-streams", action="store_true", help="record every stream, not only --stream")
    p.add_argument("--flush", type=at.positive_float, default=0.5,
                   help="seconds between chunk flushes: what a killed recorder can lose (default 0.5)")
    p.add_argument("--no-foxglove", action="store_true",
                   help="msgpack channels only (each message whole; no Foxglove image, pose or calibration channels)")
    p.add_argument("--queue", type=at.positive_int, default=4096,
                   help="messages waiting for their Foxglove view before the oldest is dropped (default 4096)")
    p.add_argument("--nice", type=at.int_in(0, 19), default=10,
                   help="lower this process's CPU priority by this much, 0-19 (default 10: the live path goes first)")
    p.add_argument("--compression", choices=("none", "zstd", "lz4"), default="none",
                   help="MCAP chunk compression (default none: images do not compress, and the flow and "
                        "depth in the wire messages are compressed already; docs/recording.md)")
    p.add_argument("--split-mb", type=at.nonneg_float, default=4096.0,
                   help="finish the file and start the next once it holds this many MB (0: never; default 4096)")
    p.add_argument("--split-minutes", type=at.nonneg_float, default=0.0,
                   help="finish the file and start the next after this many minutes (default 0: never)")
    return p


def run(args, conf: zenoh.Config) -> int:
    lower_priority(args.nice)
    out = fresh_path(args.output)
    if str(out) != args.output:
        log.warning("%s exists (a previous run or a killed recorder): recording to %s", args.output, out)
    views: dict[str, FoxgloveView] = {}
    lock = threading.Lock()  # the writer is shared by zenoh's thread (wire bytes), the flusher and the views
    # the session closes before the file: nothing arrives once the file is finished
    streams: list[str] = []  # whose Foxglove channels every file registers (a split's next file too)
    # 4 MiB chunks: the writer keeps an index entry per chunk for the footer (memory grows with
    # their number: ~14 per second with 1 MiB chunks at 640x480 and 30 fps); flushes still close
    # a chunk every --flush seconds
    files = SplitRecorder(args.output, out, split_bytes=int(args.split_mb * 2**20), split_s=args.split_minutes * 60,
                          on_open=lambda rec: [foxglove.register_channels(rec, s) for s in streams],
                          flush_s=args.flush, compression=args.compression, chunk_size=4 << 20)
    with files, ServiceRuntime("recorder", args.stream, conf) as rt:
        meter = RateMeter()
        errors = {"bad_keys": 0, "view_errors": 0, "internal_errors": 0, "unrecorded": 0}
        logged = {"bytes": 0}
        failure: list[str] = []  # why the file cannot be written (a full disk, a file size limit)

        def write_failed(e: OSError) -> None:  # under the lock
            """The first failed write stops the recording, said once and clearly (docs/reliability.md)."""
            if not failure:
                failure.append(f"cannot write {files.rec.path}: {e.strerror or e}")
                log.error("%s; recording stops here (what is on disk stays: `quick-stream recover %s` salvages "
                          "it), and the recorder exits 2", failure[0], files.rec.path)
                files.rec.abandon()
                rt.stop.set()
        last_gap_log: dict[str, float] = {}
        # A restarted recorder continues its predecessor's account: what that one flushed (its side
        # file, docs/reliability.md) up to what arrives now was published while no recorder ran.
        before = load_recorded(args.output)
        holes = {"messages": 0}

        def hole(gap: Gap) -> None:
            holes["messages"] += gap.count
            log.warning("recorder restart: %s/%s seq %d-%d (%d) were published while no recorder ran and are in "
                        "no recording", gap.stream, gap.stage, gap.first, gap.last, gap.count)

        def gap_seen(gap: Gap) -> None:  # zenoh's thread; one line per stage and second at most
            if (gap.stream, gap.stage) in before and gap.first == before[(gap.stream, gap.stage)] + 1:
                hole(gap)
                return
            now = time.monotonic()
            if now - last_gap_log.get(gap.stage, -1e9) >= 1.0:
                last_gap_log[gap.stage] = now
                log.warning("%s/%s: seq %d-%d never arrived (%d; %d of this stage so far): dropped upstream "
                            "(see that stage's stats) or lost in transport", gap.stream, gap.stage, gap.first,
                            gap.last, gap.count, inbox.arrivals.unreceived().get(gap.stage, 0))

        def wrote(n: int) -> None:  # under the lock
            finished = files.wrote(n)
            if finished is not None:
                log.info("split: finished %s (%d messages), recording to %s", finished, files.done[-1][1],
                         files.rec.path)

        def stats():
            with lock:
                ledger = inbox.arrivals  # seqs of each stage that never arrived: no loss upstream is silent
                unreceived = ledger.unreceived()
                return {"state": "error" if failure else "running", **({"error": failure[0]} if failure else {}),
                        "messages": files.messages, "bytes": logged["bytes"],
                        "files": len(files.done) + 1, **errors, "restart_hole": holes["messages"],
                        "unreceived": sum(unreceived.values()),
                        **{f"unreceived_{k}": v for k, v in unreceived.items()}, "late": ledger.late,
                        "duplicates": ledger.duplicates, "renumberings": ledger.renumberings,
                        **meter.take("log")}

        def accept(key_expr: str, payload: bytes, t_ns: int) -> None:
            """Zenoh's thread, on arrival: the message (its JPEG in its Foxglove image record) into the
            file's open chunk at once, so what arrived is on disk within ``--flush`` seconds however
            far the views lag behind."""
            try:
                stream, _ = keys.parse(key_expr)
            except ValueError as e:
                errors["bad_keys"] += 1
                log.error("%s", e)
                return
            t0 = time.perf_counter()
            with lock:
                if files.rec.closed:
                    errors["unrecorded"] += bool(failure)  # arrived after the recording failed
                    return
                try:
                    if not args.no_foxglove and stream not in streams:  # its channels, before its first message
                        streams.append(stream)
                        foxglove.register_channels(files.rec, stream)
                    n = write_message(lambda topic, data: files.rec.write(topic, data, log_time_ns=t_ns),
                                      key_expr, payload, t_ns, images=not args.no_foxglove)
                    logged["bytes"] += n
                    wrote(n)
                except OSError as e:
                    errors["unrecorded"] += 1
                    write_failed(e)
                    return
                meter.add((time.perf_counter() - t0) * 1e3)
            if (env := peek(payload)) is not None and env[0] == "end":
                log.info("recorded the end of %s", key_expr)  # what a stage's last message was, for operators

        def view_one(key_expr: str, payload: bytes, t_ns: int) -> None:
            """The Foxglove channels derived from one message (same log time as its wire message);
            JPEG images were written on arrival (:func:`accept`)."""
            try:
                stream, stage = keys.parse(key_expr)
            except ValueError:
                return  # counted in accept
            view = views.get(stream)
            if view is None:
                view = views[stream] = FoxgloveView(stream)  # its channels: registered on its first message
            try:
                converted = list(view.convert(stage, payload, t_ns, jpeg=False))
            except WireError as e:
                errors["view_errors"] += 1
                log.error("%s: no Foxglove view: %s", key_expr, e)
                return
            with lock:
                try:
                    for topic, data in converted:
                        if files.rec.closed:
                            return
                        files.rec.write(topic, data, log_time_ns=t_ns)
                        wrote(len(data))
                except OSError as e:
                    write_failed(e)

        def flusher() -> None:
            saved = (None, -1)  # the file and flush the side file last described
            while not rt.stop.wait(min(0.1, args.flush / 4)):
                with lock:
                    if files.rec.closed:
                        continue
                    try:
                        files.rec.maybe_flush()
                        # write() flushes too when one is due, so under steady traffic most flushes
                        # happen there: describe every new one (what is on disk now, for a successor)
                        if (files.rec, files.rec.flushes) != saved and files.rec.flushes:
                            save_recorded(args.output, inbox.arrivals.newest())
                            saved = (files.rec, files.rec.flushes)
                        wrote(0)  # a time split is due even when nothing arrives
                    except OSError as e:
                        write_failed(e)

        sub_key = f"{keys.PREFIX}/*/*" if args.all_streams else keys.stream_keys(args.stream)
        inbox = rt.inbox(sub_key, args.queue, on_arrival=accept, on_gap=gap_seen)  # the queue feeds the views only
        for (stream, stage), seq in before.items():
            if (gap := inbox.arrivals.seed(stream, stage, seq)) is not None:
                hole(gap)
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
        rt.publish_stats({**stats(), "state": "error" if failure else "stopped"})
    log.info("%s %s: %d messages%s", "abandoned" if failure else "closed", files.rec.path, files.rec.messages,
             f" ({len(files.done)} earlier files, {files.messages} messages in all)" if files.done else "")
    if unreceived := inbox.arrivals.unreceived():
        log.warning("never arrived, per stage: %s", unreceived)
    recorded_path(args.output).unlink(missing_ok=True)  # a clean stop: no successor continues this account
    return 2 if failure else 0  # 2: not restarted (docs/reliability.md: a full disk stops the run)


def main(argv: list[str] | None = None) -> int:
    return service_main("recorder", build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())

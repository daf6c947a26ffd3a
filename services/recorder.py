"""``recorder``: every stage's messages of a stream (or of all streams) into MCAP files (docs/recording.md).

Subscribes ``quick/@v1/<stream>/*`` (``--all-streams``: every stream's) and logs each message on a
msgpack channel named after its key (exact replay, ``quick-stream rerun``), its JPEG stored once in
a Foxglove image record, plus the Foxglove pose, transform and calibration channels (``--no-foxglove``:
msgpack only). Every file starts with the stabilizer settings record (``--settings``: the stages'
file). A message is in the file's open chunk as it arrives and on disk within ``--flush`` seconds;
a killed recorder's file is repaired by ``quick-stream recover`` and its successor writes the next
``<name>-N.mcap``; long runs split at ``--split-mb``/``--split-minutes`` with nothing lost or doubled;
seqs that never arrived are logged and counted (``unreceived_<stage>``); a message that arrives
again byte for byte (a restarted publisher's) is stored once (``replays``), one with the same seq and
other bytes is kept and logged (``seq_conflicts``); a full disk stops it (exit 2, docs/reliability.md). All of it is :class:`quick_stream.io.stream_recording.StreamRecording`.
"""
from __future__ import annotations

import argparse
import sys
import threading

import zenoh

from quick_stream.core.settings import settings_digest
from quick_stream.io.settings_file import settings_record
from quick_stream.io.stabilizer_flags import add_stabilizer_args, stabilizer_params
from quick_stream.io.stream_recording import StreamRecording
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.process import lower_priority, service_main, service_parser
from quick_stream.stream.runtime import Input, ServiceRuntime


def build_parser() -> argparse.ArgumentParser:
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
    add_stabilizer_args(p)  # the settings the stages run with: every file's settings record
    return p


def run(args: argparse.Namespace, conf: zenoh.Config) -> int:
    lower_priority(args.nice)
    params = stabilizer_params(args)
    # the session closes before the file: nothing arrives once the file is finished; the first failed
    # write stops the recording, and so the service
    with StreamRecording(args.output, foxglove_views=not args.no_foxglove, flush_s=args.flush,
                         compression=args.compression, split_mb=args.split_mb, split_minutes=args.split_minutes,
                         settings=settings_record(params), on_failure=lambda: rt.stop.set()) as rec, \
            ServiceRuntime("recorder", args.stream, conf, settings=settings_digest(params)) as rt:
        sub_key = f"{keys.PREFIX}/*/*" if args.all_streams else keys.stream_keys(args.stream)
        # the queue feeds the views; a message received before, byte for byte (a restarted motion sends
        # its predecessor's last motions again), is dropped on arrival: stored once, not a renumbering
        inbox = rt.inbox(sub_key, args.queue, on_arrival=rec.accept, on_gap=rec.gap_seen, replays=rec.replays)
        rec.attach(inbox.arrivals)
        rt.serve_cursor(args.all_streams)  # the newest seq of every stage: how far a restarted service's predecessor got
        threading.Thread(target=rec.flusher, args=(rt.stop,), name="recorder-flush", daemon=True).start()
        rt.ready()

        def drain() -> None:  # stopping: the views of what was already received
            while (item := inbox.pop()) is not None:
                rec.view(*item)

        rt.serve([Input(inbox, raw=rec.view, label=lambda key: f"Foxglove view of a message on {key}")], rec.stats,
                 on_stop=drain, final_state=lambda: "error" if rec.failure else "stopped")
    return 2 if rec.failure else 0  # 2: not restarted (docs/reliability.md: a full disk stops the run)


def main(argv: list[str] | None = None) -> int:
    return service_main("recorder", build_parser(), run, argv, check=stabilizer_params)


if __name__ == "__main__":
    sys.exit(main())

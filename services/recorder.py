"""``recorder``: every stage's messages of a stream (or of all streams) into an MCAP file.

Subscribes ``quick/@v1/<stream>/*`` (``--all-streams``: ``quick/@v1/*/*``) and
logs each message on a msgpack channel named after its key (exact replay: ``capture
--source mcap:FILE``, ``quick-stream rerun``), plus the Foxglove-viewable protobuf
channels (images, calibration, camera and stabilized poses and transforms;
:mod:`quick_stream.io.foxglove`, docs/recording.md). Every file starts with the stabilizer
settings (``--settings`` and the flags: give it what the stages run with) as a metadata record,
which ``quick-stream rerun`` and ``--source mcap:`` replay read back.

Images are stored once: the JPEG of a frame's colour and of a stabilized image goes into
its ``foxglove.CompressedImage`` record, and the msgpack record holds the wire message
referencing it; readers put it back byte for byte (:mod:`quick_stream.io.recording_images`).
``--no-foxglove``: msgpack channels only, each message whole.

Nothing accepted is lost to a kill: each message (with its image record) goes into the
file's open chunk as it arrives (in zenoh's thread, not behind a queue), and the chunk is
written out at least every ``--flush`` seconds (default 0.5), so a SIGKILL loses at most
what arrived in the last ``--flush`` seconds. The other Foxglove channels are derived in
the service loop from a drop-oldest queue (``--queue``; drops counted as ``inbox0_dropped``):
under CPU pressure they may thin out, the wire and image channels never. ``quick-stream recover`` repairs
the footer-less file, and a restarted recorder writes to ``<name>-1.mcap`` (``-2``, ...)
instead of overwriting it.

Long runs are split (``--split-mb``, default 4096; ``--split-minutes``): the file is finished
(footer, indexes) and the next free ``<name>-N.mcap`` starts, with the same channels; no
message is lost or doubled at the seam. This bounds each file and the writer's in-memory
index (one entry per chunk, kept for the footer: about 1 MB a minute at 640x480, 30 frames/s).

No loss upstream is silent: the seqs of each stage that never arrived (dropped by a stage,
lost in transport) are logged and counted in the stats (``unreceived``, per stage
``unreceived_<stage>``; :mod:`quick_stream.stream.arrivals`). All of it is
:class:`quick_stream.io.stream_recording.StreamRecording`.
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
        inbox = rt.inbox(sub_key, args.queue, on_arrival=rec.accept, on_gap=rec.gap_seen)  # the queue feeds the views
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

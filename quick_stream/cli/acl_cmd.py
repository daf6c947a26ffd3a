"""``quick-stream acl``: the TLS router's configuration with access control for your streams.

Prints (or writes to ``--output``) a router-tls.json5 whose access control lets each stream's
certificates (deploy/tls/make-certs.sh ``--streams``, common names ``quick-<service>-<stream>``)
do what that service needs on that stream and nothing else (quick_stream/stream/acl.py). The router reads
it once, at start: generate it again, and restart the router, when a stream is added.
deploy/zenoh/router-tls.json5 is ``quick-stream acl --streams cam0``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..stream import argtypes as at, keys


def _streams(text: str) -> list[str]:
    streams = [keys.check_stream(s.strip()) for s in text.split(",")]
    if len(set(streams)) != len(streams):
        raise ValueError(f"a stream is named twice in {text!r}")
    return streams


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("acl", help="router-tls.json5 with access control for the given streams",
                       description=at.plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--streams", type=at.checked(_streams, "streams"), default=["cam0"], metavar="ID[,ID...]",
                   help="comma-separated stream ids (default: cam0)")
    p.add_argument("--output", type=at.output_file("--output"), default="", metavar="FILE",
                   help="write here instead of printing (default: standard output)")
    at.add_force(p)


def run(args: argparse.Namespace) -> int:
    from ..stream.acl import router_config_text

    text = router_config_text(args.streams)
    if args.output:
        Path(args.output).write_text(text)
    else:
        sys.stdout.write(text)
    return 0

"""Zenoh session set-up shared by every service: the standard zenoh CLI flags -> ``zenoh.Config``.

Flags as in the zenoh-python examples: ``-m/--mode``, ``-e/--connect``,
``-l/--listen``, ``-c/--config``, ``--no-multicast-scouting``, ``--cfg KEY:VALUE``
(VALUE is JSON5, e.g. ``--cfg 'transport/shared_memory/enabled:false'``).
Pitfalls measured here (design/transport-facts.md): peers that only connect to a
router exchange no data unless they also listen, so a peer with ``-e`` and no
``-l`` listens on ``tcp/127.0.0.1:0``; never enable ``transport/unicast/lowlatency``.
"""
from __future__ import annotations

import argparse
import json

import zenoh


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("zenoh")
    g.add_argument("-m", "--mode", choices=("peer", "client", "router"), help="session mode (default peer)")
    g.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable)")
    g.add_argument("-c", "--config", metavar="FILE", help="zenoh JSON5 configuration file")
    g.add_argument("--no-multicast-scouting", action="store_true", help="disable multicast scouting")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="set a configuration key to a JSON5 value (repeatable)")


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """Build the session configuration; errors name the flag or key at fault (ValueError)."""
    try:
        conf = zenoh.Config.from_file(args.config) if args.config else zenoh.Config()
    except (zenoh.ZError, OSError, ValueError) as e:
        raise ValueError(f"--config {args.config}: {e}") from None

    def put(key: str, value_json: str, flag: str) -> None:
        try:
            conf.insert_json5(key, value_json)
        except (zenoh.ZError, ValueError) as e:
            raise ValueError(f"{flag}: cannot set {key} to {value_json}: {e}") from None

    if args.mode:
        put("mode", json.dumps(args.mode), "--mode")
    if args.connect:
        put("connect/endpoints", json.dumps(args.connect), "--connect")
    if args.listen:
        put("listen/endpoints", json.dumps(args.listen), "--listen")
    elif args.connect and (args.mode or "peer") == "peer":
        put("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]), "--connect")
    if args.no_multicast_scouting:
        put("scouting/multicast/enabled", "false", "--no-multicast-scouting")
    for item in args.cfg:
        k, sep, v = item.partition(":")
        if not sep or not k:
            raise ValueError(f"--cfg expects KEY:VALUE, got {item!r}")
        put(k, v, f"--cfg {item}")
    return conf

"""``quick-stream`` command line: one sub-command per job.

Sub-commands live in their own modules and register an ``add_parser`` and a
``run(args) -> int`` pair here.
"""
from __future__ import annotations

import argparse
import logging
import sys

from . import bench_cmd, evaluate_cmd, motion_cmd, recover_cmd, rerun_cmd, router_cmd, stabilize_cmd, up_cmd

COMMANDS = {
    "stabilize": stabilize_cmd, "evaluate": evaluate_cmd, "motion": motion_cmd, "bench": bench_cmd,
    "recover": recover_cmd, "rerun": rerun_cmd, "router": router_cmd, "up": up_cmd,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="quick-stream",
        description="QuICK 3D video stabilization for RGB-D cameras.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, mod in COMMANDS.items():
        mod.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    return COMMANDS[args.command].run(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""``quick-stream`` command line: one sub-command per job.

Sub-commands live in their own modules and register an ``add_parser`` and a
``run(args) -> int`` pair here. They are imported when the parser is built, not with
this package, so ``quick-stream router`` and ``up`` start without the evaluation and
benchmark modules (and SciPy's) behind the other commands. The cli is the top layer: the
services never import it (their shared flags are :mod:`quick_stream.stream.argtypes` and
:mod:`quick_stream.stream.stabilizer_flags`).
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys
from types import ModuleType

from ..stream.argtypes import check_outputs

COMMANDS = ("stabilize", "evaluate", "motion", "bench", "recover", "rerun", "recording-stats", "router", "up", "acl")


def command(name: str) -> ModuleType:
    """The module of sub-command ``name`` (``<name>_cmd``, dashes as underscores)."""
    return importlib.import_module(f"{__name__}.{name.replace('-', '_')}_cmd")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="quick-stream",
        description="QuICK 3D video stabilization for RGB-D cameras.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        command(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        check_outputs(args)  # before any work: an output path that cannot be written (argtypes)
    except ValueError as e:
        print(f"quick-stream {args.command}: {e}", file=sys.stderr)
        return 2
    return command(args.command).run(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

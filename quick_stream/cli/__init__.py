"""``quick-stream`` command line: one sub-command per job.

Sub-commands live in their own modules and register an ``add_parser`` and a
``run(args) -> int`` pair here. They are imported when the parser is built, not with
this package, so ``quick-stream router`` and ``up`` start without the evaluation and
benchmark modules (and SciPy's) behind the other commands. The cli is the top layer: the
services never import it (their shared flags are :mod:`quick_stream.stream.argtypes` and
:mod:`quick_stream.io.stabilizer_flags`).

Conventions every sub-command keeps (tests/unit/test_cli_help.py walks the parsers): help
is plain text (a module docstring becomes a description through
:func:`~quick_stream.stream.argtypes.plain_text`), every option has help that shows its
default; ``--json FILE`` (``-``: standard output, :mod:`.jsonout`); outputs are never
overwritten silently (default names numbered, named files refused without ``--force``:
:func:`~quick_stream.stream.argtypes.claim_outputs`), and every output path is checked before
any work; progress goes to stderr (:mod:`.progress`).
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys
from types import ModuleType

from ..stream.argtypes import check_outputs, claim_outputs
from ..stream.heap import keep_freed_buffers

COMMANDS = ("stabilize", "settings", "evaluate", "motion", "bench", "recover", "rerun", "recording-stats", "router", "up", "acl")


ALIASES = {"config": "settings"}


def command(name: str) -> ModuleType:
    """The module of sub-command ``name`` or of its alias (``<name>_cmd``, dashes as underscores)."""
    name = ALIASES.get(name, name)
    return importlib.import_module(f"{__name__}.{name.replace('-', '_')}_cmd")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="quick-stream",
        description="QuICK 3D video stabilization for RGB-D cameras. 'quick-stream COMMAND -h' describes "
                    "a command; the services run as quick-stream-capture, -flow, -motion, -render and -recorder "
                    "(or python -m quick_stream.services.NAME).",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        command(name).add_parser(sub)
    return parser


def _chosen_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The innermost sub-command's parser that ``args`` came through (``bench pipeline``: the pipeline's)."""
    while True:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        chosen = getattr(args, subs[0].dest, None) if subs else None
        if chosen not in (subs[0].choices if subs else {}):
            return parser
        parser = subs[0].choices[chosen]


def bench_installed() -> bool:
    """Whether the benchmarks are here: a source checkout's install has them, the wheel leaves them out
    (pyproject.toml's package list: the product installs what a user runs)."""
    return importlib.util.find_spec("quick_stream.bench") is not None


def main(argv: list[str] | None = None) -> int:
    words = [a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-")]
    if words[:1] == ["bench"] and not bench_installed():
        print("quick-stream bench: the benchmarks come with a source checkout (git clone, then pip install -e .), "
              "not with the installed product", file=sys.stderr)
        return 2
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # said by the sub-command's own parser, with its usage (not the top level's)
        _chosen_parser(parser, args).error(f"unrecognized arguments: {' '.join(extra)}")
    keep_freed_buffers()  # the in-process stages allocate frame-sized buffers as the services do
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        # before any work: no file overwritten silently, and every output path can be written (argtypes)
        claim_outputs(args, force=getattr(args, "force", False))
        check_outputs(args)
    except ValueError as e:
        name = " ".join(x for x in (args.command, getattr(args, "bench", None)) if x)
        print(f"quick-stream {name}: {e}", file=sys.stderr)
        return 2
    return command(args.command).run(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

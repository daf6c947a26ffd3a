"""``quick-stream settings show`` (or ``config show``): every stabilizer setting, as the commands and
services would run them.

Prints the whole settings tree as TOML (docs/settings.md): the defaults, or the settings of
the recording given with --source mcap:FILE, then --settings FILE, then the flags given, the
same way stabilize, up, rerun and every service resolve them. The output is a valid
settings file: --output FILE writes it for --settings (and for the deploy files' ConfigMap);
--json FILE (-: standard output) writes the tree as JSON. A bad file or value is an error
naming the file and the key.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..core.settings import settings_dict, settings_digest
from ..io.settings_file import settings_toml
from ..io.sources import SourceError, source_settings
from ..io.stabilizer_flags import add_stabilizer_args, given_flags, stabilizer_params
from ..stream import argtypes as at
from .jsonout import add_json, text_out, write_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("settings", aliases=["config"], help="show the stabilizer settings (a settings file)",
                       description=at.plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    c = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    s = c.add_parser("show", help="print every setting as TOML", description=at.plain_text(__doc__),
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--source", default=None, metavar="SPEC",
                   help="mcap:FILE: start from the settings that recording was made with (default: the defaults)")
    s.add_argument("--output", type=at.output_file("--output", (".toml",), "settings"), default=None,
                   metavar="FILE", help="also write the TOML to FILE, .toml (default: none)")
    add_json(s, "the settings")
    at.add_force(s)
    add_stabilizer_args(s)


def run(args: argparse.Namespace) -> int:
    try:
        recorded = source_settings(args.source) if args.source else None
        if args.source and recorded is None:
            raise ValueError(f"--source {args.source}: holds no settings (only an mcap:FILE recording made by "
                             "quick-stream does)")
        params = stabilizer_params(args, recorded=recorded)
    except (SourceError, ValueError) as e:
        print(f"quick-stream settings: {e}", file=sys.stderr)
        return 2
    origin = f"the settings of {args.source}" if recorded is not None else "the defaults"
    given = ", ".join(x for x in (f"--settings {args.settings}" if args.settings else "",
                                  " ".join(f"--{k.replace('_', '-')}" for k in given_flags(args))) if x)
    header = (f"quick-stream settings {settings_digest(params)}: {origin}" + (f", then {given}" if given else "")
              + "\nedit and pass with --settings FILE (docs/settings.md)")
    text = settings_toml(params, header)
    if args.output:
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        Path(args.output).write_text(text)
    if args.json:
        write_json(args.json, {"digest": settings_digest(params), "settings": settings_dict(params)}, default=None)
    if args.output:  # the file holds the text: only say where it went
        print(f"wrote {args.output}", file=sys.stderr)
    else:
        print(text, end="", file=text_out(args))
    return 0

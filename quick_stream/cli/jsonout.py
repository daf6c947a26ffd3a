"""``--json FILE`` the same way in every command: FILE gets the result as one JSON document,
``-`` puts it on standard output instead of the text report (which then goes to stderr, so
standard output holds nothing but the JSON)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable, TextIO

from ..stream import argtypes as at


def add_json(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--json", type=at.json_output("--json"), default=None, metavar="FILE",
                   help=f"also write {what} as JSON to FILE; '-': to standard output, the text report going to "
                   "stderr instead (default: no JSON)")


def text_out(args: argparse.Namespace) -> TextIO:
    """Where the text report goes: stderr when the JSON takes standard output."""
    return sys.stderr if getattr(args, "json", None) == "-" else sys.stdout


def write_json(dest: str, doc: Any, default: Callable[[Any], Any] | None = float) -> None:
    """``doc`` as JSON to ``dest`` (a file, or ``-``: standard output)."""
    text = json.dumps(doc, indent=1, default=default) + "\n"
    if dest == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    Path(dest).parent.mkdir(parents=True, exist_ok=True)
    Path(dest).write_text(text)

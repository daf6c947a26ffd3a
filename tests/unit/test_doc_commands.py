"""Every command line the README and docs/ show in a shell block is one the commands accept.

Each ``quick-stream ...`` (and ``quick-stream-<service> ...``) line of a ```sh block (continuations
joined, ``&&``/``|``/``;`` chains split, comments dropped) is parsed by the command's own argparse
parser: an unknown flag, a removed sub-command or a value its type refuses fails here. Parsing runs
nothing (no camera, no data, no output written); what the commands do is the other tests' business.
"""
from __future__ import annotations

import importlib
import re
import shlex

import pytest

from quick_stream.cli import build_parser
from tests.tools import REPO

BLOCK = re.compile(r"```(?:sh|bash|console)?\n(.*?)```", re.S)
SERVICES = ("capture", "flow", "motion", "render", "recorder")


def shown_commands(text: str) -> list[str]:
    out = []
    for block in BLOCK.findall(text):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip().removeprefix("$ ")
            for part in re.split(r"\s*(?:&&|\|\||;|\|)\s*", line):
                part = part.split(" #")[0].strip()
                if re.match(r"quick-stream(-\w+)? ", part + " "):
                    out.append(part)
    return out


DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SHOWN = [(p.relative_to(REPO).as_posix(), c) for p in DOCS for c in shown_commands(p.read_text())]


def test_the_docs_show_commands():
    assert len(SHOWN) >= 20 and any(doc == "README.md" for doc, _ in SHOWN)


@pytest.mark.parametrize("doc, command", SHOWN, ids=[f"{d}:{c[:60]}" for d, c in SHOWN])
def test_each_command_shown_parses(doc: str, command: str):
    argv = shlex.split(command)
    name = argv[0].removeprefix("quick-stream")
    if name:
        assert name[1:] in SERVICES, f"{doc}: {argv[0]} is no command"
        parser = importlib.import_module(f"quick_stream.services.{name[1:]}").build_parser()
    else:
        parser = build_parser()
    try:
        parser.parse_args(argv[1:])
    except SystemExit as e:
        raise AssertionError(f"{doc}: `{command}` is refused by its parser (exit {e.code})") from None


def test_a_wrong_flag_in_a_shown_command_is_caught():
    text = "```sh\nquick-stream stabilize --max-zoon 1.2\n```\n"
    (cmd,) = shown_commands(text)
    with pytest.raises(AssertionError, match="refused by its parser"):
        test_each_command_shown_parses("x.md", cmd)

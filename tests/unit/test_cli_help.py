"""Every parser's help, walked: plain text, every option with help that shows its default, one
``--json FILE`` convention, ``--force`` wherever a command writes files, service programs named as
installed, ``router -m`` as it behaves.

The parsers walked: ``quick-stream`` and every sub-command (``bench`` NAME too), and each
service's ``build_parser()`` (built without starting anything).
"""
from __future__ import annotations

import argparse
import importlib
import re
import tomllib
from pathlib import Path
from typing import Iterator

import pytest

from quick_stream.cli import build_parser, main
from quick_stream.stream.argtypes import RST_MARKUP, plain_text

REPO = Path(__file__).resolve().parents[2]
SERVICES = ("capture", "flow", "motion", "render", "recorder")
SHARED_GROUPS = ("zenoh", "stabilizer settings")  # the services' flags from stream/transport.py, stabilizer_flags.py
NO_VALUE = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._StoreConstAction,
            argparse._CountAction, argparse._HelpAction, argparse._VersionAction)


def walk(parser: argparse.ArgumentParser, name: str) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, p in action.choices.items():
                yield from walk(p, f"{name} {sub}")


COMMANDS = dict(walk(build_parser(), "quick-stream"))


def service_parser(service: str) -> argparse.ArgumentParser:
    return importlib.import_module(f"quick_stream.services.{service}").build_parser()


def options(parser: argparse.ArgumentParser) -> Iterator[argparse.Action]:
    for a in parser._actions:
        if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):
            yield a


def group_of(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    return next((g.title for g in parser._action_groups if action in g._group_actions), "")


def shows_default(action: argparse.Action) -> bool:
    """An option that takes a value says what happens without it; a positional or a switch need not."""
    if not action.option_strings or isinstance(action, NO_VALUE):
        return True
    return bool(re.search(r"\bdefault\b", action.help or "", re.I))


def label(action: argparse.Action) -> str:
    return "/".join(action.option_strings) or action.dest


def problems(name: str, parser: argparse.ArgumentParser, only_groups: tuple[str, ...] | None = None) -> list[str]:
    out = []
    for a in options(parser):
        if only_groups is not None and group_of(parser, a) not in only_groups:
            continue
        if not a.help:
            out.append(f"{name} {label(a)}: no help")
            continue
        if RST_MARKUP.search(a.help):
            out.append(f"{name} {label(a)}: RST markup in help: {a.help!r}")
        if not shows_default(a):
            out.append(f"{name} {label(a)}: help does not show the default ({a.default!r}): {a.help!r}")
    return out


@pytest.mark.parametrize("name", sorted(COMMANDS), ids=str)
def test_every_option_of_every_command_has_help_showing_its_default(name: str) -> None:
    assert not problems(name, COMMANDS[name]), "\n".join(problems(name, COMMANDS[name]))


@pytest.mark.parametrize("name", sorted(COMMANDS), ids=str)
def test_command_help_is_plain_text(name: str) -> None:
    parser = COMMANDS[name]
    text = parser.format_help()
    assert not RST_MARKUP.search(text), f"{name} -h shows RST markup:\n{text}"
    if name != "quick-stream":
        assert parser.description, f"{name} has no description"


@pytest.mark.parametrize("service", SERVICES)
def test_service_options_have_help_and_no_markup(service: str) -> None:
    """Every option has help without RST; the flags shared from transport.py and stabilizer_flags.py
    also show their defaults."""
    p = service_parser(service)
    bad = [x for x in problems(service, p) if "no help" in x or "RST" in x]
    bad += problems(service, p, only_groups=SHARED_GROUPS)
    assert not bad, "\n".join(bad)


# The services' descriptions (module docstrings) and their own options are set in services/*.py and
@pytest.mark.parametrize("service", SERVICES)
def test_service_help_is_plain_text_and_shows_every_default(service: str) -> None:
    p = service_parser(service)
    assert not RST_MARKUP.search(p.format_help())
    assert not problems(service, p)


@pytest.mark.parametrize("service", SERVICES)
def test_service_programs_are_the_installed_names(service: str) -> None:
    """The usage line names a command that exists: the console script of pyproject.toml, which runs
    the module that ``python -m quick_stream.services.NAME`` runs."""
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    p = service_parser(service)
    assert p.prog == f"quick-stream-{service}" and p.format_usage().startswith(f"usage: quick-stream-{service} ")
    assert scripts[p.prog] == f"quick_stream.services.{service}:main"


def test_json_is_one_convention_everywhere() -> None:
    """``--json FILE`` ('-': standard output) in every command that has one."""
    found = []
    for name, parser in COMMANDS.items():
        for a in options(parser):
            if "--json" in a.option_strings:
                found.append(name)
                assert getattr(a.type, "__name__", "") == "json_output" and a.metavar == "FILE", name
                assert "'-'" in a.help and "standard output" in a.help, name
    assert {"quick-stream motion", "quick-stream evaluate", "quick-stream recording-stats",
            "quick-stream bench pipeline", "quick-stream bench quality", "quick-stream bench speed"} <= set(found)


@pytest.mark.parametrize("name", sorted(COMMANDS), ids=str)
def test_commands_that_write_files_have_force(name: str) -> None:
    parser = COMMANDS[name]
    writes = [label(a) for a in options(parser) if getattr(a.type, "overwrites", False)]
    if writes:
        assert any("--force" in a.option_strings for a in options(parser)), f"{name} writes {writes}, no --force"


def test_router_mode_help_says_what_it_does(capsys: pytest.CaptureFixture) -> None:
    mode = next(a for a in options(COMMANDS["quick-stream router"]) if a.dest == "mode")
    assert mode.choices == ("router",) and "always router" in mode.help
    with pytest.raises(SystemExit) as e:
        main(["router", "-m", "peer"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "-m/--mode" in err and "'peer'" in err and "Traceback" not in err


def test_plain_text_unwraps_markup() -> None:
    doc = """``quick-stream recover``: see :class:`~quick_stream.io.recording.Recorder` and
    :mod:`quick_stream.io.recording`, `a link`_ and ``x``."""
    text = plain_text(doc)
    assert text == ("quick-stream recover: see Recorder and\nquick_stream.io.recording, a link and x.")
    assert not RST_MARKUP.search(text)

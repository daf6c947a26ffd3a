"""Named settings of ours for ``quick-stream bench quality``: stabilizer flags parsed exactly as
``quick-stream stabilize`` parses them (``--variant NAME='--flag value ...'``, ``--grid``)."""
from __future__ import annotations

import argparse
import re
import shlex
from dataclasses import dataclass

from ..core.params import StabilizerParams

GROUPS = ("se3", "sim3", "sa3", "ga3")
ENDS = ("identity", "smoothed")


class _RaisingParser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise ValueError(message)


@dataclass
class Variant:
    """A named setting of ours: the stabiliser flags and the StabilizerParams they give."""

    name: str
    argv: list[str]
    params: StabilizerParams
    flags: dict  # the stabiliser flags' values (their defaults, and those given)


def parse_settings(argv: list[str], name: str = "ours") -> Variant:
    """Stabiliser flags -> Variant, exactly as ``quick-stream stabilize`` parses them; ValueError if wrong."""
    from ..io.stabilizer_flags import FLAG_DEFAULTS, add_stabilizer_args, given_flags, stabilizer_params

    p = _RaisingParser(prog=name, add_help=False)
    add_stabilizer_args(p)
    args = p.parse_args(list(argv))
    return Variant(name, list(argv), stabilizer_params(args), {**FLAG_DEFAULTS, **given_flags(args)})


def default_settings() -> Variant:
    """Ours at the defaults: the stabiliser flags parsed from an empty argv."""
    return parse_settings([], "ours")


BORDERED = "bordered"
BORDERED_FLAGS = ("--max-zoom", "0", "--framing", "black")  # no crop budget, no zoom, no border fill


def bordered_variant() -> Variant:
    """Ours leaving black borders as most peers do (no crop budget, no zoom, no border fill): what a
    peer that shows borders is compared with like for like (its jitter is not charged for a crop)."""
    return parse_settings(list(BORDERED_FLAGS), BORDERED)


def parse_variant(text: str) -> Variant:
    """``NAME=--flag value ...`` (shell-quoted flags of ``quick-stream stabilize``) -> Variant."""
    name, sep, rest = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise ValueError(f"expected NAME='--flag value ...', got {text!r}")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+-]*", name) or name == "ours":
        raise ValueError(f"variant name {name!r}: use letters, digits and _ . + - (and not 'ours')")
    try:
        argv = shlex.split(rest)
    except ValueError as e:
        raise ValueError(f"variant {name}: {e}") from None
    try:
        return parse_settings(argv, name)
    except ValueError as e:
        raise ValueError(f"variant {name}: {e}") from None


def grid_variants() -> list[Variant]:
    """The former benchmark: every group x both end modes, and the paper's own path (no low-pass)."""
    out = [parse_settings(["--group", g, "--end", e], f"{g}-{e}") for g in GROUPS for e in ENDS]
    out.append(parse_settings(["--group", "se3", "--end", "identity", "--lowpass-sigma", "0"], "paper-path"))
    return out

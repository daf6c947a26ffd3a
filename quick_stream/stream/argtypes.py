"""argparse ``type=`` validators shared by every command and service (docs/reliability.md, "Bad input").

A bad value stops the program before any work starts, the way argparse reports its own
errors: ``argument --fps: must be a number > 0, got '0'`` and exit code 2. Numbers must be
finite (NaN and infinities are refused everywhere) and within the bound the flag needs.

Output paths are two-step. The ``type=`` here checks only what the text says (a video needs a
video suffix); whether the path can be written (no regular file in the way of its folder, not
an existing directory, a writable ancestor) is :func:`check_outputs`, called once the command
is about to run. Parsing must not depend on this host's file system: the deployment tests
parse the containers' commands, whose paths exist only inside the containers.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Callable, Iterable, TypeVar

from . import keys

T = TypeVar("T")

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v")  # cv2.VideoWriter opens these with mp4v


def checked(check: Callable[[str], T], name: str | None = None) -> Callable[[str], T]:
    """An argparse type from a validator that raises ValueError: its message becomes argparse's error."""
    def parse(text: str) -> T:
        try:
            return check(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    parse.__name__ = name or check.__name__
    return parse


def _bounds(lo: float | None, hi: float | None, lo_open: bool) -> str:
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    return f"<= {hi:g}" if hi is not None else ""


def int_in(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """Type: an integer in [lo, hi] (either bound may be None)."""
    what = f"an integer {_bounds(lo, hi, False)}"

    def check(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:
            raise ValueError(f"must be {what}, got {text!r}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ValueError(f"must be {what}, got {text!r}")
        return value

    return checked(check, "int")


def float_in(lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> Callable[[str], float]:
    """Type: a finite number in [lo, hi], or (lo, hi] with ``lo_open``."""
    what = f"a finite number {_bounds(lo, hi, lo_open)}"

    def check(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"must be {what}, got {text!r}") from None
        low_ok = lo is None or (value > lo if lo_open else value >= lo)
        if not (math.isfinite(value) and low_ok and (hi is None or value <= hi)):
            raise ValueError(f"must be {what}, got {text!r}")
        return value

    return checked(check, "float")


positive_int = int_in(1)
nonneg_int = int_in(0)
positive_float = float_in(0.0, lo_open=True)
nonneg_float = float_in(0.0)
quality = int_in(1, 100)  # JPEG quality, as the wire accepts it
port = int_in(0, 65535)
stream_id = checked(keys.check_stream, "stream_id")


def _service_names(text: str) -> str:
    for name in filter(None, (s.strip() for s in text.split(","))):
        keys.check_service(name)
    return text


service_names = checked(_service_names, "service_names")  # "a,b,c" (empty: none)


def choice_list(choices: Iterable[str]) -> Callable[[str], tuple[str, ...]]:
    """Type: a comma-separated, non-empty list of ``choices``."""
    allowed = tuple(choices)

    def check(text: str) -> tuple[str, ...]:
        items = tuple(s.strip() for s in text.split(",") if s.strip())
        bad = [s for s in items if s not in allowed]
        if bad or not items:
            raise ValueError(f"expected a comma-separated list of {', '.join(allowed)}, got {text!r}")
        return items

    return checked(check, "choice_list")


def _rates(text: str) -> list[float | None]:
    number = float_in(0.0, lo_open=True)
    out: list[float | None] = []
    for item in text.split(","):
        item = item.strip()
        try:
            out.append(None if item == "fast" else number(item))
        except argparse.ArgumentTypeError:
            raise ValueError(f"each rate must be 'fast' or a finite number > 0 (frames/s), got {item!r}") from None
    return out


def _frame_size(text: str) -> str:
    w, sep, h = text.strip().lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and 16 <= int(w) <= 8192 and 16 <= int(h) <= 8192):
        raise ValueError(f"must be WIDTHxHEIGHT, each 16-8192, got {text!r}")
    return f"{int(w)}x{int(h)}"


frame_size = checked(_frame_size, "frame_size")  # "640x480"
rates = checked(_rates, "rates")  # "30,60,fast": frames/s per run, None = as fast as possible


# --- output paths -------------------------------------------------------------------------------

class OutputPath(str):
    """A path the command will write (a file, or a folder with ``directory``), and the flag that
    named it; :func:`check_outputs` finds these among the parsed arguments."""

    flag: str
    directory: bool

    def __new__(cls, text: str, flag: str = "", directory: bool = False) -> "OutputPath":
        self = super().__new__(cls, text)
        self.flag, self.directory = flag, directory
        return self


def output_file(flag: str, suffixes: Iterable[str] = (), what: str = "file") -> Callable[[str], str]:
    """Type: a file to write (``""``: none), with one of ``suffixes`` if given."""
    allowed = tuple(suffixes)

    def check(text: str) -> str:
        if not text:
            return text
        if allowed and Path(text).suffix.lower() not in allowed:
            raise ValueError(f"{text!r} is not a {what} name (use {', '.join(allowed)})")
        return OutputPath(text, flag)

    return checked(check, "output_file")


def image_file(flag: str) -> Callable[[str], str]:
    """Type: an image file to write (``""``: none), in a format OpenCV can write."""
    def check(text: str) -> str:
        import cv2

        if text and not cv2.haveImageWriter(text):
            raise ValueError(f"{text!r}: OpenCV cannot write images with suffix {Path(text).suffix!r} (use .png)")
        return OutputPath(text, flag) if text else text

    return checked(check, "image_file")


def output_dir(flag: str) -> Callable[[str], str]:
    """Type: a folder to write into (``""``: none); it may not exist yet."""
    def check(text: str) -> str:
        return OutputPath(text, flag, directory=True) if text else text

    return checked(check, "output_dir")


def _existing_ancestor(path: Path) -> Path:
    for p in (path, *path.parents):
        if p.exists():
            return p
    return Path(".")


def check_output(value: OutputPath) -> None:
    """ValueError naming the flag when ``value`` cannot be written here."""
    path = Path(value)
    where = f"{value.flag} {value}"
    if value.directory and path.exists() and not path.is_dir():
        raise ValueError(f"{where}: exists and is not a directory")
    if not value.directory and path.is_dir():
        raise ValueError(f"{where}: is a directory (give a file name)")
    folder = path if value.directory else path.parent
    base = _existing_ancestor(folder)
    if not base.is_dir():
        raise ValueError(f"{where}: cannot create folder {folder}: {base} is a file, not a directory")
    if not os.access(base, os.W_OK | os.X_OK):
        raise ValueError(f"{where}: {base} is not writable")
    if path.exists() and not os.access(path, os.W_OK):
        raise ValueError(f"{where}: not writable")


def check_outputs(args: argparse.Namespace) -> None:
    """Check every output path among the parsed arguments (see :func:`check_output`)."""
    for value in vars(args).values():
        if isinstance(value, OutputPath):
            check_output(value)

"""argparse ``type=`` validators shared by every command and service (docs/reliability.md, "Bad input").

A bad value stops the program before any work starts, the way argparse reports its own
errors: ``argument --fps: must be a number > 0, got '0'`` and exit code 2. Numbers must be
finite (NaN and infinities are refused everywhere) and within the bound the flag needs.

Output paths are two-step. The ``type=`` here checks only what the text says (a video needs a
video suffix); whether the path can be written (no regular file in the way of its folder, not
an existing directory, a folder a file can be created in: tried, not guessed from permission
bits) is :func:`check_outputs`, called once the command is about to run. Parsing must not
depend on this host's file system: the deployment tests parse the containers' commands, whose
paths exist only inside the containers. The ``quick-stream`` commands also never overwrite a
file silently (:func:`claim_outputs`): a default output name is numbered like the recordings
(``stabilized-1.mp4``), a named file that exists is refused unless ``--force``.

Help texts are plain text (:func:`plain_text` turns a module docstring into a description).
"""
from __future__ import annotations

import argparse
import inspect
import math
import os
import re
import tempfile
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


# --- help texts ---------------------------------------------------------------------------------

_ROLE = re.compile(r":[a-z]+(?::[a-z]+)?:`(~?)([^`<]*?)\s*(?:<[^>]*>)?`")  # :class:`x`, :func:`~a.b`
_LITERAL = re.compile(r"``(.+?)``", re.S)
_LINK = re.compile(r"`([^`]+?)`_{0,2}")
RST_MARKUP = re.compile(r"``|:[a-z]+(?::[a-z]+)?:`|`[^`]+`_|\.\. [a-z]+::")  # what plain help must not hold


def plain_text(doc: str | None) -> str:
    """A docstring as plain help text: reStructuredText roles and literals unwrapped
    (``:class:`~a.B``` -> ``B``, ````x```` -> ``x``), indentation removed."""
    if not doc:
        return ""
    text = _ROLE.sub(lambda m: m.group(2).rsplit(".", 1)[-1] if m.group(1) else m.group(2), doc)
    text = _LITERAL.sub(r"\1", text)
    text = _LINK.sub(r"\1", text)
    return inspect.cleandoc(text)


# --- output paths -------------------------------------------------------------------------------

class OutputPath(str):
    """A path the command will write (a file, or a folder with ``directory``), and the flag that
    named it; :func:`check_outputs` finds these among the parsed arguments. ``numbered``: a
    default name, given the next free number instead of overwriting (:func:`claim_outputs`);
    ``files``: for a folder, the glob of the files the command writes in it (refused where they
    exist, unless ``--force``)."""

    flag: str
    directory: bool
    numbered: bool
    files: str

    def __new__(cls, text: str, flag: str = "", directory: bool = False, numbered: bool = False,
                files: str = "") -> "OutputPath":
        self = super().__new__(cls, text)
        self.flag, self.directory, self.numbered, self.files = flag, directory, numbered, files
        return self

    def with_text(self, text: str) -> "OutputPath":
        return OutputPath(text, self.flag, self.directory, self.numbered, self.files)


def default_name(text: str) -> OutputPath:
    """A ``default=`` for an output flag: when it is used, the file gets the next free number
    (``out/stabilized.mp4``, then ``out/stabilized-1.mp4``, ...) instead of overwriting."""
    return OutputPath(text, numbered=True)


def _overwrites(parse: Callable[[str], T]) -> Callable[[str], T]:
    parse.overwrites = True  # type: ignore[attr-defined]  # the command needs --force (tests check it has one)
    return parse


def output_file(flag: str, suffixes: Iterable[str] = (), what: str = "file") -> Callable[[str], str]:
    """Type: a file to write (``""``: none), with one of ``suffixes`` if given."""
    allowed = tuple(suffixes)

    def check(text: str) -> str:
        if not text:
            return text
        if allowed and Path(text).suffix.lower() not in allowed:
            raise ValueError(f"{text!r} is not a {what} name (use {', '.join(allowed)})")
        return OutputPath(text, flag, numbered=getattr(text, "numbered", False))

    return _overwrites(checked(check, "output_file"))


def json_output(flag: str = "--json") -> Callable[[str], str]:
    """Type: where ``--json`` goes: a file to write, or ``-`` for standard output."""
    file = output_file(flag)

    def parse(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError("expected a file name, or - for standard output")
        return "-" if text == "-" else file(text)

    parse.__name__ = "json_output"
    return _overwrites(parse)


def image_file(flag: str) -> Callable[[str], str]:
    """Type: an image file to write (``""``: none), in a format OpenCV can write."""
    def check(text: str) -> str:
        import cv2

        if text and not cv2.haveImageWriter(text):
            raise ValueError(f"{text!r}: OpenCV cannot write images with suffix {Path(text).suffix!r} (use .png)")
        return OutputPath(text, flag, numbered=getattr(text, "numbered", False)) if text else text

    return _overwrites(checked(check, "image_file"))


def output_dir(flag: str, files: str = "") -> Callable[[str], str]:
    """Type: a folder to write into (``""``: none); it may not exist yet. ``files``: the glob of
    the files written in it (say ``*.png``), which must not be there already unless ``--force``."""
    def check(text: str) -> str:
        return OutputPath(text, flag, directory=True, files=files) if text else text

    parse = checked(check, "output_dir")
    return _overwrites(parse) if files else parse


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
    _try_writing(value, path, base, where)


def _try_writing(value: OutputPath, path: Path, base: Path, where: str) -> None:
    """Permission bits do not tell (root passes every access check, /proc and /sys refuse new files
    anyway): create and remove a file where the output will go, open an existing file for appending."""
    try:
        if not value.directory and path.is_file():
            with open(path, "ab"):
                pass
            return
        with tempfile.TemporaryFile(dir=base, prefix=".quick-stream-probe-"):
            pass
    except OSError as e:
        what = f"cannot write {path}" if not value.directory and path.exists() else f"cannot create files in {base}"
        raise ValueError(f"{where}: {what} ({e.strerror or e})") from None


def check_outputs(args: argparse.Namespace) -> None:
    """Check every output path among the parsed arguments (see :func:`check_output`)."""
    for value in vars(args).values():
        if isinstance(value, OutputPath):
            check_output(value)


def numbered_path(path: str | os.PathLike, n: int) -> str:
    """``path`` for n = 0, else ``<stem>-<n><suffix>`` (``out/stabilized-2.mp4``)."""
    p = Path(path)
    return str(p) if n == 0 else str(p.with_name(f"{p.stem}-{n}{p.suffix}"))


def first_free(paths: Iterable[str | os.PathLike]) -> int:
    """The smallest n >= 0 for which no ``numbered_path(p, n)`` exists: outputs of one run share it."""
    paths = list(paths)
    n = 0
    while any(os.path.lexists(numbered_path(p, n)) for p in paths):
        n += 1
    return n


def claim_outputs(args: argparse.Namespace, force: bool = False) -> None:
    """Never overwrite silently: the outputs left at their default names (``default_name``) all get
    the first number free for every one of them (``stabilized-1.mp4``, ``report-1.json``, ...;
    ``args`` is updated); a file named on the command line that exists, or a folder that already
    holds the files the command writes in it, is a ValueError naming the flag unless ``force``."""
    outputs = {dest: v for dest, v in vars(args).items() if isinstance(v, OutputPath)}
    defaults = {dest: v for dest, v in outputs.items() if v.numbered and not v.directory}
    n = first_free(defaults.values())
    for dest, v in defaults.items():
        setattr(args, dest, v.with_text(numbered_path(v, n)))
    if force:
        return
    for v in outputs.values():
        path = Path(v)
        if v.numbered:
            continue
        if not v.directory and path.is_file():
            raise ValueError(f"{v.flag} {v}: exists (give another name, or --force to overwrite it)")
        if v.directory and v.files and path.is_dir() and next(path.glob(v.files), None) is not None:
            raise ValueError(f"{v.flag} {v}: already holds {v.files} files (give another folder, or --force to "
                             f"overwrite them)")


FORCE_HELP = "overwrite output files that exist (default: refuse, naming the file)"


def add_force(p: argparse.ArgumentParser) -> None:
    """``--force``, for a command that writes files (:func:`claim_outputs`)."""
    p.add_argument("--force", action="store_true", help=FORCE_HELP)

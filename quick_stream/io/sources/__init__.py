"""Frame sources and the ``open_source`` spec parser.

Specs: ``synthetic`` or ``synthetic:key=value,...`` (the embedded default, no
data needed) and ``tum:PATH`` or ``tum:PATH,key=value,...`` (a TUM-layout
folder) and ``mcap:FILE`` or ``mcap:FILE,stream=ID`` (replay of a recording's
``frame`` messages) and ``depthai[:DEVICE][,key=value,...]`` (a live OAK camera, or
``fake=...`` for the scripted stand-in; :mod:`~quick_stream.io.sources.oak`).
"""
from __future__ import annotations

import os
import re
from typing import TYPE_CHECKING

from .base import FrameOrGap, Source, SourceError

if TYPE_CHECKING:
    from ...core.params import StabilizerParams

SOURCE_KINDS = ("synthetic", "tum", "mcap", "depthai")
_OPTION = re.compile(r"[A-Za-z_][A-Za-z0-9_]*=.*")  # a key=value option of a tum: or mcap: spec


def _split_options(text: str) -> tuple[list[str], dict[str, str]]:
    positional: list[str] = []
    options: dict[str, str] = {}
    for part in filter(None, text.split(",")):
        if "=" in part:
            k, _, v = part.partition("=")
            options[k.strip()] = v.strip()
        else:
            positional.append(part)
    return positional, options


def _path_and_options(rest: str, extra: dict[str, str], usage: str) -> tuple[str, dict[str, str]]:
    """``PATH[,key=value...]``: (path, options with ``extra`` on top); SourceError ``usage`` without a
    path. The path may contain commas (the folders the benchmarks make do): the options are the
    longest run of ``key=value`` items at the end, and a ``rest`` that names an existing file or
    folder is a path whole."""
    path, opt_text = rest, ""
    if not os.path.exists(rest):
        parts = rest.split(",")
        i = len(parts)
        while i > 1 and _OPTION.fullmatch(parts[i - 1].strip()):
            i -= 1
        path, opt_text = ",".join(parts[:i]), ",".join(parts[i:])
    _, options = _split_options(opt_text)
    options.update(extra)
    if not path:
        raise SourceError(usage)
    return path, options


def open_source(spec: str, **overrides: object) -> Source:
    """Open a source from its spec string; ``overrides`` are extra options (CLI flags).

    Raises :class:`SourceError` with the spec in the message when the spec or an
    option is wrong or the source cannot be opened.
    """
    kind, _, rest = spec.partition(":")
    kind = kind.strip().lower()
    opts_extra = {k: str(v) for k, v in overrides.items() if v is not None}
    try:
        if kind == "synthetic":
            from .synthetic import SyntheticSource

            _, options = _split_options(rest)
            options.update(opts_extra)
            return SyntheticSource.from_spec(options)
        if kind == "depthai":
            from .oak import open_oak

            positional, options = _split_options(rest)
            options.update(opts_extra)
            if len(positional) > 1:
                raise SourceError(f"depthai source takes one device id, got {positional}")
            return open_oak(positional[0] if positional else "", options)
        if kind == "tum":
            from .tum import TumSource

            return TumSource.from_spec(*_path_and_options(rest, opts_extra, "tum source needs a folder: tum:PATH"))
        if kind == "mcap":
            from .mcap_replay import McapSource

            return McapSource.from_spec(*_path_and_options(
                rest, opts_extra, "mcap source needs a recording: mcap:FILE[,stream=ID]"))
    except SourceError:
        raise
    except ImportError as e:  # an optional extra is missing; the message names it
        raise SourceError(f"source {spec!r}: {e}") from None
    except (ValueError, OSError) as e:
        raise SourceError(f"source {spec!r}: {e}") from None
    raise SourceError(f"unknown source kind {kind!r} in {spec!r}; expected one of {', '.join(SOURCE_KINDS)}")


def check_source(spec: str) -> None:
    """SourceError (as :func:`open_source` raises it) if ``spec`` cannot be opened. A live camera
    (``depthai`` without ``fake``) is not opened (the process that will use it must be the one to
    open it): its options are checked and the device must be listed as connected."""
    kind, _, rest = spec.partition(":")
    if kind.strip().lower() == "depthai":
        positional, options = _split_options(rest)
        if not options.get("fake"):
            from .oak_options import oak_settings

            if len(positional) > 1:
                raise SourceError(f"depthai source takes one device id, got {positional}")
            try:
                oak_settings(options)
            except ValueError as e:
                raise SourceError(f"source {spec!r}: {e}") from None
            _check_oak_connected(spec, positional[0] if positional else "")
            return
    open_source(spec)


def _check_oak_connected(spec: str, device: str) -> None:
    """SourceError unless an OAK device (``device``, if named) is listed as connected (~1 s)."""
    from .oak_device import list_devices

    try:
        found = list_devices()
    except ImportError as e:
        raise SourceError(f"source {spec!r}: {e}") from None
    except Exception as e:  # noqa: BLE001 - depthai's own errors (USB access and the like)
        raise SourceError(f"source {spec!r}: cannot list OAK devices: {type(e).__name__}: {e}") from None
    if not found:
        raise SourceError(f"source {spec!r}: no OAK device found (check the USB cable, the udev rule, or Docker's "
                          "/dev/bus/usb mapping; `quick-stream-capture --list-devices` lists what is connected)")
    if device and device not in {d["id"] for d in found}:
        raise SourceError(f"source {spec!r}: no OAK device {device!r}; connected: "
                          + ", ".join(f"{d['id']} ({d['name']})" for d in found))


__all__ = ["FrameOrGap", "SOURCE_KINDS", "Source", "SourceError", "check_source", "open_source"]


def source_settings(spec: str) -> "StabilizerParams | None":
    """The stabilizer settings a source was made with: a recording's (``mcap:FILE``, its settings
    record), else None. SourceError naming the file when the recording or its record is unreadable."""
    kind, _, rest = spec.partition(":")
    if kind.strip().lower() != "mcap":
        return None
    from ..recording import RecordingError
    from ..settings_file import recording_settings

    path, _ = _path_and_options(rest, {}, "mcap source needs a recording: mcap:FILE[,stream=ID]")
    try:
        return recording_settings(path)
    except RecordingError as e:
        raise SourceError(str(e)) from None

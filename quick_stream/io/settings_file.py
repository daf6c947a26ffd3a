"""Settings files (TOML or JSON) and the settings record of a recording.

* :func:`load_settings_file` reads a ``--settings FILE`` (``.toml``, or ``.json``) into the settings
  tree, laid over a base (docs/settings.md): the file holds only what it changes.
* :func:`settings_toml` writes the whole tree as TOML (``quick-stream settings show``; the file
  ``quick-stream up`` hands every service).
* Every recording holds the settings it was made with in one MCAP metadata record named
  :data:`RECORD_NAME` (:func:`settings_record`); :func:`recorded_settings` reads it back, from an
  intact file through its index and from a footer-less one by streaming.
"""
from __future__ import annotations

import json
import math
import os
import tomllib
from pathlib import Path
from typing import Any

from mcap.records import Message, Metadata
from mcap.stream_reader import StreamReader

from ..core.settings import SettingsError, settings_dict, settings_digest, settings_from_dict
from ..core.params import StabilizerParams
from .recording import RecordingError, describe_damage, open_recording

RECORD_NAME = "quick-stream.settings"
RECORD_VERSION = "1"
SUFFIXES = (".toml", ".json")


def read_settings_file(path: str | os.PathLike) -> dict[str, Any]:
    """The plain data of a settings file; SettingsError naming the file when it cannot be read."""
    path = Path(path)
    if path.suffix not in SUFFIXES:
        raise SettingsError(f"{path}: a settings file is .toml or .json, got {path.suffix or 'no suffix'!r}")
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise SettingsError(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise SettingsError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    try:
        data = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SettingsError(f"{path}: not valid TOML: {e}") from None
    except json.JSONDecodeError as e:
        raise SettingsError(f"{path}: not valid JSON: {e.msg} (line {e.lineno}, column {e.colno})") from None
    if not isinstance(data, dict):
        raise SettingsError(f"{path}: expected a table of settings, got {type(data).__name__}")
    return data


def load_settings_file(path: str | os.PathLike, base: StabilizerParams | None = None) -> StabilizerParams:
    """The settings of ``path`` laid over ``base``; SettingsError naming the file and the key."""
    data = read_settings_file(path)
    try:
        return settings_from_dict(data, base)
    except SettingsError as e:
        raise SettingsError(f"{path}: {e}") from None


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)  # the shortest text that reads back as the same float
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string: the same escapes
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {v!r}")


def settings_toml(params: StabilizerParams, header: str = "") -> str:
    """Every setting as TOML; reads back (:func:`load_settings_file`) as the same tree, bit for bit."""
    lines = [f"# {h}" for h in header.splitlines()] if header else []

    def table(data: dict[str, Any], path: list[str]) -> None:
        if path:
            lines.extend(["", f"[{'.'.join(path)}]"])
        for k, v in data.items():
            if not isinstance(v, dict):
                lines.append(f"{k} = {_toml_value(v)}")
        for k, v in data.items():
            if isinstance(v, dict):
                table(v, path + [k])

    table(settings_dict(params), [])
    return "\n".join(lines).lstrip("\n") + "\n"


def settings_record(params: StabilizerParams) -> dict[str, str]:
    """The metadata record's data: the settings as JSON, their digest and the record's version."""
    return {"settings": json.dumps(settings_dict(params), sort_keys=True), "digest": settings_digest(params),
            "version": RECORD_VERSION}


def _parse_record(path: Path, data: dict[str, str]) -> dict[str, Any]:
    if data.get("version") != RECORD_VERSION:
        raise RecordingError(f"{path}: settings record version {data.get('version')!r}, this reader knows "
                             f"{RECORD_VERSION!r}")
    try:
        settings = json.loads(data["settings"])
    except (KeyError, json.JSONDecodeError) as e:
        raise RecordingError(f"{path}: settings record is damaged ({e})") from None
    if not isinstance(settings, dict):
        raise RecordingError(f"{path}: settings record is damaged (not a table)")
    return settings


def recorded_settings(path: str | os.PathLike) -> dict[str, Any] | None:
    """The plain settings data of the recording ``path`` (its first settings record), or None when it
    holds none (made before recordings held settings); RecordingError if the file cannot be read.
    The recorder writes the record at the start of every file, so reading stops at the first message."""
    path = Path(path)
    try:
        with open_recording(path) as f:
            try:
                for record in StreamReader(f, record_size_limit=max(f.size, 1)).records:
                    if isinstance(record, Metadata) and record.name == RECORD_NAME:
                        return _parse_record(path, dict(record.metadata))
                    if isinstance(record, Message):  # written before any message: there is none
                        return None
            except RecordingError:
                raise
            except Exception as e:  # noqa: BLE001 - a damaged record raises assorted errors (describe_damage)
                raise RecordingError(f"{path}: damaged before its settings record (near byte {f.pos}): "
                                     f"{describe_damage(e)}") from None
    except OSError as e:
        raise RecordingError(f"{path}: cannot read: {e.strerror or e}") from None
    return None


def recording_settings(path: str | os.PathLike) -> StabilizerParams | None:
    """The settings tree a recording was made with (None: it holds none); RecordingError naming the
    file when the record is unreadable or refused."""
    data = recorded_settings(path)
    if data is None:
        return None
    try:
        return settings_from_dict(data)
    except SettingsError as e:
        raise RecordingError(f"{path}: its settings record: {e}") from None

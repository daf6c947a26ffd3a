"""The stabilizer's settings as plain data: one tree, read from and written to dicts.

:class:`~quick_stream.core.params.StabilizerParams` is the settings tree (flow, continuity,
motion, planner, warp, framing; each a dataclass of numbers, strings and flags). This module
turns it into plain data (TOML/JSON-ready dicts, the form a settings file and a recording's
metadata record hold) and back, strictly: an unknown key, a value of the wrong type or a value
the stage refuses is a :class:`SettingsError` naming the dotted key (``planner.keyframes.interval``).

A dict is laid *over* a base tree: keys it leaves out keep the base's values, so a settings file
may hold only what it changes. Files and recordings are :mod:`quick_stream.io.settings_file`;
flags are :mod:`quick_stream.io.stabilizer_flags`; docs/settings.md describes every key.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import typing
from typing import Any

from .lie import GROUPS
from .params import StabilizerParams

__all__ = ["SettingsError", "settings_dict", "settings_from_dict", "check_settings", "settings_digest"]


class SettingsError(ValueError):
    """A settings value is unknown, of the wrong type or refused; the message names its dotted key."""


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


def settings_dict(params: StabilizerParams) -> dict[str, Any]:
    """Every setting as nested plain data (dicts, lists, str, int, float, bool)."""
    return _plain(params)


def _convert(value: Any, hint: Any, where: str) -> Any:
    """``value`` (plain data) as a value of the field type ``hint``; SettingsError naming ``where``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise SettingsError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise SettingsError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_convert(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if hint is bool:
        if not isinstance(value, bool):
            raise SettingsError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SettingsError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingsError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise SettingsError(f"{where}: expected a string, got {value!r}")
        return value
    raise TypeError(f"{where}: settings field type {hint!r} has no plain-data form")  # a new field's type


def _overlay(base: Any, data: Any, where: str) -> Any:
    if not isinstance(data, dict):
        raise SettingsError(f"{where or 'settings'}: expected a table of settings, got {data!r}")
    hints = typing.get_type_hints(type(base))
    names = [f.name for f in dataclasses.fields(base)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        key = f"{where}.{unknown[0]}" if where else unknown[0]
        raise SettingsError(f"{key}: unknown setting (known here: {', '.join(names)})")
    changes = {}
    for name, value in data.items():
        key = f"{where}.{name}" if where else name
        current = getattr(base, name)
        changes[name] = (_overlay(current, value, key) if dataclasses.is_dataclass(current)
                         else _convert(value, hints[name], key))
    return dataclasses.replace(base, **changes) if changes else base


def settings_from_dict(data: dict[str, Any], base: StabilizerParams | None = None) -> StabilizerParams:
    """``data`` laid over ``base`` (default: every field's default), checked (:func:`check_settings`)."""
    try:
        params = _overlay(base if base is not None else StabilizerParams(), data, "")
    except SettingsError:
        raise
    except ValueError as e:  # StabilizerParams refuses motion and path groups that differ
        raise SettingsError(f"motion.group/planner.group: {e} (set both to the same group)") from None
    check_settings(params)
    return params


def check_settings(params: StabilizerParams) -> None:
    """Every stage's own check of its settings; SettingsError naming the section at fault."""
    checks = [("flow", params.flow.validate), ("continuity", params.continuity.validate),
              ("motion", params.motion.validate), ("planner", params.planner.validate),
              ("planner.path.weights",
               lambda: params.planner.path.weight_vector(GROUPS[params.planner.group].dim)),
              ("warp", params.warp.validate), ("framing", params.framing.validate)]
    if params.motion.group != params.planner.group:
        raise SettingsError(f"motion.group {params.motion.group!r} and planner.group {params.planner.group!r} "
                            "must be the same group")
    if not (math.isfinite(params.planner.lowpass_sigma) and params.planner.lowpass_sigma >= 0):
        raise SettingsError(f"planner.lowpass_sigma: must be a finite number >= 0 (frames), "
                            f"got {params.planner.lowpass_sigma!r}")
    for section, check in checks:
        try:
            check()
        except (ValueError, KeyError) as e:
            raise SettingsError(f"{section}: {e}") from None


def settings_digest(params: StabilizerParams) -> str:
    """A short fingerprint of every setting (12 hex digits): equal settings, equal digests."""
    text = json.dumps(settings_dict(params), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:12]

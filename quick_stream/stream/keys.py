"""Zenoh key expressions: ``quick/@v1/<stream>/<stage>`` (docs/wire-format.md).

One stream per camera; every stage publishes under its stream's prefix, so
several streams share a deployment without seeing each other's data. Stream
ids are restricted to ``[A-Za-z0-9_-]`` (no ``/``, ``*``, ``$``, ``@``, ``#``,
``?``, which are key-expression syntax), 1-64 characters.
"""
from __future__ import annotations

import re

from .topology import LOSSLESS_KEYS

PREFIX = "quick/@v1"
STAGES = (*LOSSLESS_KEYS, "stats", "health")  # the pipeline's data keys (its table), then every service's own
_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")  # stream ids and service names


def _check_name(value: str, what: str) -> str:
    if not isinstance(value, str) or not _NAME.match(value):
        raise ValueError(f"{what} must be 1-64 characters of [A-Za-z0-9_-], got {value!r}")
    return value


def _check_stage(stage: str) -> str:
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    return stage


def check_stream(stream: str) -> str:
    """The stream id, or ValueError naming what is wrong with it."""
    return _check_name(stream, "stream id")


def key(stream: str, stage: str) -> str:
    """The key expression a stage of a stream publishes on, e.g. ``quick/@v1/cam0/motion``."""
    stage = _check_stage(stage)
    return f"{PREFIX}/{check_stream(stream)}/{stage}"


def all_streams(stage: str) -> str:
    """Key expression matching ``stage`` of every stream (``quick/@v1/*/<stage>``)."""
    return f"{PREFIX}/*/{_check_stage(stage)}"


def stream_keys(stream: str) -> str:
    """Key expression matching every stage of one stream (``quick/@v1/<stream>/*``)."""
    return f"{PREFIX}/{check_stream(stream)}/*"


def check_service(service: str) -> str:
    """The service name, or ValueError naming what is wrong with it (same rule as stream ids)."""
    return _check_name(service, "service name")


def health_key(stream: str, service: str) -> str:
    """Liveliness token key of a running service, ``quick/@v1/<stream>/health/<service>``."""
    return _service_key(stream, "health", service)


def cursor_key(stream: str, service: str = "*") -> str:
    """Queryable key where ``service`` answers with the newest seq per stage of the stream it has seen,
    ``quick/@v1/<stream>/cursor/<service>`` (``*`` service: every service's, for a query; ``*``
    stream: a queryable for every stream)."""
    s = "*" if stream == "*" else check_stream(stream)
    if service == "*":
        return f"{PREFIX}/{s}/cursor/*"
    return f"{PREFIX}/*/cursor/{check_service(service)}" if s == "*" else _service_key(stream, "cursor", service)


def _service_key(stream: str, kind: str, service: str) -> str:
    return f"{PREFIX}/{check_stream(stream)}/{kind}/{check_service(service)}"


def parse_health(key_expr: str) -> tuple[str, str]:
    """(stream, service) of a liveliness token key; ValueError if it is not one."""
    parts = str(key_expr).split("/")
    if len(parts) != 5 or "/".join(parts[:2]) != PREFIX or parts[3] != "health" or not _NAME.match(parts[4]):
        raise ValueError(f"not a quick-stream health key ({PREFIX}/<stream>/health/<service>): {key_expr!r}")
    return check_stream(parts[2]), parts[4]


def parse(key_expr: str) -> tuple[str, str]:
    """(stream, stage) of a concrete key; ValueError if it is not one of ours."""
    parts = str(key_expr).split("/")
    if len(parts) != 4 or "/".join(parts[:2]) != PREFIX or parts[3] not in STAGES:
        raise ValueError(f"not a quick-stream key ({PREFIX}/<stream>/<stage>): {key_expr!r}")
    return check_stream(parts[2]), parts[3]


def stage_of(topic: str) -> str | None:
    """The stage of a quick-stream key (a recording's topic), None for any other key."""
    try:
        return parse(topic)[1]
    except ValueError:
        return None

"""Zenoh key expressions: ``quick/@v1/<stream>/<stage>`` (issue 4; docs/wire-format.md).

One stream per camera; every stage publishes under its stream's prefix, so
several streams share a deployment without seeing each other's data. Stream
ids are restricted to ``[A-Za-z0-9_-]`` (no ``/``, ``*``, ``$``, ``@``, ``#``,
``?``, which are key-expression syntax), 1-64 characters.
"""
from __future__ import annotations

import re

PREFIX = "quick/@v1"
STAGES = ("frame", "flow", "motion", "correction", "stabilized", "stats", "health")
_STREAM = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_stream(stream: str) -> str:
    """The stream id, or ValueError naming what is wrong with it."""
    if not isinstance(stream, str) or not _STREAM.match(stream):
        raise ValueError(f"stream id must be 1-64 characters of [A-Za-z0-9_-], got {stream!r}")
    return stream


def key(stream: str, stage: str) -> str:
    """The key expression a stage of a stream publishes on, e.g. ``quick/@v1/cam0/motion``."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    return f"{PREFIX}/{check_stream(stream)}/{stage}"


def all_streams(stage: str) -> str:
    """Key expression matching ``stage`` of every stream (``quick/@v1/*/<stage>``)."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    return f"{PREFIX}/*/{stage}"


def stream_keys(stream: str) -> str:
    """Key expression matching every stage of one stream (``quick/@v1/<stream>/*``)."""
    return f"{PREFIX}/{check_stream(stream)}/*"


_SERVICE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_service(service: str) -> str:
    """The service name, or ValueError naming what is wrong with it (same rule as stream ids)."""
    if not isinstance(service, str) or not _SERVICE.match(service):
        raise ValueError(f"service name must be 1-64 characters of [A-Za-z0-9_-], got {service!r}")
    return service


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
    if len(parts) != 5 or "/".join(parts[:2]) != PREFIX or parts[3] != "health" or not _SERVICE.match(parts[4]):
        raise ValueError(f"not a quick-stream health key ({PREFIX}/<stream>/health/<service>): {key_expr!r}")
    return check_stream(parts[2]), parts[4]


def parse(key_expr: str) -> tuple[str, str]:
    """(stream, stage) of a concrete key; ValueError if it is not one of ours."""
    parts = str(key_expr).split("/")
    if len(parts) != 4 or "/".join(parts[:2]) != PREFIX or parts[3] not in STAGES:
        raise ValueError(f"not a quick-stream key ({PREFIX}/<stream>/<stage>): {key_expr!r}")
    return check_stream(parts[2]), parts[3]

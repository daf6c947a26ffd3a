"""The pipeline's shape in one table: each service's keys in and out, how they are delivered, what
history it reads and which cursor it takes over by (docs/architecture.md, docs/deployment.md,
"Delivery guarantees per key").

Everything that depends on the shape reads it from here: the key names (:mod:`.keys`), the lossless keys the runtime publishes
numbered and recovers (:mod:`.runtime`, :mod:`.inbox`), the access control's roles (:mod:`.acl`),
the receivers a capture waits for (:mod:`.capture`), ``quick-stream up``'s processes and their
order, the pipeline benchmark and the test harness. Adding a stage is a row here plus its service
module (docs/reading-guide.md, "How to add a stage").
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Service:
    """One process of a stream's pipeline."""

    name: str
    publishes: tuple[str, ...] = ()  # its keys, quick/@v1/<stream>/<key> (besides stats and health)
    reads: tuple[str, ...] = ()  # the keys it subscribes to
    history: tuple[str, ...] = ()  # the keys whose publishers' caches it queries (takeover, recovery)
    cursor: str | None = None  # the key a restarted one takes over after (the stream cursor it asks)
    serves_cursor: bool = False  # answers how far it got, per key it receives (a restarted one's question)
    asks_cursor: bool = False  # asks the stream cursor (besides taking over): a capture, before its end marker

    @property
    def asks(self) -> bool:
        """Asks the stream cursor: to take over after a restart, or (a capture) before its end marker."""
        return self.cursor is not None or self.asks_cursor


# every data key is lossless (numbered, in its publisher's recovery cache, with heartbeats): a receiver
# whose own link dropped a message fetches it back; only stats are sent plain
PIPELINE: tuple[Service, ...] = (
    Service("capture", publishes=("frame",), reads=("motion", "stabilized"), asks_cursor=True),
    Service("flow", publishes=("flow",), reads=("frame", "motion", "stabilized"), history=("frame",),
            cursor="flow", serves_cursor=True),
    Service("motion", publishes=("motion", "correction"), reads=("flow",), history=("flow",),
            cursor="correction", serves_cursor=True),
    Service("render", publishes=("stabilized",), reads=("frame", "correction"), history=("frame", "correction"),
            cursor="stabilized", serves_cursor=True),
    Service("recorder", reads=("frame", "flow", "motion", "correction", "stabilized", "stats"),
            history=("frame", "flow", "motion", "correction", "stabilized"), serves_cursor=True),
)

SERVICES: tuple[str, ...] = tuple(s.name for s in PIPELINE)  # in the order data flows
BY_NAME: dict[str, Service] = {s.name: s for s in PIPELINE}
LOSSLESS_KEYS: tuple[str, ...] = tuple(k for s in PIPELINE for k in s.publishes)  # every data key
SOURCE = PIPELINE[0].name  # the service that brings frames in
RECORDER = "recorder"  # receives every key, publishes none
STAGES: tuple[str, ...] = tuple(s.name for s in PIPELINE if s.publishes and s.name != SOURCE)  # flow, motion, render
START_ORDER: tuple[str, ...] = (RECORDER, *STAGES, SOURCE)  # receivers up before the frames come
assert set(START_ORDER) == set(SERVICES) and not BY_NAME[RECORDER].publishes


def upstream(key: str) -> tuple[str, ...]:
    """The services ``key`` is computed through, from the source's frames on, in the order data flows:
    its publisher and, through the keys each reads history of (its inputs), theirs (the source not
    included). What a stage's progress needs up (the capture's and flow's shedding limits)."""
    publisher = {k: s for s in PIPELINE for k in s.publishes}
    seen: set[str] = set()
    todo = [key]
    while todo:
        s = publisher[todo.pop()]
        if s.name != SOURCE and s.name not in seen:
            seen.add(s.name)
            todo += list(s.history)
    return tuple(n for n in SERVICES if n in seen)


def receivers(key: str) -> tuple[str, ...]:
    """The services that subscribe to ``key`` (the capture waits for the frame's receivers)."""
    return tuple(s.name for s in PIPELINE if key in s.reads)


"""MCAP recording: every stage's messages on their own channels, flushed often, recoverable.

* :class:`Recorder` writes msgpack channels (exact replay; message encoding
  ``msgpack``, no schema) and any other channel a caller registers (e.g. JSON
  with a JSON schema for viewers). The MCAP writer keeps the open chunk in
  memory, so :meth:`Recorder.write` closes it (``Writer.flush``) whenever
  ``flush_s`` seconds have passed: a killed process loses at most about that
  long (transport-facts.md: without flushing, small messages were all lost).
* :func:`recover` repairs a file left without a footer (a writer killed with
  SIGKILL): it stream-reads records up to the first damaged one and rewrites
  schemas, channels and messages into a new, indexed file.
* :func:`read_messages` iterates a recording in log-time order, through the
  index when there is one and by streaming when there is not.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

PROFILE = "quick-stream"


def fresh_path(path: str | os.PathLike) -> Path:
    """``path``, or ``<stem>-1<suffix>``, ``-2``, ... if it exists: a restarted recorder never
    overwrites the file its predecessor left (``quick-stream recover`` repairs that one)."""
    base = Path(path)
    p, n = base, 0
    while p.exists():
        n += 1
        p = base.with_name(f"{base.stem}-{n}{base.suffix}")
    return p


class RecordingError(RuntimeError):
    """A recording cannot be read or repaired; the message names the file and the problem."""


class Recorder:
    """One MCAP file; not thread-safe (one recorder per process)."""

    def __init__(self, path: str | os.PathLike, flush_s: float = 1.0, chunk_size: int = 1 << 20,
                 compression: str = "none") -> None:
        comp = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}
        if compression not in comp:
            raise ValueError(f"recording compression must be one of {sorted(comp)}, got {compression!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp[compression])
        self._writer.start(profile=PROFILE, library="quick-stream")
        self._channels: dict[str, int] = {}
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._seq: dict[str, int] = {}
        self.flush_s = flush_s
        self._last_flush = time.monotonic()
        self.messages = 0
        self.closed = False

    def channel(self, topic: str, encoding: str = "msgpack", schema_name: str = "", schema: bytes = b"",
                schema_encoding: str = "", metadata: dict[str, str] | None = None) -> int:
        """Register (once) the channel for ``topic``; returns its id."""
        if topic in self._channels:
            return self._channels[topic]
        schema_id = 0
        if schema_name:
            key = (schema_name, schema_encoding, schema)
            if key not in self._schemas:
                self._schemas[key] = self._writer.register_schema(schema_name, schema_encoding, schema)
            schema_id = self._schemas[key]
        cid = self._writer.register_channel(topic, encoding, schema_id, metadata or {})
        self._channels[topic] = cid
        self._seq[topic] = 0
        return cid

    def write(self, topic: str, data: bytes, log_time_ns: int | None = None,
              publish_time_ns: int | None = None) -> None:
        """Log ``data`` on ``topic`` (registered as msgpack if new); flush if ``flush_s`` has passed."""
        if self.closed:
            raise RecordingError(f"{self.path}: recorder is closed")
        cid = self._channels.get(topic)
        if cid is None:
            cid = self.channel(topic)
        now = time.time_ns()
        log_time = now if log_time_ns is None else int(log_time_ns)
        self._writer.add_message(cid, log_time, bytes(data), now if publish_time_ns is None else int(publish_time_ns),
                                 self._seq[topic])
        self._seq[topic] += 1
        self.messages += 1
        if time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()

    def maybe_flush(self) -> None:
        """Flush if ``flush_s`` has passed since the last flush (call when idle)."""
        if time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        """Write the open chunk and flush the file (what a kill can lose is what came after)."""
        self._writer.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            try:
                self._writer.finish()
            finally:
                self._file.close()

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class RecoveryReport:
    source: str
    output: str
    messages: int
    channels: int
    complete: bool  # the source was intact (had its footer)
    stopped_at: str = ""  # why reading stopped early, if it did
    topics: dict[str, int] = field(default_factory=dict)


def recover(src: str | os.PathLike, dst: str | os.PathLike) -> RecoveryReport:
    """Copy every readable message of ``src`` into a new indexed MCAP file ``dst``."""
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise RecordingError(f"{src}: recover needs a different output file")
    try:
        fin = open(src, "rb")
    except OSError as e:
        raise RecordingError(f"{src}: cannot open: {e.strerror}") from None
    schemas: dict[int, Schema] = {}
    out_channels: dict[int, str] = {}  # source channel id -> topic (registered in the output)
    topics: dict[str, int] = {}
    stopped, complete, n = "", False, 0
    with fin, Recorder(dst) as rec:
        try:
            for record in StreamReader(fin, record_size_limit=1 << 31).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    s = schemas.get(record.schema_id)
                    rec.channel(record.topic, record.message_encoding, s.name if s else "", s.data if s else b"",
                                s.encoding if s else "", dict(record.metadata))
                    out_channels[record.id] = record.topic
                elif isinstance(record, Message):
                    topic = out_channels.get(record.channel_id)
                    if topic is None:
                        continue
                    rec.write(topic, record.data, record.log_time, record.publish_time)
                    topics[topic] = topics.get(topic, 0) + 1
                    n += 1
                elif type(record).__name__ == "Footer":
                    complete = True
        except Exception as e:  # noqa: BLE001 - a torn tail raises assorted errors; keep what was read
            stopped = f"{type(e).__name__}: {e}"
    if not n and not out_channels:
        raise RecordingError(f"{src}: no readable MCAP records ({stopped or 'empty file'})")
    return RecoveryReport(str(src), str(dst), n, len(out_channels), complete and not stopped, stopped, topics)


def read_messages(path: str | os.PathLike, topics: list[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log_time_ns, data) in log-time order; raises :class:`RecordingError` if unreadable."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for _schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                yield channel.topic, message.log_time, message.data
    except OSError as e:
        raise RecordingError(f"{path}: cannot read: {e.strerror}") from None
    except (McapError, EOFError, ValueError) as e:
        raise RecordingError(f"{path}: not a complete MCAP file ({e}); try `quick-stream recover {path}`") from None

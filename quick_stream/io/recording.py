"""MCAP recording: every stage's messages on their own channels, flushed often, recoverable.

* :class:`Recorder` writes msgpack channels (exact replay; message encoding
  ``msgpack``, no schema) and any other channel a caller registers (e.g. JSON
  with a JSON schema for viewers). The MCAP writer keeps the open chunk in
  memory, so :meth:`Recorder.write` closes it (``Writer.flush``) whenever
  ``flush_s`` seconds have passed: a killed process loses at most about that
  long (measured: without flushing, small messages were all lost).
* :func:`recover` repairs a file left without a footer (a writer killed with
  SIGKILL): it stream-reads records up to the first damaged one and rewrites
  schemas, channels, metadata and messages into a new, indexed file.
* :func:`read_messages` iterates a recording in log-time order, through the
  index when there is one and by streaming when there is not.

Damaged files: every reader opens the recording with :func:`open_recording`, whose reads
never ask for more than what is left of the file (the mcap library sizes its reads by
length fields of the file, so a damaged length made it allocate up to 2^64 bytes:
``MemoryError``), and turns whatever the mcap library raises on a damaged record
(``struct.error``, ``KeyError``, ``UnicodeDecodeError``, zstd/lz4 errors, ...) into
:class:`RecordingError` naming the file, the message count and byte offset reached and the
problem in words (:func:`describe_damage`; found by ``python -m tests.tools.fuzz --target mcap``).
"""
from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import zstandard
from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from .recording_images import Rejoiner

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


MAGIC = b"\x89MCAP0\r\n"
MIN_FILE_BYTES = 8 + 9 + 20 + 8  # magic, footer record, magic: the least an indexed reader needs


class _ClosedOnExit:
    """``with x:`` closes ``x`` at the end of the block."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class BoundedFile(_ClosedOnExit):
    """A recording opened for reading; ``read(n)`` never asks the OS for more than what is left.

    mcap's readers call ``read(length)`` with lengths taken from the file; through a plain
    file object a damaged length (say 2^62) first allocates that many bytes. Here it is cut
    to the bytes left, so a damaged length reads to the end and fails as a short record.
    ``pos`` is the byte offset reached (for error messages).
    """

    def __init__(self, f: BinaryIO) -> None:
        self._f = f
        self.size = os.fstat(f.fileno()).st_size
        self.pos = f.tell()

    def read(self, n: int | None = -1) -> bytes:
        left = self.size - self.pos
        if n is None or n < 0 or n > left:
            self.size = os.fstat(self._f.fileno()).st_size  # a file still being written may have grown
            left = max(self.size - self.pos, 0)
            n = left if n is None or n < 0 else min(n, left)
        data = self._f.read(n)
        self.pos += len(data)
        return data

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        self.pos = self._f.seek(offset, whence)
        return self.pos

    def tell(self) -> int:
        return self.pos

    def seekable(self) -> bool:
        return True

    def close(self) -> None:
        self._f.close()


def open_recording(path: str | os.PathLike) -> BoundedFile:
    """Open a recording for reading (raises ``OSError`` like ``open``)."""
    return BoundedFile(open(path, "rb"))


def describe_damage(e: BaseException) -> str:
    """In words, what the mcap library's exception on a damaged record means (type kept in brackets)."""
    name = "struct.error" if isinstance(e, struct.error) else type(e).__name__
    if isinstance(e, (EndOfFile, struct.error)):
        return f"the file ends inside a record (truncated, or a record length is wrong) [{name}]"
    if isinstance(e, UnicodeDecodeError):
        return f"a string field is not UTF-8 (byte {e.start} of the string) [{name}]"
    if isinstance(e, KeyError):
        return f"a record refers to channel or schema id {e.args[0]!r}, which no record defines [{name}]"
    if isinstance(e, RecordLengthLimitExceeded):
        return f"{e}: longer than the file, a damaged length [{name}]"
    if isinstance(e, (MemoryError, OverflowError)):
        return f"a length field asks for a larger buffer than there can be (a damaged length) [{name}]"
    if isinstance(e, zstandard.ZstdError) or (isinstance(e, RuntimeError) and "LZ4" in str(e)):
        return f"a chunk does not decompress ({e}) [{name}]"
    return f"{e} [{name}]" if str(e) else f"[{name}]"


class Recorder(_ClosedOnExit):
    """One MCAP file; not thread-safe (one recorder per process).

    ``flush_on_write``: :meth:`write` flushes when ``flush_s`` has passed (default). Off, only
    :meth:`maybe_flush` and :meth:`flush` do, so a caller that writes one message as several
    records (an image, then the message referring to it) knows which of them a flush took: the
    recorder service keeps its account of what is on disk that way (docs/reliability.md)."""

    def __init__(self, path: str | os.PathLike, flush_s: float = 1.0, chunk_size: int = 1 << 20,
                 compression: str = "none", flush_on_write: bool = True) -> None:
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
        self.flush_s, self.flush_on_write = flush_s, flush_on_write
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

    def metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record (e.g. the settings a recording was made with)."""
        self._writer.add_metadata(name, data)

    def write(self, topic: str, data: bytes, log_time_ns: int | None = None,
              publish_time_ns: int | None = None, sequence: int | None = None) -> int:
        """Log ``data`` on ``topic`` (registered as msgpack if new); flush if ``flush_s`` has passed
        (unless ``flush_on_write`` is off).

        Returns the message's sequence number on its channel: 0, 1, 2, ... per channel and file
        unless ``sequence`` gives it (:func:`recover` keeps the source's, which stored-apart
        images are referenced by: :mod:`quick_stream.io.recording_images`)."""
        if self.closed:
            raise RecordingError(f"{self.path}: recorder is closed")
        cid = self._channels.get(topic)
        if cid is None:
            cid = self.channel(topic)
        now = time.time_ns()
        log_time = now if log_time_ns is None else int(log_time_ns)
        seq = self._seq[topic] if sequence is None else int(sequence)
        self._writer.add_message(cid, log_time, bytes(data), now if publish_time_ns is None else int(publish_time_ns),
                                 seq)
        self._seq[topic] = seq + 1
        self.messages += 1
        if self.flush_on_write and time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()
        return seq

    def maybe_flush(self) -> bool:
        """Flush if ``flush_s`` has passed since the last flush (call when idle); whether it did."""
        if time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()
            return True
        return False

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

    def abandon(self) -> None:
        """Stop writing without a footer (the disk is full: writing one would fail too). The chunks
        already on disk stay readable by :func:`recover`."""
        if not self.closed:
            self.closed = True
            try:
                self._file.close()
            except OSError:
                pass  # what was still buffered cannot be written either


class SplitRecorder(_ClosedOnExit):
    """A recording split over files: ``rec`` is the :class:`Recorder` being written; once it holds
    ``split_bytes`` or is ``split_s`` old (0: never) :meth:`wrote` finishes it (footer, indexes)
    and opens the first free ``<base stem>-N<suffix>`` (:func:`fresh_path`), calling ``on_open``
    on each new file (to register its channels). Not thread-safe, like :class:`Recorder`."""

    def __init__(self, base: str | os.PathLike, first: str | os.PathLike, split_bytes: int = 0,
                 split_s: float = 0.0, on_open: Callable[[Recorder], object] | None = None, **recorder_kw) -> None:
        self.base, self.split_bytes, self.split_s = base, split_bytes, split_s
        self._on_open, self._kw = on_open, recorder_kw
        self.done: list[tuple[Path, int]] = []  # (path, messages) of the finished files
        self._open(first)

    def _open(self, path: str | os.PathLike) -> None:
        self.rec = Recorder(path, **self._kw)
        self.bytes, self.t0 = 0, time.monotonic()
        if self._on_open is not None:
            self._on_open(self.rec)

    def wrote(self, n: int) -> Path | None:
        """``n`` bytes went into the current file; start the next if one is due (returns the finished file)."""
        self.bytes += n
        if not ((self.split_bytes and self.bytes >= self.split_bytes)
                or (self.split_s and time.monotonic() - self.t0 >= self.split_s)):
            return None
        old = self.rec
        old.close()
        self.done.append((old.path, old.messages))
        self._open(fresh_path(self.base))
        return old.path

    @property
    def messages(self) -> int:
        """Messages in every file so far."""
        return sum(n for _, n in self.done) + self.rec.messages

    def close(self) -> None:
        self.rec.close()


@dataclass
class RecoveryReport:
    source: str
    output: str
    messages: int
    channels: int
    complete: bool  # the source was intact (had its footer)
    stopped_at: str = ""  # why reading stopped early, if it did
    topics: dict[str, int] = field(default_factory=dict)


def recover(src: str | os.PathLike, dst: str | os.PathLike, *, overwrite: bool = False) -> RecoveryReport:
    """Copy every readable message of ``src`` into a new indexed MCAP file ``dst``.

    The copy is written beside ``dst`` (``<dst>.part``) and renamed to ``dst`` once complete: a
    recording that cannot be repaired leaves no file. An existing ``dst`` is a RecordingError
    unless ``overwrite``."""
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise RecordingError(f"{src}: recover needs a different output file")
    if dst.exists() and not overwrite:
        raise RecordingError(f"{dst}: exists (give another output file, or overwrite it: --force)")
    try:
        fin = open_recording(src)
    except OSError as e:
        raise RecordingError(f"{src}: cannot open: {e.strerror}") from None
    part = dst.with_name(dst.name + ".part")
    try:
        report = _copy_readable(src, fin, part, dst)
        if not overwrite and dst.exists():  # appeared meanwhile: still not ours to replace
            raise RecordingError(f"{dst}: exists (give another output file, or overwrite it: --force)")
        os.replace(part, dst)
    finally:
        part.unlink(missing_ok=True)
    return report


def _copy_readable(src: Path, fin: BoundedFile, part: Path, dst: Path) -> RecoveryReport:
    schemas: dict[int, Schema] = {}
    out_channels: dict[int, str] = {}  # source channel id -> topic (registered in the output)
    topics: dict[str, int] = {}
    stopped, complete, n = "", False, 0
    with fin, Recorder(part) as rec:
        try:
            for record in StreamReader(fin, record_size_limit=max(fin.size, 1)).records:
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
                    rec.write(topic, record.data, record.log_time, record.publish_time, record.sequence)
                    topics[topic] = topics.get(topic, 0) + 1
                    n += 1
                elif isinstance(record, Metadata):
                    rec.metadata(record.name, dict(record.metadata))
                elif type(record).__name__ == "Footer":
                    complete = True
        except Exception as e:  # noqa: BLE001 - a torn tail raises assorted errors; keep what was read
            stopped = f"at byte {fin.pos} after {n} messages: {describe_damage(e)}"
    if not n and not out_channels:
        raise RecordingError(f"{src}: no readable MCAP records ({stopped or 'empty file'})")
    return RecoveryReport(str(src), str(dst), n, len(out_channels), complete and not stopped, stopped, topics)


def read_messages(path: str | os.PathLike, topics: list[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log_time_ns, data) in log-time order; raises :class:`RecordingError` if unreadable.

    Wire messages come out as they were received: a JPEG the recorder stored once, in its
    Foxglove image record, is put back (:class:`~quick_stream.io.recording_images.Rejoiner`).
    The error names the file and the problem: no intact footer/summary (a killed writer; the
    message says to run ``quick-stream recover``), or a damaged record after the n-th message read.
    """
    path = Path(path)
    rejoin = Rejoiner(topics)
    n = 0
    try:
        with open_recording(path) as f:
            reader = _indexed_reader(path, f)
            try:
                for _schema, channel, message in reader.iter_messages(topics=rejoin.read_topics,
                                                                      log_time_order=True):
                    n += 1
                    data = rejoin.take(channel.topic, message.sequence, message.data)
                    if data is not None:
                        yield channel.topic, message.log_time, data
            except Exception as e:  # noqa: BLE001 - a damaged record raises assorted errors (describe_damage)
                raise RecordingError(f"{path}: damaged record after {n} messages (near byte {f.pos}): "
                                     f"{describe_damage(e)}; `quick-stream recover {path}` keeps what is "
                                     "readable") from None
    except OSError as e:
        raise RecordingError(f"{path}: cannot read: {e.strerror or e}") from None


def _indexed_reader(path: Path, f: BoundedFile) -> SeekingReader:
    """A seeking reader whose summary (footer, chunk indexes) has been read; RecordingError if it cannot."""
    if f.read(len(MAGIC)) != MAGIC:
        raise RecordingError(f"{path}: not a valid MCAP file (it does not start with the MCAP magic bytes)")
    if f.size < MIN_FILE_BYTES:
        raise RecordingError(f"{path}: not a valid MCAP file: {f.size} bytes is too short for one "
                             f"(at least {MIN_FILE_BYTES})")
    f.seek(0)
    reader = SeekingReader(f, record_size_limit=f.size)
    try:
        reader.get_summary()
    except Exception as e:  # noqa: BLE001 - a torn or damaged file raises assorted errors (describe_damage)
        raise RecordingError(f"{path}: not a complete MCAP file, no intact footer and summary "
                             f"({describe_damage(e)}); try `quick-stream recover {path}`") from None
    return reader

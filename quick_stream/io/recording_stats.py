"""Per-channel byte rates of an MCAP recording (``quick-stream recording-stats FILE``).

How much each channel of a recording costs: messages, bytes of message data, share of all
message data, bytes per second of log time, bytes per message and per frame, and the file's
own size per second (message data plus MCAP records, indexes and summary). The file is read
by streaming its records, so a recording left without a footer (a killed writer) is measured
up to its first damaged record, and the result says where reading stopped.

Rates are over the recording's log-time span (first to last message). A capture that shed
frames (docs/reliability.md) records fewer frames per second than it was asked for, so the
per-frame sizes, and the rate they give at a nominal frame rate (``--fps``), are what compare
recordings made under different loads (docs/recording.md, "Sizes").
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from ..stream import keys
from .recording import RecordingError, describe_damage, open_recording


@dataclass
class ChannelStats:
    """One channel: its topic, encodings, message count and bytes of message data."""

    topic: str
    message_encoding: str
    schema: str
    messages: int = 0
    bytes: int = 0


@dataclass
class RecordingStats:
    """What :func:`recording_stats` measured; rates are per second of log time."""

    path: str
    file_bytes: int
    channels: dict[str, ChannelStats] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None
    frames: int = 0  # messages on the streams' ``frame`` channels (the frames recorded)
    streams: int = 0  # streams with a ``frame`` channel
    stopped_at: str = ""  # why reading stopped before the end (a damaged or unfinished file)

    @property
    def duration_s(self) -> float:
        """Log time from the first message to the last, seconds (0 with fewer than two)."""
        if self.first_ns is None or self.last_ns is None:
            return 0.0
        return (self.last_ns - self.first_ns) / 1e9

    @property
    def message_bytes(self) -> int:
        return sum(c.bytes for c in self.channels.values())

    @property
    def messages(self) -> int:
        return sum(c.messages for c in self.channels.values())

    def rate(self, nbytes: int) -> float | None:
        """``nbytes`` per second of log time (None when the recording spans no time)."""
        d = self.duration_s
        return nbytes / d if d > 0 else None

    def per_frame(self, nbytes: int) -> float | None:
        """``nbytes`` per recorded frame (None without frames)."""
        return nbytes / self.frames if self.frames else None

    def as_dict(self, fps: float | None = None) -> dict:
        """A JSON-ready summary (``fps``: also each rate at that many frames per second per stream)."""
        def at(nbytes: int) -> float | None:
            pf = self.per_frame(nbytes)
            return None if pf is None or fps is None else pf * fps * max(self.streams, 1)

        total = self.message_bytes
        return {
            "path": self.path, "duration_s": self.duration_s, "file_bytes": self.file_bytes,
            "file_bytes_per_s": self.rate(self.file_bytes), "message_bytes": total,
            "message_bytes_per_s": self.rate(total), "messages": self.messages, "frames": self.frames,
            "streams": self.streams, "fps": fps, "file_bytes_per_s_at_fps": at(self.file_bytes),
            "stopped_at": self.stopped_at,
            "channels": [{"topic": c.topic, "message_encoding": c.message_encoding, "schema": c.schema,
                          "messages": c.messages, "bytes": c.bytes, "share": c.bytes / total if total else 0.0,
                          "bytes_per_s": self.rate(c.bytes), "bytes_per_message": c.bytes / c.messages
                          if c.messages else 0.0, "bytes_per_frame": self.per_frame(c.bytes),
                          "bytes_per_s_at_fps": at(c.bytes)}
                         for c in sorted(self.channels.values(), key=lambda c: -c.bytes)],
        }


def recording_stats(path: str | os.PathLike) -> RecordingStats:
    """Measure a recording; raises :class:`RecordingError` when it cannot be opened or holds no MCAP."""
    path = Path(path)
    try:
        f = open_recording(path)
    except OSError as e:
        raise RecordingError(f"{path}: cannot open: {e.strerror or e}") from None
    stats = RecordingStats(str(path), f.size)
    by_id: dict[int, ChannelStats] = {}
    schemas: dict[int, str] = {}
    records = 0
    with f:
        try:
            for record in StreamReader(f, record_size_limit=max(f.size, 1)).records:
                records += 1
                if isinstance(record, Channel):
                    ch = stats.channels.get(record.topic)
                    if ch is None:
                        ch = stats.channels[record.topic] = ChannelStats(
                            record.topic, record.message_encoding, schemas.get(record.schema_id, ""))
                    by_id[record.id] = ch
                elif isinstance(record, Message):
                    ch = by_id.get(record.channel_id)
                    if ch is None:
                        continue
                    ch.messages += 1
                    ch.bytes += len(record.data)
                    t = record.log_time
                    stats.first_ns = t if stats.first_ns is None else min(stats.first_ns, t)
                    stats.last_ns = t if stats.last_ns is None else max(stats.last_ns, t)
                elif isinstance(record, Schema):
                    schemas[record.id] = record.name
        except Exception as e:  # noqa: BLE001 - a torn or damaged file raises assorted errors (describe_damage)
            if not records:  # not even the header: no MCAP file
                raise RecordingError(f"{path}: not a readable MCAP file ({describe_damage(e)})") from None
            stats.stopped_at = f"near byte {f.pos}: {describe_damage(e)}"
    frame_channels = [c for c in stats.channels.values() if keys.stage_of(c.topic) == "frame"]
    stats.frames = sum(c.messages for c in frame_channels)
    stats.streams = len(frame_channels)
    return stats


def _mb(n: float | None) -> str:
    return "-" if n is None else f"{n / 1e6:.3f}"


def _kb(n: float | None) -> str:
    return "-" if n is None else f"{n / 1e3:.1f}"


def report(s: RecordingStats, fps: float | None = None) -> str:
    """The table ``quick-stream recording-stats`` prints (1 MB = 10^6 bytes, 1 kB = 10^3)."""
    total = s.message_bytes
    head = (f"{s.path}: {s.messages} messages over {s.duration_s:.2f} s of log time, {s.frames} frames"
            f"{f' in {s.streams} streams' if s.streams > 1 else ''}")
    at = fps is not None and s.frames > 0
    scale = (fps or 0) * max(s.streams, 1)
    cols = f"{'channel':34} {'encoding':9} {'messages':>8} {'MB':>9} {'share':>6} {'MB/s':>8} {'kB/msg':>8} {'kB/frame':>9}"
    if at:
        cols += f" {f'MB/s@{fps:g}fps':>12}"
    lines = [head, cols]

    def row(name: str, enc: str, n: int | str, nbytes: int, share: str) -> str:
        pf = s.per_frame(nbytes)
        line = (f"{name:34} {enc:9} {n:>8} {nbytes / 1e6:>9.3f} {share:>6} {_mb(s.rate(nbytes)):>8} "
                f"{_kb(nbytes / n if isinstance(n, int) and n else None):>8} {_kb(pf):>9}")
        if at:
            line += f" {_mb(pf * scale if pf is not None else None):>12}"
        return line

    for c in sorted(s.channels.values(), key=lambda c: -c.bytes):
        lines.append(row(c.topic, c.message_encoding, c.messages, c.bytes,
                         f"{100 * c.bytes / total:.1f}%" if total else "-"))
    lines.append(row("all message data", "", s.messages, total, "100%" if total else "-"))
    lines.append(row("file (records, indexes, summary)", "", "", s.file_bytes, ""))
    if s.stopped_at:
        lines.append(f"note: reading stopped {s.stopped_at}; the numbers cover what was read")
    return "\n".join(lines)


__all__ = ["ChannelStats", "RecordingStats", "recording_stats", "report"]

"""Replay the ``frame`` messages of an MCAP recording as a frame source.

Spec: ``mcap:FILE`` or ``mcap:FILE,stream=ID``. The source reads the msgpack channel
``quick/@v1/<stream>/frame`` (the exact wire bytes, see :mod:`quick_stream.io.recording`)
and decodes each message with :func:`quick_stream.stream.wire.decode`; frames keep their
recorded ``seq``, capture timestamp, intrinsics, pose and origin. Without ``stream``
the recording must hold exactly one stream with frame messages.

* A message that does not decode (or whose frame fails validation) becomes a
  :class:`~quick_stream.core.frame.BadFrame` whose error names the file, the message's
  index on the channel, its log time and the problem; iteration goes on.
* The ``end`` marker the capture sends after its last frame (on the frame channel, so
  a recording holds it) ends the replay cleanly: it is neither a frame nor a bad
  frame, and ``len`` does not count it.
* An intact (indexed) file is read through its index; ``len`` comes from the
  summary statistics. A file without a footer (a killed writer) or with a damaged
  summary is read by streaming records up to the first damaged one, which is what
  ``quick-stream recover`` would keep; opening then scans the file once to count.
* ``intrinsics`` and ``depth_scale`` (the wire quantization, so re-publishing keeps
  it) come from the first decodable frame; ``fps`` from the median spacing of the
  capture timestamps and ``has_ground_truth`` from the poses of the first
  :data:`PROBE_MESSAGES` frame messages (read without decoding their images).
"""
from __future__ import annotations

import errno
import logging
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import numpy as np
from mcap.reader import SeekingReader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from ...core.frame import BadFrame, FrameError, Intrinsics, RGBDFrame
from ...stream.keys import PREFIX, check_stream, key, parse, stage_of
from ...stream.wire import WireError, decode
from ...stream.wire.codec import unpack
from ..recording import RecordingError, describe_damage, open_recording, read_messages
from ..recording_images import Rejoiner
from .base import FrameOrGap, SourceError

log = logging.getLogger("quick_stream.io.sources.mcap_replay")

PROBE_MESSAGES = 100  # frame messages read at open time for fps and ground truth
DEFAULT_FPS = 30.0  # when fewer than two distinct capture timestamps are known
_OPTIONS = ("stream",)


def _stream_records(path: Path, topics: set[str] | None,
                    on_stop: Callable[[str], None]) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log_time_ns, data) in file order, up to the first damaged record; images stored
    apart put back into their wire messages (:class:`~quick_stream.io.recording_images.Rejoiner`)."""
    channels: dict[int, str] = {}
    rejoin = Rejoiner(None if topics is None else sorted(topics))
    read = None if rejoin.read_topics is None else set(rejoin.read_topics)
    n, pos = 0, 0
    try:
        with open_recording(path) as f:
            for record in StreamReader(f, record_size_limit=max(f.size, 1)).records:
                pos = f.pos
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message):
                    n += 1
                    topic = channels.get(record.channel_id)
                    if topic is not None and (read is None or topic in read):
                        data = rejoin.take(topic, record.sequence, record.data)
                        if data is not None:
                            yield topic, record.log_time, data
    except OSError as e:
        on_stop(f"{path}: cannot read: {e.strerror or e}")
    except Exception as e:  # noqa: BLE001 - a torn tail raises assorted errors; keep what was read
        on_stop(f"{path}: reading stopped at a damaged record after {n} messages (near byte {pos}): "
                f"{describe_damage(e)}")


def _summary_counts(path: Path, stage: str | None = "frame") -> tuple[dict[str, int] | None, str]:
    """({topic of ``stage``: message count}, "") from an indexed file, or (None, why it is not
    usable); ``stage`` None: every quick-stream topic."""
    try:
        with open_recording(path) as f:
            summary = SeekingReader(f, record_size_limit=max(f.size, 1)).get_summary()
    except OSError as e:
        if e.errno == errno.EINVAL:  # seeking to the footer of a file shorter than one
            return None, "no readable footer/summary (the file is shorter than a footer)"
        raise SourceError(f"cannot open recording {path}: {e.strerror or e}") from None
    except Exception as e:  # noqa: BLE001 - footer-less or damaged files raise assorted errors
        return None, f"no readable footer/summary ({describe_damage(e)})"
    if summary is None:
        return None, "no summary section"
    frame_ids = {cid: ch.topic for cid, ch in summary.channels.items() if _is_stage_topic(ch.topic, stage)}
    stats = summary.statistics
    if stats is None or (frame_ids and not stats.channel_message_counts):
        counts: dict[str, int] = {t: 0 for t in frame_ids.values()}
        if counts:
            try:
                for t, _, _ in read_messages(path, list(counts)):
                    counts[t] += 1
            except RecordingError as e:
                return None, str(e)
        return counts, ""
    counts = {}
    for cid, t in frame_ids.items():
        counts[t] = counts.get(t, 0) + int(stats.channel_message_counts.get(cid, 0))
    return counts, ""


def _is_stage_topic(topic: str, stage: str | None) -> bool:
    """``topic`` is ``quick/@v1/<stream>/<stage>`` (of any stage for None)."""
    s = stage_of(topic)
    return s is not None and (stage is None or s == stage)


def _is_end(data: bytes) -> bool:
    """Whether a message on a frame channel is the stream's ``end`` marker (envelope only, no pixels)."""
    try:
        return unpack(data).type == "end"
    except WireError:
        return False


def _frame_counts(path: Path, on_stop: Callable[[str], None],
                  stage: str | None = "frame") -> tuple[dict[str, int], bool, str]:
    """({topic of ``stage``: count}, indexed, why not indexed); footer-less files are scanned once."""
    counts, problem = _summary_counts(path, stage)
    if counts is not None:
        return counts, True, ""
    log.warning("%s: %s; reading it by streaming up to the first damaged record", path, problem)
    counts = {}
    for t, _, data in _stream_records(path, None, on_stop):
        if _is_stage_topic(t, stage) and not _is_end(data):
            counts[t] = counts.get(t, 0) + 1
    return counts, False, problem


def recorded_streams(path: str | os.PathLike, stage: str | None = "frame") -> dict[str, int]:
    """{stream id: number of ``stage`` messages} of a recording (``stage`` None: messages of any
    stage), sorted by stream, streams without such messages left out. Counted from the summary of an
    indexed file, else by reading it up to its first damaged record. SourceError when the file
    cannot be opened."""
    counts, _, _ = _frame_counts(Path(path), lambda _why: None, stage)
    streams: dict[str, int] = {}
    for topic, n in sorted(counts.items()):
        if n > 0:
            s = parse(topic)[0]
            streams[s] = streams.get(s, 0) + n
    return streams


class McapSource:
    """The frames of one stream of an MCAP recording, decoded lazily, in log-time order."""

    def __init__(self, path: str | os.PathLike, stream: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise SourceError(f"recording not found: {self.path}")
        self.stopped_at = ""  # set when reading stopped early at a damaged record
        counts, self.indexed, self.problem = _frame_counts(self.path, self._stop)  # problem: why streamed
        streams = {parse(t)[0]: n for t, n in sorted(counts.items()) if n > 0}  # one frame topic a stream
        self.stream = self._choose(streams, stream)
        self.topic = key(self.stream, "frame")
        self._count = streams[self.stream] - self._trailing_ends()
        self.name = f"mcap:{self.path},stream={self.stream}"
        self._probe()

    def _choose(self, streams: dict[str, int], stream: str | None) -> str:
        listing = ", ".join(f"{s} ({n} frames)" for s, n in streams.items()) or "none"
        if stream is not None:
            try:
                check_stream(stream)
            except ValueError as e:
                raise SourceError(f"mcap source {self.path}: {e}") from None
            if stream not in streams:
                raise SourceError(f"recording {self.path} has no frame messages of stream {stream!r} "
                                  f"(streams with frames: {listing})")
            return stream
        if not streams:
            why = f" ({self.stopped_at or self.problem})" if not self.indexed else ""
            raise SourceError(f"recording {self.path} has no frame messages (no {PREFIX}/<stream>/frame "
                              f"channel){why}")
        if len(streams) > 1:
            raise SourceError(f"recording {self.path} holds several streams with frames: {listing}; "
                              f"choose one with mcap:{self.path},stream=ID")
        return next(iter(streams))

    def _probe(self) -> None:
        """Intrinsics/depth scale of the first decodable frame; fps and ground truth from the first few."""
        first = None
        times: list[int] = []
        self.has_ground_truth = False
        why: list[str] = []  # the first decoding error and why reading stopped, for the error below
        for i, (_log_time, data) in enumerate(self._messages(on_stop=why.append)):
            if i >= PROBE_MESSAGES and first is not None:
                break
            try:
                r = unpack(data)
                if isinstance(r.d.get("t_ns"), int):
                    times.append(r.d["t_ns"])
                self.has_ground_truth |= r.d.get("pose") is not None
                if first is None and r.type == "frame":
                    first = decode(data)
            except WireError as e:
                if not why:
                    why.append(f"message {i}: {e}")
                continue
        if first is None:
            raise SourceError(f"recording {self.path}: none of the {self._count} frame messages of stream "
                              f"{self.stream!r} decodes ({'; '.join(why) or 'none could be read'})")
        self.intrinsics: Intrinsics = first.obj.intrinsics
        self.depth_scale: float = float(first.depth_scale)
        self.color_encoding: str = first.color_encoding
        dts = np.diff(np.asarray(times, dtype=np.float64))
        dts = dts[dts > 0]
        self.fps = 1e9 / float(np.median(dts)) if len(dts) else DEFAULT_FPS

    @classmethod
    def from_spec(cls, path: str, options: Mapping[str, str]) -> McapSource:
        """Open from a spec path (``mcap:`` prefix optional) and string options (``stream``)."""
        path = path.removeprefix("mcap:")
        unknown = sorted(set(options) - set(_OPTIONS))
        if unknown:
            raise ValueError(f"mcap source: unknown option {unknown[0]!r} (known: {', '.join(_OPTIONS)})")
        return cls(path, stream=options.get("stream") or None)

    # -- access ------------------------------------------------------------------
    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[FrameOrGap]:
        for item, _data in self.iter_with_messages():
            yield item

    def iter_with_messages(self, pixels: bool = True) -> Iterator[tuple[FrameOrGap, bytes]]:
        """Each frame (or BadFrame) with the recorded message bytes it came from (exact replay).
        ``pixels=False``: every field is checked but images and depth are left undecoded (zero-filled,
        their compressed streams not validated: ~0.05 ms a frame instead of ~3), for a replay that sends
        the recorded bytes (its receivers decode and check the pixels, and count what they refuse)."""
        period_ns = round(1e9 / self.fps)
        prev: tuple[int, int] | None = None  # (seq, timestamp_ns) of the last item yielded
        for index, (log_time, data) in enumerate(self._messages()):
            try:
                msg = decode(data, pixels=pixels, color="bgr+luma", streams=pixels)  # the grey the flow reads
                if msg.type == "end":  # the capture's end marker: not a frame (a later run's frames may follow)
                    log.debug("%s: end marker at message %d", self.path, index)
                    continue
                if msg.type != "frame":
                    raise WireError(f"expected a 'frame' message, got {msg.type!r}", stream=msg.stream, seq=msg.seq)
                frame: RGBDFrame = msg.obj.validate() if pixels else msg.obj
            except (WireError, FrameError) as e:
                gap = self._gap(index, log_time, data, e, prev, period_ns)
                log.warning("%s", gap.error)
                prev = (gap.seq, gap.timestamp_ns)
                yield gap, data
                continue
            prev = (frame.seq, frame.timestamp_ns)
            yield frame, data

    def __repr__(self) -> str:
        return (f"McapSource({str(self.path)!r}, stream={self.stream!r}, frames={len(self)}, "
                f"fps={self.fps:.3g}, depth_scale={self.depth_scale:g}, indexed={self.indexed})")

    # -- internals ---------------------------------------------------------------
    def _trailing_ends(self) -> int:
        """How many of the channel's last messages are end markers (the count from the summary holds
        them): read from the end of an indexed file, which costs one message; streamed files were
        counted without them already."""
        if not self.indexed:
            return 0
        n = 0
        try:
            with open_recording(self.path) as f:
                reader = SeekingReader(f, record_size_limit=max(f.size, 1))
                for _schema, _channel, message in reader.iter_messages(topics=[self.topic], reverse=True):
                    if not _is_end(message.data):
                        break
                    n += 1
        except Exception as e:  # noqa: BLE001 - a damaged index: iteration finds it and says so
            log.debug("%s: cannot read the last messages for end markers: %s", self.path, describe_damage(e))
        return n

    def _stop(self, why: str) -> None:
        self.stopped_at = why
        log.warning("%s", why)

    def _messages(self, on_stop: Callable[[str], None] | None = None) -> Iterator[tuple[int, bytes]]:
        """(log_time_ns, data) of this stream's frame messages; ``on_stop`` (default: record it in
        ``stopped_at`` and log it) hears why reading stopped early."""
        on_stop = on_stop or self._stop
        if not self.indexed:
            for _t, log_time, data in _stream_records(self.path, {self.topic}, on_stop):
                yield log_time, data
            return
        try:
            for _t, log_time, data in read_messages(self.path, [self.topic]):
                yield log_time, data
        except RecordingError as e:
            on_stop(f"{e} (reading stopped)")

    def _gap(self, index: int, log_time: int, data: bytes, err: Exception,
             prev: tuple[int, int] | None, period_ns: int) -> BadFrame:
        """The BadFrame of an undecodable message: its seq/time when readable, else the next expected."""
        seq, t_ns = getattr(err, "seq", None), None
        try:
            r = unpack(data)
            seq = r.seq if seq is None else seq
            t_ns = r.d.get("t_ns") if isinstance(r.d.get("t_ns"), int) else None
        except WireError:
            pass
        if seq is None:
            seq = index if prev is None else prev[0] + 1
        if t_ns is None:
            t_ns = log_time if prev is None else prev[1] + period_ns
        origin = f"{self.path} message {index}"
        error = f"{self.path}: {self.topic} message {index} (log time {log_time} ns): {err}"
        return BadFrame(int(seq), int(t_ns), origin, error)

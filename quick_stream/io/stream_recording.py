"""The recorder service's recording: every message of a stream (or of all streams) into split MCAP files.

:class:`StreamRecording` holds what ``quick-stream-recorder`` does with each message
(docs/recording.md, docs/reliability.md):

* :meth:`~StreamRecording.accept` (zenoh's thread, as each message arrives): its wire bytes, and
  its JPEG in its Foxglove image record (:mod:`quick_stream.io.recording_images`), into the file's
  open chunk at once, so what arrived is on disk within ``flush_s`` however far the views lag;
* :meth:`~StreamRecording.view` (the service loop, from a drop-oldest queue): the other Foxglove
  channels derived from it (:class:`~quick_stream.io.foxglove_view.FoxgloveView`);
* :meth:`~StreamRecording.flusher` (a thread; ``accept`` too, when one is due): the open chunk
  written out every ``flush_s``, then the side file a restarted recorder continues its account
  from, which says what that flush put on disk, not what had arrived
  (:mod:`quick_stream.io.recorded_account`); a time split when due;
* :meth:`~StreamRecording.gap_seen`: the seqs of a stage that never arrived, logged (a restarted
  recorder's hole, what was published while none ran or not yet flushed by its predecessor, said
  once and counted apart);
* :attr:`~StreamRecording.replays`: for the inbox, so a message received before, byte for byte (a
  restarted publisher sending again what its predecessor had sent), is stored once
  (:mod:`quick_stream.stream.replays`; docs/recording.md);
* the first failed write (a full disk) stops the recording, said once, and the service (exit 2).
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

from ..stream import keys
from ..stream.arrivals import ArrivalLedger, Gap
from ..stream.meters import RateMeter
from ..stream.replays import ReplayFilter
from ..stream.wire import WireError
from ..stream.wire.codec import peek
from . import foxglove
from .foxglove_view import FoxgloveView
from .recorded_account import OnDisk, load_recorded, recorded_path, save_recorded
from .recording import Recorder, SplitRecorder, fresh_path
from .recording_images import write_message
from .settings_file import RECORD_NAME

log = logging.getLogger(__name__)


class StreamRecording:
    """A recorder service's files and account (module docstring); use as a context manager (the
    files are finished on leaving: close the session first, so nothing arrives after)."""

    def __init__(self, output: str, *, foxglove_views: bool = True, flush_s: float = 0.5, compression: str = "none",
                 split_mb: float = 0.0, split_minutes: float = 0.0, settings: dict[str, str] | None = None,
                 on_failure: Callable[[], Any] = lambda: None) -> None:
        """``settings``: the settings record every file starts with (:func:`~quick_stream.io.settings_file.settings_record`)."""
        self.output, self.views_on, self.flush_s, self.on_failure = output, foxglove_views, flush_s, on_failure
        out = fresh_path(output)
        if str(out) != output:
            log.warning("%s exists (a previous run or a killed recorder): recording to %s", output, out)
        self.lock = threading.Lock()  # the writer is shared by zenoh's thread (wire bytes), the flusher and the views
        self.streams: list[str] = []  # whose Foxglove channels every file registers (a split's next file too)
        self.views: dict[str, FoxgloveView] = {}
        # 4 MiB chunks: the writer keeps an index entry per chunk for the footer (memory grows with
        # their number: ~14 per second with 1 MiB chunks at 640x480 and 30 fps); flushes still close
        # a chunk every flush_s
        self.files = SplitRecorder(output, out, split_bytes=int(split_mb * 2**20), split_s=split_minutes * 60,
                                   on_open=lambda rec: self._opened(rec, settings),
                                   flush_s=flush_s, compression=compression, chunk_size=4 << 20,
                                   flush_on_write=False)  # flushed here, after whole messages (accept)
        self.meter = RateMeter()
        self.counts = {"bad_keys": 0, "view_errors": 0, "unrecorded": 0}
        self._view_kinds: dict[tuple[str, str], int] = {}  # view errors per (stage, kind): each kind logged once
        self.bytes = 0
        self.failure: list[str] = []  # why the file cannot be written (a full disk, a file size limit)
        # A restarted recorder continues its predecessor's account: what that one flushed (its side
        # file, docs/reliability.md) up to what arrives now is in no recording.
        before = load_recorded(output)
        self.restarted = before is not None  # a killed predecessor's side file was found
        self.before: dict[tuple[str, str], int] = before or {}
        self._unnamed: set[tuple[str, str]] = set()  # stages its side file did not name, seen since
        self.on_disk = OnDisk(self.before)  # what is on disk, for a successor (this one's flushes move it)
        self.replays = ReplayFilter()  # the inbox's: a message received before, byte for byte, is stored once
        self.hole_messages = 0
        self.ledger = ArrivalLedger()  # replaced by the inbox's (attach)
        self._last_gap_log: dict[str, float] = {}

    def _opened(self, rec: Recorder, settings: dict[str, str] | None) -> None:
        """A new file (the first, or a split's next): the settings record, then the streams' Foxglove channels."""
        if settings is not None:
            rec.metadata(RECORD_NAME, settings)
        for s in self.streams:
            foxglove.register_channels(rec, s)

    def attach(self, ledger: ArrivalLedger) -> None:
        """The inbox's arrival ledger (what arrived and what never did), seeded with the predecessor's
        account; the side file written at once (killed before its first flush, this recorder's
        successor still knows there was one, and its predecessor's account)."""
        self.ledger = ledger
        for (stream, stage), seq in self.before.items():
            if (gap := ledger.seed(stream, stage, seq)) is not None:
                self._hole(gap)
        with self.lock:
            try:
                save_recorded(self.output, self.on_disk.flushed)
            except OSError as e:
                self._write_failed(e)

    def _hole(self, gap: Gap) -> None:
        self.hole_messages += gap.count
        log.warning("recorder restart: %s/%s seq %d-%d (%d) are in no recording: published while no recorder "
                    "ran, or received by the killed one after its last flush", gap.stream, gap.stage, gap.first,
                    gap.last, gap.count)

    def gap_seen(self, gap: Gap) -> None:
        """Zenoh's thread: seqs of a stage skipped; one line per stage and second at most."""
        if (gap.stream, gap.stage) in self.before and gap.first == self.before[(gap.stream, gap.stage)] + 1:
            self._hole(gap)
            return
        now = time.monotonic()
        if now - self._last_gap_log.get(gap.stage, -1e9) >= 1.0:
            self._last_gap_log[gap.stage] = now
            log.warning("%s/%s: seq %d-%d never arrived (%d; %d of this stage so far): dropped upstream "
                        "(see that stage's stats) or lost in transport", gap.stream, gap.stage, gap.first,
                        gap.last, gap.count, self.ledger.unreceived().get(gap.stage, 0))

    def _write_failed(self, e: OSError) -> None:  # under the lock
        """The first failed write stops the recording, said once and clearly (docs/reliability.md)."""
        if not self.failure:
            self.failure.append(f"cannot write {self.files.rec.path}: {e.strerror or e}")
            log.error("%s; recording stops here (what is on disk stays: `quick-stream recover %s` salvages "
                      "it), and the recorder exits 2", self.failure[0], self.files.rec.path)
            self.files.rec.abandon()
            self.on_failure()

    def _wrote(self, n: int) -> None:  # under the lock
        finished = self.files.wrote(n)
        if finished is not None:
            self._on_disk()  # the finished file holds everything written so far
            log.info("split: finished %s (%d messages), recording to %s", finished, self.files.done[-1][1],
                     self.files.rec.path)

    def _flush_due(self) -> None:  # under the lock
        """Flush the open chunk if ``flush_s`` has passed, and say so in the side file."""
        if self.files.rec.maybe_flush():
            self._on_disk()

    def _on_disk(self) -> None:  # under the lock, right after a flush
        """Everything written so far is on disk: the side file says so (for a successor)."""
        self.on_disk.flushed_now()
        save_recorded(self.output, self.on_disk.flushed)

    def _account(self, stream: str, stage: str, env: tuple[str, int]) -> None:  # under the lock
        """A wire message is written: what the next flush puts on disk; and, after a restart, the hole
        of a stage the predecessor had nothing of on disk (its side file does not name it)."""
        where = (stream, stage)
        newest = self.ledger.newest().get(where)
        self.on_disk.wrote(where, env[0], env[1], newest)
        if self.restarted and newest == env[1] and where not in self.before and where not in self._unnamed:
            self._unnamed.add(where)
            if env[1] > 0:
                self._hole(Gap(stream, stage, 0, env[1] - 1))

    def accept(self, key_expr: str, payload: bytes, t_ns: int) -> None:
        """Zenoh's thread, on arrival: the message (its JPEG in its Foxglove image record) into the
        file's open chunk at once."""
        try:
            stream, stage = keys.parse(key_expr)
        except ValueError as e:
            self.counts["bad_keys"] += 1
            log.error("%s", e)
            return
        t0 = time.perf_counter()
        with self.lock:
            rec = self.files.rec
            if rec.closed:
                self.counts["unrecorded"] += bool(self.failure)  # arrived after the recording failed
                return
            try:
                if self.views_on and stream not in self.streams:  # its channels, before its first message
                    self.streams.append(stream)
                    foxglove.register_channels(rec, stream)
                n = write_message(lambda topic, data: rec.write(topic, data, log_time_ns=t_ns),
                                  key_expr, payload, t_ns, images=self.views_on)
                if env := peek(payload):  # all of its records written: the next flush puts it on disk
                    self._account(stream, stage, env)
                self.bytes += n
                self._wrote(n)
                self._flush_due()
            except OSError as e:
                self.counts["unrecorded"] += 1
                self._write_failed(e)
                return
            self.meter.add((time.perf_counter() - t0) * 1e3)

    def view(self, key_expr: str, payload: bytes, t_ns: int) -> None:
        """The Foxglove channels derived from one message (same log time as its wire message; JPEG
        images were written on arrival). Only messages the inbox took come here: checked, and an ``end``
        only from the stream's own publisher."""
        if (env := peek(payload)) is not None and env[0] == "end":
            log.info("recorded the end of %s", key_expr)  # what a stage's last message was, for operators
        if not self.views_on:
            return
        try:
            stream, stage = keys.parse(key_expr)
        except ValueError:
            return  # counted in accept
        view = self.views.get(stream)
        if view is None:
            view = self.views[stream] = FoxgloveView(stream)  # its channels: registered on its first message
        try:
            converted = list(view.convert(stage, payload, t_ns, jpeg=False))
        except Exception as e:  # noqa: BLE001 - one message's view, never the channel (docs/reliability.md)
            self._view_failed(key_expr, stage, e)
            return
        with self.lock:
            try:
                for topic, data in converted:
                    if self.files.rec.closed:
                        return
                    self.files.rec.write(topic, data, log_time_ns=t_ns)
                    self._wrote(len(data))
            except OSError as e:
                self._write_failed(e)

    def _view_failed(self, key_expr: str, stage: str, e: Exception) -> None:
        """A message whose Foxglove view could not be made: counted, its view skipped, said once per kind
        (stage and error type; a forged message repeated at 30 Hz must not bury the log)."""
        self.counts["view_errors"] += 1
        kind = (stage, type(e).__name__ if not isinstance(e, WireError) else f"WireError:{e.field}")
        n = self._view_kinds[kind] = self._view_kinds.get(kind, 0) + 1
        if n == 1:
            log.error("%s: no Foxglove view of this message (%s: %s); skipped, the channels go on (more of this "
                      "kind are counted in view_errors, not logged)", key_expr, type(e).__name__, e,
                      exc_info=not isinstance(e, WireError))

    def flusher(self, stop: threading.Event) -> None:
        """A thread until ``stop``: the open chunk out every ``flush_s`` (accept flushes too when one is
        due), each flush described in the side file (what is on disk now, for a successor), a time
        split when due even when nothing arrives."""
        while not stop.wait(min(0.1, self.flush_s / 4)):
            with self.lock:
                if self.files.rec.closed:
                    continue
                try:
                    self._flush_due()
                    self._wrote(0)
                except OSError as e:
                    self._write_failed(e)

    def stats(self) -> dict[str, Any]:
        with self.lock:
            ledger = self.ledger  # seqs of each stage that never arrived: no loss upstream is silent
            unreceived = ledger.unreceived()
            return {"state": "error" if self.failure else "running", **({"error": self.failure[0]} if self.failure else {}),
                    "messages": self.files.messages, "bytes": self.bytes, "files": len(self.files.done) + 1,
                    **self.counts, "restart_hole": self.hole_messages, "unreceived": sum(unreceived.values()),
                    **{f"unreceived_{k}": v for k, v in unreceived.items()}, "late": ledger.late,
                    "duplicates": ledger.duplicates, "renumberings": ledger.renumberings,
                    "replays": self.replays.replays, "seq_conflicts": self.replays.conflicts, **self.meter.take("log")}

    def __enter__(self) -> "StreamRecording":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.files.close()
        rec = self.files.rec
        log.info("%s %s: %d messages%s", "abandoned" if self.failure else "closed", rec.path, rec.messages,
                 f" ({len(self.files.done)} earlier files, {self.files.messages} messages in all)"
                 if self.files.done else "")
        if unreceived := self.ledger.unreceived():
            log.warning("never arrived, per stage: %s", unreceived)
        if exc[0] is None:
            recorded_path(self.output).unlink(missing_ok=True)  # a clean stop: no successor continues this account

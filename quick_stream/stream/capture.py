"""A capture's stream on the wire: frames paced, numbered, shed or held, encoded and published, then the end.

:class:`Capture` is what ``quick-stream-capture`` does with a source's frames (the policy is
core's: :mod:`quick_stream.core.pacing`, :mod:`quick_stream.core.shedding`):

* before the first frame: the services named by ``--wait-for`` are up, and a capture restarted
  while its stream was under way continues the numbering after the newest frame any service has
  seen (the stream's cursor);
* each frame: paced (``--pace realtime``: at its own time, shed when offered faster than the
  pipeline takes frames; ``--pace fast``: held until the pipeline has credit for it,
  :class:`OutputCredit`), encoded (or, replaying a recording, its exact bytes re-stamped) and
  published; a frame the source cannot deliver or that cannot be encoded is logged and counted;
* the stream's first frame reaches every frame receiver among ``--wait-for`` before the next
  (a receiver recovers only what follows the first frame it got);
* at the end: the last frame reaches every consumer, then the ``end`` marker goes out through the
  frames' publisher (numbered after the last frame, so it is recovered in order), and the session
  stays open until every receiver has it (the publisher's cache closes with it).
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, fields
from typing import Any, Iterable

import zenoh

from ..core.frame import BadFrame, RGBDFrame
from ..core.pacing import CREDIT_STAGES, CreditWindow, Numbering, Pacer
from ..core.shedding import DEFAULT_LIMITS, ShedLimits, Shedder
from . import keys, topology
from .inbox import TimedPublisher
from .meters import RateMeter
from .runtime import ServiceRuntime
from .wire import EndOfStream, WireError, encode_end, encode_frame
from .wire.codec import unpack
from .wire.messages import restamp_frame

log = logging.getLogger(__name__)

FRAME_RECEIVERS = frozenset(topology.receivers("frame"))  # the services that subscribe to frames
# A stopped capture (SIGTERM: ``up``'s --duration or Ctrl-C) still ends its stream: each of the two end
# waits lasts this long at most (the supervisor's SIGKILL comes 5 s after its SIGTERM); a second signal ends them.
STOPPING_WAIT_S = 2.0


def have(services: set[str]) -> str:
    """``render has`` / ``flow, render have``."""
    return f"{', '.join(sorted(services))} {'has' if len(services) == 1 else 'have'}"


def waited(t0: float, timeout_s: float, cut_short: bool) -> str:
    """How long a wait begun at ``t0`` lasted, in words (``0.1 s (a second signal ended the wait)``)."""
    text = f"{time.monotonic() - t0:.1f} s"
    return text + (" (a signal ended the wait)" if cut_short else f" (waits {timeout_s:g} s at most)")


class OutputCredit:
    """How far the pipeline has got (the motion stage's and the stabilized output's newest frame, from
    their messages), and what capture does with it: ``--pace fast`` holds a frame until the
    :class:`~quick_stream.core.pacing.CreditWindow` lets it go (:meth:`wait_for`; after ``stall_s``
    with no progress it says so and goes on waiting: a stage or the router restarting comes back;
    with nothing downstream at all, use ``--window 0`` or realtime pace); ``--pace realtime``
    (:meth:`admit`) sheds what the pipeline cannot take (:class:`~quick_stream.core.shedding.Shedder`).
    Progress beyond the newest frame sent (:meth:`sending`) is no stage's: it is ignored."""

    def __init__(self, rt: ServiceRuntime, stream: str, window: int, stall_s: float = 10.0,
                 shed: dict[str, ShedLimits] | None = None) -> None:
        self.rt, self.stall_s = rt, stall_s
        self.credit = CreditWindow(window)
        self.shedder = Shedder(shed or {})
        self.waits = 0
        self.newest_sent = -1  # no stage can have reached a later frame: a message saying so is not the pipeline's
        self._cond = threading.Condition()
        if window > 0 or self.shedder.enabled:
            for stage in CREDIT_STAGES:
                rt.subscribe(keys.key(stream, stage), self._on_output)
        if self.shedder.enabled:  # a slow service is up, a restarting one is not (nothing shed for it)
            rt.watch_health(self._on_health)

    def _on_health(self, service: str, up: bool) -> None:
        with self._cond:
            self.shedder.set_up(service, up, time.monotonic())

    def _on_output(self, sample: zenoh.Sample) -> None:
        try:
            r = unpack(sample.payload.to_bytes())
        except WireError:
            return
        seq = r.d.get("seq_next") if r.type == "motion" else r.seq
        if r.type in CREDIT_STAGES and isinstance(seq, int):
            with self._cond:
                if seq > self.newest_sent:  # forged or garbled: one far-future seq switched flow control off
                    return
                self.credit.progressed(r.type, seq)
                self.shedder.progressed(r.type, seq, time.monotonic())
                self._cond.notify_all()

    def sending(self, seq: int) -> None:
        """Frame ``seq`` goes out now (before its put: the stages may answer at once)."""
        with self._cond:
            self.newest_sent = max(self.newest_sent, seq)

    def resume_from(self, seq: int) -> None:
        """A restarted capture: every stage had reached frame ``seq`` (the stream's cursor)."""
        with self._cond:
            self.newest_sent = max(self.newest_sent, seq)
            self.credit.resume_from(seq)
            self.shedder.resume_from(seq)

    def wait_for(self, seq: int) -> None:
        """Fast pace: until frame ``seq`` has credit (or the service stops)."""
        if self.credit.window <= 0:
            return
        deadline = time.monotonic() + self.stall_s
        with self._cond:
            if self.credit.blocked(seq):
                self.waits += 1
            while self.credit.blocked(seq) and not self.rt.stop.is_set():
                if time.monotonic() > deadline:
                    log.warning("no pipeline progress for %.0f s (frame %d waits for the stabilized output to "
                                "reach %d): still waiting; --window 0 sends without flow control", self.stall_s,
                                seq, seq - self.credit.window)
                    deadline = time.monotonic() + self.stall_s
                self._cond.wait(0.05)

    def admit(self, seq: int) -> bool:
        """Realtime pace: send frame ``seq`` (True) or shed it (False, counted)."""
        with self._cond:
            return self.shedder.admit(seq, time.monotonic())


@dataclass(frozen=True)
class CaptureOptions:
    """What a capture is told (the capture service's flags, ``quick-stream-capture -h``)."""

    stream: str
    source: str  # the source's spec, for messages
    pace: str = "realtime"  # realtime: the source's clock, shedding what the pipeline cannot take; fast: as fast as it takes frames
    fps: float | None = None  # the realtime pace's rate (None: the source's)
    speed: float = 1.0  # the realtime pace's speed-up
    frames: int | None = None  # send at most this many
    window: int = 60  # fast pace: frames in flight to the output at most
    shed: str = "on"  # realtime pace: shed what the pipeline cannot take (on) or send every frame (off)
    color: str = "jpeg"  # the frame's colour encoding on the wire
    quality: int = 90  # its JPEG quality
    depth: str = "zstd"  # the depth's encoding
    wait_for: tuple[str, ...] = ()  # the services whose liveliness tokens it waits for before the stream
    wait_timeout: float = 30.0  # ... at most this long (s)
    start_wait: float = 10.0  # the first frames: until every receiver has the frame before the next (s)
    end_wait: float = 10.0  # the end: until the receivers have the last frame, then the end marker (s)

    @classmethod
    def from_flags(cls, flags: Any) -> "CaptureOptions":
        """From the capture service's parsed flags (an object with these attributes; ``wait_for`` the
        flag's comma-separated text)."""
        kw = {f.name: getattr(flags, f.name) for f in fields(cls) if hasattr(flags, f.name)}
        if isinstance(kw.get("wait_for"), str):
            kw["wait_for"] = tuple(s for s in kw["wait_for"].split(",") if s)
        return cls(**kw)


class Capture:
    """One capture service's stream (module docstring), as ``options`` say."""

    def __init__(self, rt: ServiceRuntime, pub: TimedPublisher, options: CaptureOptions,
                 depth_scale: float = 1000.0) -> None:
        self.rt, self.pub, self.options, self.depth_scale = rt, pub, options, depth_scale
        self.wait = list(options.wait_for)
        self.meter = RateMeter()
        self.bad = self.sent = 0
        self.last_seq = -1
        self.shed_logged = -math.inf  # when shedding was last logged
        self.credit: OutputCredit | None = None
        self.numbering = Numbering()
        self.pacer = Pacer(options.fps, options.speed)

    def values(self) -> dict[str, Any]:
        """The capture's stats."""
        c = self.credit
        return {"state": "running", "sent": self.sent, "bad_frames": self.bad,
                "behind_ms": round(self.pacer.behind_ms, 1), "credit_waits": c.waits if c else 0,
                "shed": c.shedder.shed if c else 0, **self.meter.take("send")}

    def start(self) -> int | None:
        """Wait for the ``--wait-for`` services, follow the pipeline, continue a stream under way;
        an exit code when the services never came up."""
        a, rt = self.options, self.rt
        if self.wait:
            missing = rt.wait_for(self.wait, a.wait_timeout)
            if missing and not rt.stop.is_set():
                log.error("services not up after %.0f s: %s", a.wait_timeout, ", ".join(sorted(missing)))
                return 3
        fast = a.pace == "fast"
        self.credit = OutputCredit(rt, a.stream, a.window if fast else 0,
                                   shed=DEFAULT_LIMITS if not fast and a.shed == "on" else None)
        self.numbering = Numbering(rt.stream_cursor("frame"))
        if (resume := self.numbering.resume_after) is not None:
            self.credit.resume_from(resume)
            log.warning("stream %s is under way (frame %d seen downstream; a restarted capture): numbering "
                        "continues after it", a.stream, resume)
        return None

    def send_all(self, items: Iterable[tuple[RGBDFrame | BadFrame, bytes | None]]) -> str:
        """Pace, number, encode and publish every frame (with the recorded message, replaying one);
        returns why it stopped. A source that fails for good ends the stream, said loudly."""
        try:
            return self._send_all(items)
        except Exception as e:  # noqa: BLE001 - a source's own failure, whatever its type
            log.error("source %s failed: %s", self.options.source, e)
            return f"source failed: {e}"

    def _send_all(self, items: Iterable[tuple[RGBDFrame | BadFrame, bytes | None]]) -> str:
        a, rt, credit = self.options, self.rt, self.credit
        assert credit is not None, "start() first"
        self.pacer = pacer = Pacer(a.fps, a.speed)
        for i, (fr, recorded) in enumerate(items):
            if rt.stop.is_set() or (a.frames is not None and i >= a.frames):
                break
            if isinstance(fr, BadFrame):
                self.bad += 1
                log.error("%s: skipped: %s", fr.label, fr.error)
                continue
            if a.pace == "realtime" and (delay := pacer.delay(i, fr.timestamp_ns)) > 0:
                rt.stop.wait(delay)
            credit.wait_for(self.numbering.seq(fr.seq))
            t0 = time.perf_counter()
            seq = self.numbering.seq(fr.seq)
            if not credit.admit(seq):  # offered faster than the pipeline takes frames: skipped, not encoded
                self._shedding()
                continue
            try:
                if recorded is not None:  # a recording: its exact bytes, re-stamped
                    data = restamp_frame(recorded, a.stream, time.time_ns(), seq)
                else:
                    data = encode_frame(fr if seq == fr.seq else fr.with_(seq=seq), a.stream, color=a.color,
                                        quality=a.quality, depth=a.depth, depth_scale=self.depth_scale,
                                        pub_ns=time.time_ns())
            except WireError as e:
                self.bad += 1
                log.error("%s: cannot encode: %s", fr.label, e)
                continue
            credit.sending(seq)
            self.pub.put(data)
            self.sent += 1
            self.last_seq = seq
            self.meter.add((time.perf_counter() - t0) * 1e3)
            if self.sent == 1 and (receivers := FRAME_RECEIVERS & set(self.wait)):
                # the stream's first frame reaches every receiver before the next one: a receiver's link may
                # drop a frame under a burst (no put waits) and it recovers only what follows the first
                # frame it got (seen as frame 0 lost at render in tests/integration/test_netns.py under TLS)
                t_first = time.monotonic()
                if behind := rt.lagging("frame", seq, a.start_wait, required=frozenset(receivers)):
                    log.warning("%s not received the first frame (%d) after %.1f s; going on",
                                have(behind), seq, time.monotonic() - t_first)
                pacer.restart_at(i, fr.timestamp_ns)
            rt.maybe_stats(self.values)
        return "stopped" if rt.stop.is_set() else "source exhausted"

    def _shedding(self) -> None:
        if time.monotonic() - self.shed_logged >= 5.0:
            self.shed_logged = time.monotonic()
            sh = self.credit.shedder
            log.warning("shedding frames: the pipeline is behind (%d sent not through motion, %d not "
                        "stabilized); %d shed so far", sh.in_flight("motion"), sh.in_flight("stabilized"), sh.shed)

    def end(self, reason: str) -> None:
        """The end of the stream: the last frames reach every consumer before the end marker, and the
        end marker every receiver before the session closes. Stopped (a signal), it still waits for
        both, :data:`STOPPING_WAIT_S` each at most, unless another signal comes."""
        rt, wait_s = self.rt, self.options.end_wait
        interrupted = None  # the stop event
        if rt.stop.is_set():
            wait_s, signals = min(wait_s, STOPPING_WAIT_S), getattr(rt, "signals", 0)
            interrupted = lambda: getattr(rt, "signals", 0) > signals  # noqa: E731

        def cut_short() -> bool:
            return interrupted() if interrupted is not None else rt.stop.is_set()

        t0 = time.monotonic()
        if self.sent and (behind := rt.lagging("frame", self.last_seq, wait_s, interrupted=interrupted)):
            log.warning("ending the stream although %s not received frame %d after %s", have(behind),
                        self.last_seq, waited(t0, wait_s, cut_short()))
        # through the frames' publisher: numbered after the last frame, so a receiver whose link dropped it
        # recovers it in order, and no subscriber can hold it (it was a BLOCK put of its own: a viewer that
        # stopped reading held it, and so the end of the stream, until zenoh closed the viewer's link, 5 s)
        self.pub.put(encode_end(EndOfStream(self.last_seq, reason), self.options.stream))
        t0 = time.monotonic()
        if self.sent and (behind := rt.until_ended("frame", wait_s, interrupted=interrupted)):
            log.warning("closing although %s not received the end of the stream after %s", have(behind),
                        waited(t0, wait_s, cut_short()))
        rt.publish_stats({**self.values(), "state": "ended"})
        log.info("sent %d frames (%d bad); %s", self.sent, self.bad, reason)

"""``capture``: a frame source onto ``quick/@v1/<stream>/frame``.

Any source spec (``synthetic[:...]``, ``tum:PATH``, ``mcap:FILE``) is read, paced
at its own timestamps (``--pace realtime``, ``--speed`` to scale) or sent as fast
as possible (``--pace fast``), encoded as ``frame`` messages (JPEG or raw colour,
raw or zstd depth at the source's own depth scale) and published. A frame the
source cannot deliver is logged with its reason and counted; the stream goes on.
A recording (``mcap:``) is replayed exactly: each frame message is sent as
recorded (only re-addressed to ``--stream`` and re-stamped), unless ``--reencode``.
At the end an ``end`` message follows the last frame. ``--wait-for`` holds the
first frame until the named services are up, so a run loses nothing at start-up.
"""
from __future__ import annotations

import logging
import math
import signal
import sys
import threading
import time

import zenoh

from quick_stream.core.frame import BadFrame
from quick_stream.core.shedding import DEFAULT_LIMITS, ShedLimits, Shedder
from quick_stream.io.sources import SourceError, open_source
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.meters import RateMeter
from quick_stream.stream.runtime import ServiceRuntime, TimedPublisher, service_main, service_parser
from quick_stream.stream.wire import EndOfStream, WireError, encode_end, encode_frame
from quick_stream.stream.wire.codec import unpack
from quick_stream.stream.wire.messages import restamp_frame

log = logging.getLogger("capture")


def build_parser():
    p = service_parser("capture", __doc__)
    p.add_argument("--source", default="synthetic",
                   help="synthetic[:k=v,...] (default), tum:PATH, mcap:FILE or depthai[:DEVICE_ID][,width=W,height=H,fps=F]")
    p.add_argument("--list-devices", action="store_true", help="list the OAK (depthai) devices visible and exit")
    p.add_argument("--frames", type=at.positive_int, default=None, help="send at most this many frames")
    p.add_argument("--pace", choices=("realtime", "fast"), default="realtime",
                   help="realtime: at the frames' own timestamps (default); fast: as fast as the pipeline "
                        "takes them (at most --window frames ahead of the last stabilized one)")
    p.add_argument("--window", type=at.nonneg_int, default=60,
                   help="fast pace: frames in flight before waiting for stabilized output (default 60; "
                        "a third of it for the motion stage; 0: no limit)")
    p.add_argument("--shed", choices=("on", "off"), default="on",
                   help="realtime pace: frames offered faster than the pipeline takes them are shed (skipped "
                        "before encoding, evenly spaced, counted in 'shed'; default on; docs/reliability.md)")
    p.add_argument("--speed", type=at.positive_float, default=1.0, help="realtime pacing speed factor (default 1)")
    p.add_argument("--fps", type=at.positive_float, default=None,
                   help="override the pacing rate (frames/s; realtime only)")
    p.add_argument("--color", choices=("jpeg", "raw"), default="jpeg", help="colour encoding (default jpeg)")
    p.add_argument("--quality", type=at.quality, default=90, help="JPEG quality, 1-100 (default 90)")
    p.add_argument("--depth", choices=("raw", "zstd"), default="zstd", help="depth encoding (default zstd)")
    p.add_argument("--reencode", action="store_true",
                   help="mcap sources: re-encode frames with --color/--depth instead of sending the recorded bytes")
    p.add_argument("--history", type=at.int_in(0), default=150,
                   help="frames kept for a restarted flow or render service to take over from (default 150, "
                        "5 s at 30 fps, what render holds at most by default; at least 150 are kept for receivers to recover "
                        "what their link dropped)")
    p.add_argument("--wait-for", type=at.service_names, default="", metavar="S1,S2",
                   help="services (of this stream) to wait for before the first frame, e.g. flow,motion,render")
    p.add_argument("--wait-timeout", type=at.nonneg_float, default=30.0, help="seconds to wait for them (default 30)")
    p.add_argument("--start-wait", type=at.nonneg_float, default=10.0,
                   help="with --wait-for: seconds to wait until the receivers of frames among them (flow, render, "
                        "recorder) have the first frame before sending the next (default 10)")
    p.add_argument("--end-wait", type=at.nonneg_float, default=10.0,
                   help="at the end, seconds to wait until every consumer has received the last frame before "
                        "sending the end marker, and again until they have the end marker before closing "
                        "(default 10)")
    return p


class OutputCredit:
    """How far the pipeline has got (the motion stage's and the stabilized output's newest frame, from
    their messages), and what capture does with it.

    ``--pace fast`` (:meth:`wait_for`): hold frame ``seq`` until the stabilized output has reached
    ``seq - window`` and the motion stage ``seq - window // 3``, so a replay runs as fast as the
    slowest stage without overrunning its drop-oldest queue (flow holds 30 frames; output lags by a
    segment, so the output window must be wider). After ``stall_s`` with no progress it says so and
    goes on waiting: a stage or the router restarting comes back (sending without flow control then
    overran the stages and lost frames); with nothing downstream at all, use ``--window 0`` or
    realtime pace.

    ``--pace realtime`` (:meth:`admit`): a live source cannot wait, so frames offered faster than the
    pipeline takes them are shed before they are encoded (:class:`quick_stream.core.shedding.Shedder`).
    """

    def __init__(self, rt: ServiceRuntime, stream: str, window: int, stall_s: float = 10.0,
                 shed: dict[str, ShedLimits] | None = None) -> None:
        self.rt, self.window, self.stall_s = rt, window, stall_s
        self.shedder = Shedder(shed or {})
        self.done = {"stabilized": -1, "motion": -1}
        self.waits = 0
        self._cond = threading.Condition()
        if window > 0 or self.shedder.enabled:
            for stage in self.done:
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
        if r.type in self.done and isinstance(seq, int):
            with self._cond:
                self.done[r.type] = max(self.done[r.type], seq)
                self.shedder.progressed(r.type, seq, time.monotonic())
                self._cond.notify_all()

    def _blocked(self, seq: int) -> bool:
        return seq - self.done["stabilized"] > self.window or seq - self.done["motion"] > self.window // 3

    def resume_from(self, seq: int) -> None:
        """A restarted capture: the stream had reached frame ``seq`` downstream (the cursor), so the
        credit counts from there, not from -1 (it waited for output the idle pipeline never made,
        10 s, then sent without flow control and overran the stages)."""
        with self._cond:
            for stage in self.done:
                self.done[stage] = max(self.done[stage], seq)
            self.shedder.resume_from(seq)

    def wait_for(self, seq: int) -> None:
        if self.window <= 0:
            return
        deadline = time.monotonic() + self.stall_s
        with self._cond:
            if self._blocked(seq):
                self.waits += 1
            while self._blocked(seq) and not self.rt.stop.is_set():
                if time.monotonic() > deadline:
                    log.warning("no pipeline progress for %.0f s (frame %d waits for the stabilized output to "
                                "reach %d): still waiting; --window 0 sends without flow control", self.stall_s,
                                seq, seq - self.window)
                    deadline = time.monotonic() + self.stall_s
                self._cond.wait(0.05)

    def admit(self, seq: int) -> bool:
        """Realtime pace: send frame ``seq`` (True) or shed it (False, counted)."""
        with self._cond:
            return self.shedder.admit(seq, time.monotonic())


def list_devices() -> int:
    from quick_stream.io.sources.oak_device import list_devices as devices

    try:
        found = devices()
    except ImportError as e:
        log.error("%s", e)
        return 2
    if not found:
        print("no OAK device found (check the USB cable, the udev rule, or Docker's /dev/bus/usb mapping)")
        return 1
    for d in found:
        print(f"{d['id']}  {d['name']}  {d['state']}  {d['platform']}")
    return 0


def run(args, conf: zenoh.Config) -> int:
    try:
        source = open_source(args.source)
    except SourceError as e:
        log.error("%s", e)
        return 2
    depth_scale = float(getattr(source, "depth_scale", 1000.0))
    if callable(getattr(source, "open", None)):  # a live device: there, or a clear error before the stream
        stopping = threading.Event()
        source.stop = stopping
        prev = signal.signal(signal.SIGTERM, lambda *_: stopping.set())  # retries give up at once
        try:
            source.open()
        except Exception as e:  # noqa: BLE001 - NoDevice, depthai's errors: the camera cannot be used
            if stopping.is_set():
                log.info("stopped while opening %s", args.source)
                return 0
            log.error("source %s cannot be opened: %s", args.source, e)
            return 2  # a configuration problem: the supervisor does not restart it
        finally:
            signal.signal(signal.SIGTERM, prev)
        if stopping.is_set():
            return 0
    with ServiceRuntime("capture", args.stream, conf) as rt:
        if hasattr(source, "stop"):
            source.stop = rt.stop  # reconnection retries end when the service is asked to stop
        pub = rt.publisher("frame", lossless=True, cache=args.history)  # lost only where counted (inboxes)
        rt.ready()
        wait = [s for s in args.wait_for.split(",") if s]
        if wait:
            missing = rt.wait_for(wait, args.wait_timeout)
            if missing and not rt.stop.is_set():
                log.error("services not up after %.0f s: %s", args.wait_timeout, ", ".join(sorted(missing)))
                return 3
        fast = args.pace == "fast"
        credit = OutputCredit(rt, args.stream, args.window if fast else 0,
                              shed=DEFAULT_LIMITS if not fast and args.shed == "on" else None)
        st = CaptureStats(credit)
        st.resume_after = rt.stream_cursor("frame")
        if st.resume_after is not None:
            credit.resume_from(st.resume_after)
            log.warning("stream %s is under way (frame %d seen downstream; a restarted capture): numbering "
                        "continues after it", args.stream, st.resume_after)
        replay = getattr(source, "iter_with_messages", None)
        # an exact replay sends the recorded bytes: their pixels are decoded (and checked) by the receivers
        items = replay(pixels=False) if replay is not None and not args.reencode else ((f, None) for f in source)
        try:
            reason = send_all(args, rt, pub, items, credit, st, depth_scale)
        except Exception as e:  # noqa: BLE001 - a source that fails for good ends the stream, said loudly
            log.error("source %s failed: %s", args.source, e)
            reason = f"source failed: {e}"
        if st.sent:  # the last frames reach every consumer before the end marker, and before the session closes
            behind = rt.lagging("frame", st.last_seq, args.end_wait)
            if behind:
                log.warning("ending the stream although %s have not received frame %d after %.0f s",
                            ", ".join(sorted(behind)), st.last_seq, args.end_wait)
        # through the frames' publisher: numbered after the last frame, so a receiver whose link dropped it
        # recovers it in order, and no subscriber can hold it (it was a BLOCK put of its own: a viewer that
        # stopped reading held it, and so the end of the stream, until zenoh closed the viewer's link, 5 s)
        pub.put(encode_end(EndOfStream(st.last_seq, reason), args.stream))
        if st.sent and (behind := rt.until_ended("frame", args.end_wait)):
            log.warning("closing although %s have not received the end of the stream after %.0f s",
                        ", ".join(sorted(behind)), args.end_wait)
        rt.publish_stats({**st.values(), "state": "ended"})
        log.info("sent %d frames (%d bad); %s", st.sent, st.bad, reason)
    return 1 if reason.startswith("source failed") else 0


FRAME_RECEIVERS = frozenset({"flow", "render", "recorder"})  # the services that subscribe to frames


class CaptureStats:
    """Capture's counters, published as its stats."""

    def __init__(self, credit: OutputCredit) -> None:
        self.credit = credit
        self.meter = RateMeter()
        self.bad = self.sent = 0
        self.last_seq = -1
        self.behind_ms = 0.0
        self.shed_logged = -math.inf  # when shedding was last logged
        self.resume_after: int | None = None  # the stream's newest frame seq when this capture started
        self.offset: int | None = None  # added to the source's seq (0, or the continuation of the stream)

    def seq(self, source_seq: int) -> int:
        """The stream seq of a source frame: the source's own, or continuing after ``resume_after``."""
        if self.offset is None:
            self.offset = 0 if self.resume_after is None else max(0, self.resume_after + 1 - source_seq)
        return source_seq + self.offset

    def values(self) -> dict:
        return {"state": "running", "sent": self.sent, "bad_frames": self.bad, "behind_ms": round(self.behind_ms, 1),
                "credit_waits": self.credit.waits, "shed": self.credit.shedder.shed, **self.meter.take("send")}


def send_all(args, rt: ServiceRuntime, pub: TimedPublisher, items, credit: OutputCredit, st: CaptureStats,
             depth_scale: float) -> str:
    """Pace, encode and publish every frame; returns why it stopped."""
    t_start, ts0 = time.monotonic(), None
    period = None if args.fps is None else 1.0 / args.fps
    for i, (fr, recorded) in enumerate(items):
        if rt.stop.is_set() or (args.frames is not None and i >= args.frames):
            break
        if isinstance(fr, BadFrame):
            st.bad += 1
            log.error("%s: skipped: %s", fr.label, fr.error)
            continue
        if args.pace == "realtime":
            if ts0 is None:
                ts0 = fr.timestamp_ns
            due = t_start + (i * period if period else (fr.timestamp_ns - ts0) / 1e9 / args.speed)
            delay = due - time.monotonic()
            if delay > 0:
                rt.stop.wait(delay)
            st.behind_ms = max(0.0, -delay * 1e3)
        credit.wait_for(st.seq(fr.seq))
        t0 = time.perf_counter()
        seq = st.seq(fr.seq)
        if not credit.admit(seq):  # offered faster than the pipeline takes frames: skipped, not encoded
            if time.monotonic() - st.shed_logged >= 5.0:
                st.shed_logged = time.monotonic()
                sh = credit.shedder
                log.warning("shedding frames: the pipeline is behind (%d sent not through motion, %d not "
                            "stabilized); %d shed so far", sh.in_flight("motion"), sh.in_flight("stabilized"),
                            sh.shed)
            continue
        try:
            if recorded is not None:  # a recording: its exact bytes, re-stamped
                data = restamp_frame(recorded, args.stream, time.time_ns(), seq)
            else:
                data = encode_frame(fr if seq == fr.seq else fr.with_(seq=seq), args.stream, color=args.color,
                                    quality=args.quality, depth=args.depth, depth_scale=depth_scale,
                                    pub_ns=time.time_ns())
        except WireError as e:
            st.bad += 1
            log.error("%s: cannot encode: %s", fr.label, e)
            continue
        pub.put(data)
        st.sent += 1
        st.last_seq = seq
        st.meter.add((time.perf_counter() - t0) * 1e3)
        if st.sent == 1 and (receivers := FRAME_RECEIVERS & set(args.wait_for.split(","))):
            # the stream's first frame reaches every receiver before the next one: a receiver's link may
            # drop a frame under a burst (no put waits) and it recovers only what follows the first
            # frame it got (the netns TLS test lost frame 0 at render that way, 2 runs in 7)
            if behind := rt.lagging("frame", seq, args.start_wait, required=frozenset(receivers)):
                log.warning("%s have not received the first frame (%d) after %.0f s; going on",
                            ", ".join(sorted(behind)), seq, args.start_wait)
            t_start, ts0 = time.monotonic() - (i * period if period else 0.0), fr.timestamp_ns
        rt.maybe_stats(st.values)
    return "stopped" if rt.stop.is_set() else "source exhausted"


def main(argv: list[str] | None = None) -> int:
    return service_main("capture", build_parser(), run, argv, early=lambda a: list_devices() if a.list_devices else None)


if __name__ == "__main__":
    sys.exit(main())

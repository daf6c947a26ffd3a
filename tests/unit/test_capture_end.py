"""The end of a capture's stream (quick_stream/stream/capture.py): its waits, and what it says about them."""
from __future__ import annotations

import logging
import threading
import time

from quick_stream.stream import capture as capture_module
from quick_stream.stream.capture import Capture, CaptureOptions
from quick_stream.stream.cursor import Cursors


class Rt:
    """A runtime whose receivers never catch up: each wait lasts until its timeout or its interruption."""

    def __init__(self, stopped: bool) -> None:
        self.stop = threading.Event()
        if stopped:
            self.stop.set()
            self.signals = 1
        else:
            self.signals = 0
        self.timeouts: list[float] = []

    def _wait(self, timeout_s, interrupted, behind):
        self.timeouts.append(timeout_s)
        interrupted = interrupted or self.stop.is_set
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not interrupted():
            time.sleep(0.01)
        return behind

    def lagging(self, stage, seq, timeout_s, required=frozenset(), interrupted=None):
        return self._wait(timeout_s, interrupted, {"render"})

    def until_ended(self, stage, timeout_s, interrupted=None):
        return self._wait(timeout_s, interrupted, {"recorder", "render"})

    def publish_stats(self, values) -> None:
        pass


class Pub:
    def put(self, data) -> None:
        pass


def capture(rt: Rt, end_wait: float) -> Capture:
    from services.capture import build_parser

    args = build_parser().parse_args(["--source", "synthetic", "--end-wait", str(end_wait)])
    c = Capture(rt, Pub(), CaptureOptions.from_flags(args))
    c.sent, c.last_seq = 27, 26
    return c


def warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def test_a_stopped_capture_says_how_long_it_waited_and_a_second_signal_ends_the_wait(caplog):
    """``up`` stopped the capture (SIGTERM) and it logged "recorder have not received the end of the
    stream after 10 s" 55 ms later: the waits had returned at once (the stop), the message said the
    timeout. Stopped, it now waits (2 s at most each) and says how long it did."""
    rt = Rt(stopped=True)
    c = capture(rt, end_wait=10.0)
    threading.Timer(0.3, lambda: setattr(rt, "signals", 2)).start()  # a second signal 0.3 s in
    with caplog.at_level(logging.WARNING):
        t0 = time.monotonic()
        c.end("stopped")
    took = time.monotonic() - t0
    assert rt.timeouts == [capture_module.STOPPING_WAIT_S] * 2 == [2.0, 2.0]
    assert 0.3 <= took < 1.0
    got = warnings(caplog)
    assert got[0].startswith("ending the stream although render has not received frame 26 after 0.3 s "
                             "(a signal ended the wait)"), got
    assert got[1] == "closing although recorder, render have not received the end of the stream after 0.0 s (a " \
                     "signal ended the wait)", got
    assert not any("10 s" in m for m in got)


def test_a_wait_that_times_out_says_its_real_length(caplog):
    rt = Rt(stopped=False)
    c = capture(rt, end_wait=0.2)
    with caplog.at_level(logging.WARNING):
        c.end("source exhausted")
    got = warnings(caplog)
    assert got == ["ending the stream although render has not received frame 26 after 0.2 s (waits 0.2 s at most)",
                   "closing although recorder, render have not received the end of the stream after 0.2 s "
                   "(waits 0.2 s at most)"], got


def test_the_cursor_waits_go_on_after_the_stop_when_told(monkeypatch):
    """Cursors.lagging / until_ended: ``interrupted`` replaces the stop event as what ends the wait early."""

    class C(Cursors):
        service, stream = "capture", "cam0"

        def __init__(self) -> None:
            self.stop = threading.Event()
            self.stop.set()

        def alive(self, stream=None):
            return {"capture", "render"}

        def _cursor_answers(self):
            yield "render", {"frame": 3}

    c = C()
    t0 = time.monotonic()
    assert c.lagging("frame", 5, 0.3) == {"render"} and time.monotonic() - t0 < 0.1  # the stop: at once
    t0 = time.monotonic()
    assert c.lagging("frame", 5, 0.3, interrupted=lambda: False) == {"render"}
    assert c.until_ended("frame", 0.3, interrupted=lambda: False) == {"render"}
    assert time.monotonic() - t0 >= 0.6

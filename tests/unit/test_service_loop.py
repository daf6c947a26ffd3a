"""The runtime's one service loop (quick_stream/stream/loop.py), without a zenoh session.

The runtime is the real :class:`ServiceRuntime` with its session left out (its stats go to a list):
messages are dispatched per type, bad ones counted and logged, an exception in a handler contained
and counted, an ``end`` lets a taking-over inbox take everything again, ``take`` and ``paused``
decide what each pass reads, and the last stats say how the service stopped.
"""
from __future__ import annotations

import logging
import threading
from types import SimpleNamespace
from unittest.mock import patch

import numpy as np
import pytest

from quick_stream.core.motion import MotionEstimate
from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.stream.runtime import Inbox, Input, ServiceRuntime
from quick_stream.stream.wire import EndOfStream, Stats, decode, encode_end, encode_frame, encode_motion, encode_stats

FRAME = next(iter(SyntheticSource(width=64, height=48, frames=1)))


class StatsSink:
    def __init__(self) -> None:
        self.sent: list[dict] = []

    def put(self, data: bytes) -> None:
        self.sent.append(decode(data).obj.values)


def bare_runtime() -> ServiceRuntime:
    """A ServiceRuntime of service ``t`` on stream cam0 with no session: inboxes and stats only."""
    rt = ServiceRuntime.__new__(ServiceRuntime)
    rt.service, rt.stream, rt.stop, rt._cond = "t", "cam0", threading.Event(), threading.Condition()
    rt._inboxes, rt._subs, rt._pubs, rt._timed = [], [], [], []
    rt.errors, rt.stats_source, rt.settings = {}, None, ""
    rt._stats_seq, rt._stats_period, rt._next_stats = 0, 3600.0, float("inf")
    rt._stats_pub = StatsSink()
    return rt


def inbox(rt: ServiceRuntime, *payloads: bytes, key: str = "quick/@v1/cam0/frame") -> Inbox:
    box = Inbox(1000, rt._cond)
    rt._inboxes.append(box)
    for data in payloads:
        box._on_sample(SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda d=data: d)))
    return box


def frame(seq: int) -> bytes:
    return encode_frame(FRAME.with_(seq=seq), "cam0", color="raw", depth="raw")


def end(seq: int, stream: str = "cam0") -> bytes:
    return encode_end(EndOfStream(seq, "done"), stream)


def stop_when_empty(rt: ServiceRuntime, *boxes: Inbox):
    return lambda: rt.stop.set() if not any(len(b) for b in boxes) else None


def test_messages_are_dispatched_per_type_and_bad_ones_counted_and_contained(caplog):
    rt = bare_runtime()
    box = inbox(rt, frame(0), b"\xc1 not msgpack", frame(1), encode_stats(Stats("x", {}), "cam0", 0), end(9, "cam9"),
                frame(2), end(2))
    box.skip_through = -1  # a service taking over: an end makes it take everything again
    got: list[tuple[str, int]] = []

    def on_frame(msg) -> None:
        got.append(("frame", msg.seq))
        if msg.seq == 1:
            raise RuntimeError("a bug")

    stopped: list[bool] = []
    with caplog.at_level(logging.ERROR):
        rt.serve([Input(box, {"frame": on_frame, "end": lambda m: got.append(("end", m.seq))},
                        label=lambda m: f"frame number {m.seq}")],
                 lambda: {"mine": len(got)}, tick=stop_when_empty(rt, box), on_stop=lambda: stopped.append(True))
    assert got == [("frame", 0), ("frame", 1), ("frame", 2), ("end", 2)]
    assert box.skip_through is None and stopped == [True]
    last = rt._stats_pub.sent[-1]
    assert last["state"] == "stopped" and last["mine"] == 4
    # garbage, stats on the frame key, cam9's end: refused on arrival, never queued (issue 30 row 6)
    assert last["inbox0_invalid"] == 3 and last["decode_errors"] == 0 and last["internal_errors"] == 1
    text = caplog.text
    assert "quick/@v1/cam0/frame: message refused on arrival: wire: not valid msgpack" in text
    assert "stats message on the frame key" in text and "message of stream 'cam9'" in text
    assert "cam0/t: frame number 1 failed (RuntimeError: a bug)" in text


def test_pending_takes_only_what_was_queued_and_a_paused_input_waits():
    rt = bare_runtime()
    first = inbox(rt, frame(0), end(0), frame(1))
    second = inbox(rt, frame(10), frame(11))
    order: list[str] = []
    state = {"paused": False}

    def on_first(msg) -> None:
        order.append(f"a{msg.seq}")
        if msg.type == "end":
            state["paused"] = True

    def on_second(msg) -> None:
        order.append(f"b{msg.seq}")
        if msg.seq == 10:  # arrives while the second input is being read: for the next pass
            second._on_sample(SimpleNamespace(key_expr="quick/@v1/cam0/frame",
                                              payload=SimpleNamespace(to_bytes=lambda: frame(12))))

    passes: list[list[str]] = []

    def tick() -> None:
        passes.append(list(order))
        order.clear()
        if len(passes) == 2:
            state["paused"] = False
        if len(passes) == 3:
            rt.stop.set()

    rt.serve([Input(first, {"frame": on_first, "end": on_first}, take="all", paused=lambda: state["paused"]),
              Input(second, {"frame": on_second}, take="pending")], lambda: {}, tick=tick)
    assert passes == [["a0", "a0", "b10", "b11"], ["b12"], ["a1"]]


def test_an_input_has_handlers_or_a_raw_handler_and_a_known_take():
    rt = bare_runtime()
    box = inbox(rt)
    with pytest.raises(ValueError, match="either"):
        Input(box)
    with pytest.raises(ValueError, match="take"):
        Input(box, {"frame": None}, take="some")


def test_raw_inputs_get_every_valid_item_undecoded_and_the_final_state_is_the_services():
    rt = bare_runtime()
    arrived: list[bytes] = []
    box = Inbox(1000, rt._cond, on_arrival=lambda k, d, t: arrived.append(d))
    rt._inboxes.append(box)
    for data in (b"anything", frame(3)):
        box._on_sample(SimpleNamespace(key_expr="quick/@v1/cam0/frame",
                                       payload=SimpleNamespace(to_bytes=lambda d=data: d)))
    seen: list[tuple[str, bytes]] = []
    rt.serve([Input(box, raw=lambda k, d, t: seen.append((k, d)))], lambda: {}, tick=stop_when_empty(rt, box),
             final_state=lambda: "error")
    assert arrived == [b"anything", frame(3)]  # on arrival: every message (the recorder records them all)
    assert [d for _, d in seen] == [frame(3)]  # queued: those that pass the check
    assert rt._stats_pub.sent[-1]["state"] == "error" and "decode_errors" not in rt._stats_pub.sent[-1]


def motion(seq: int) -> bytes:
    m = np.eye(4)
    m[:3, 3] = (0.01 * seq, 0.0, 0.02)
    return encode_motion(MotionEstimate(seq, seq + 1, "se3", "exact", m, np.zeros(6), True, "", 100, 1.0, 0.1, None),
                         "cam0")


def test_the_newest_message_its_check_decoded_whole_is_handled_as_the_check_decoded_it():
    rt = bare_runtime()
    box = inbox(rt, motion(0), motion(1), key="quick/@v1/cam0/motion")
    checked = box.arrivals.last[1]  # the newest one's decode on arrival
    got: list = []
    rt.serve([Input(box, {"motion": got.append})], lambda: {}, tick=stop_when_empty(rt, box))
    assert [m.seq for m in got] == [0, 1]
    assert got[1] is checked  # not decoded again (a flow's decode costs ~0.35 ms)
    assert got[0] is not checked and np.array_equal(got[0].obj.matrix[:3, 3], (0.0, 0.0, 0.02))  # an older one is
    assert np.array_equal(got[1].obj.matrix, decode(motion(1)).obj.matrix)


def test_a_frame_is_decoded_whole_again_after_its_check():
    rt = bare_runtime()
    box = inbox(rt, frame(0))
    assert box.arrivals.last is None  # the check left its pixels out: nothing to reuse
    got: list = []
    rt.serve([Input(box, {"frame": got.append})], lambda: {}, tick=stop_when_empty(rt, box))
    assert np.array_equal(got[0].obj.color, FRAME.color) and np.array_equal(got[0].obj.depth, FRAME.depth)


def test_a_message_its_input_does_not_admit_is_let_go_undecoded_and_a_lazy_input_gets_its_bytes():
    """``admit`` is asked before anything is decoded (the flow service's shedding); a ``lazy`` input's
    frames are checked but their pixels left undecoded, the bytes handed on for later (render)."""
    rt = bare_runtime()
    jpeg = [encode_frame(FRAME.with_(seq=seq), "cam0", color="jpeg", depth="zstd") for seq in (0, 1)]
    box = inbox(rt, *jpeg, b"garbage", end(1))
    asked: list[bytes] = []
    got: list = []

    def admit(key: str, payload: bytes) -> bool:
        asked.append(payload)
        return payload != jpeg[1]

    rt.serve([Input(box, {"frame": got.append, "end": got.append}, admit=admit, lazy=True)], lambda: {},
             tick=stop_when_empty(rt, box))
    assert asked == [*jpeg, end(1)]  # the garbage was refused on arrival: never queued, never asked
    assert [(m.type, m.seq) for m in got] == [("frame", 0), ("end", 1)]  # frame 1 let go
    assert box.arrivals.invalid == 1 and rt.errors["decode_errors"] == 0
    assert got[0].payload == jpeg[0] and not got[0].obj.color.any() and not got[0].obj.depth.any()
    assert decode(got[0].payload).obj.color.any()  # decoded when asked


def test_a_frames_depth_is_decompressed_once_when_its_inbox_keeps_it():
    """The flow service's inbox keeps the depth stream its check decompressed (``keep_depth_bytes``) for
    the decode of the very same bytes: the frame decodes bit for bit as a plain decode, and what was
    kept is forgotten once taken, or beyond the budget (the oldest first)."""
    rt = bare_runtime()
    zstd = [encode_frame(FRAME.with_(seq=seq), "cam0", color="jpeg", depth="zstd") for seq in range(4)]
    box = inbox(rt)
    raw = len(decode(zstd[0], pixels=False).depth_raw)
    box.arrivals.keep_depth_bytes = 3 * raw  # three frames' depth
    for data in zstd:
        box._on_sample(SimpleNamespace(key_expr="quick/@v1/cam0/frame", payload=SimpleNamespace(to_bytes=lambda d=data: d)))
    queued = [item[1] for item in box._q]
    assert box.arrivals.depth_of(queued[0]) is None  # the oldest, forgotten for room
    assert box.arrivals.depth_of(bytes(bytearray(zstd[1]))) is None  # equal bytes, another object: not the check's
    box._q.popleft()
    taken: list = []
    with patch("quick_stream.stream.wire.pixels._decompress", side_effect=AssertionError("decompressed again")):
        rt.serve([Input(box, {"frame": taken.append}, color="luma")], lambda: {}, tick=stop_when_empty(rt, box))
    assert [m.seq for m in taken] == [1, 2, 3] and not box.arrivals._depths and box.arrivals._depth_bytes == 0
    for m, data in zip(taken, zstd[1:]):
        assert np.array_equal(m.obj.depth, decode(data, color="luma").obj.depth) and m.depth_raw is None


def test_a_lazy_inputs_frames_are_not_decompressed_again_after_their_check_on_arrival():
    rt = bare_runtime()
    box = inbox(rt, encode_frame(FRAME.with_(seq=0), "cam0", color="jpeg", depth="zstd"))
    got: list = []
    with patch("quick_stream.stream.wire.pixels._decompress", side_effect=AssertionError("decompressed again")):
        rt.serve([Input(box, {"frame": got.append}, lazy=True)], lambda: {}, tick=stop_when_empty(rt, box))
    assert [m.seq for m in got] == [0] and got[0].depth_raw is None and not got[0].obj.depth.any()

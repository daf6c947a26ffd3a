"""The services' inbox: drop-oldest bound, and what a service taking over skips and catches up on."""
import threading
from types import SimpleNamespace

from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.stream.runtime import Inbox
from quick_stream.stream.wire import encode_end, encode_frame
from quick_stream.stream.wire.codec import pack, peek
from quick_stream.stream.wire.messages import EndOfStream

FRAME = next(iter(SyntheticSource(width=64, height=48, frames=1)))


def sample(seq: int, mtype: str = "frame", data: bytes | None = None):
    if data is None:
        data = encode_end(EndOfStream(seq, "done"), "cam0") if mtype == "end" else encode_frame(FRAME.with_(seq=seq), "cam0")
    return SimpleNamespace(key_expr="quick/@v1/cam0/frame", payload=SimpleNamespace(to_bytes=lambda: data))


def test_a_history_replay_neither_crowds_out_nor_drops_what_a_taking_over_service_needs():
    box = Inbox(5, threading.Condition())
    box.skip_through = 93  # the predecessor's output went up to frame 93
    box.capacity = 40  # catching up
    for seq in range(0, 130):  # the capture's history, then live frames
        box._on_sample(sample(seq))
    assert box.skipped == 94 and box.dropped == 0
    got = []
    while (item := box.pop()) is not None:
        got.append(item)
    assert len(got) == 36 and box.capacity == 5  # all of 94..129, then back to the live bound once drained
    for seq in range(130, 140):
        box._on_sample(sample(seq))
    assert box.dropped == 5 and len(box) == 5


def test_a_history_replay_arriving_after_live_messages_is_still_held():
    """The replay of the publishers' caches can arrive after the first live messages, when the queue
    has already drained once and fallen back to its live bound: it must not be dropped then."""
    box = Inbox(5, threading.Condition())
    box.skip_through = 65
    box.capacity = box.catch_up = 150
    for seq in (120, 121):  # live frames first
        box._on_sample(sample(seq))
    while box.pop() is not None:
        pass
    assert box.capacity == 5  # drained: back to the live bound
    for seq in range(0, 120):  # then the history: 66..119 are owed
        box._on_sample(sample(seq))
    assert box.dropped == 0 and len(box) == 54 and box.skipped == 66
    assert peek(box.pop()[1]) == ("frame", 66)  # the oldest owed frame comes first


def test_a_history_replay_in_pieces_keeps_the_catch_up_bound_while_the_queue_drains_between_them():
    """A restarted flow got the first frames of its history, drained them, fell back to the live
    bound and dropped 17 of the rest of the replay (router and flow killed together). Within the
    catch-up time a drained queue keeps the catch-up bound."""
    import time

    box = Inbox(5, threading.Condition())
    box.skip_through = 70
    box.capacity = box.catch_up = 150
    box.catch_up_until = time.monotonic() + 60.0  # still catching up
    for seq in range(0, 73):  # the first piece of the replay: 71, 72 owed
        box._on_sample(sample(seq))
    while box.pop() is not None:
        pass
    assert box.capacity == 150
    for seq in range(73, 120):  # the rest of it, more than the live bound
        box._on_sample(sample(seq))
    assert box.dropped == 0 and len(box) == 47
    box.catch_up_until = 0.0  # once the catch-up time is over, the next drain goes back to the live bound
    while box.pop() is not None:
        pass
    assert box.capacity == 5


def test_end_markers_are_never_skipped():
    box = Inbox(5, threading.Condition())
    box.skip_through = 10
    box._on_sample(sample(3, "end"))
    assert len(box) == 1 and box.skipped == 0


def test_a_message_that_fails_the_check_is_queued_but_never_skipped_or_accounted():
    """A malformed frame with a far-future seq: its consumer still gets it (to log why it is refused),
    but the skips and the arrival ledger (the restart cursor) never read its seq."""
    box = Inbox(5, threading.Condition())
    box.skip_through = 10
    box._on_sample(sample(11))
    box._on_sample(sample(0, data=pack({}, "frame", "cam0", 10**12)))
    box._on_sample(sample(3))  # owed? no: <= skip_through, skipped
    box._on_sample(sample(12))
    assert len(box) == 3 and box.skipped == 1 and box.arrivals.invalid == 1
    assert box.arrivals.newest() == {("cam0", "frame"): 12} and box.arrivals.unreceived() == {}


def test_the_status_board_counts_bad_stats_messages_and_keeps_only_good_ones():
    from quick_stream.stream.launcher import StatusBoard
    from quick_stream.stream.wire import Stats, encode_stats

    subs = []
    board = StatusBoard(SimpleNamespace(declare_subscriber=lambda key, cb: subs.append(cb) or SimpleNamespace()))

    def put(key: str, data: bytes) -> None:
        subs[0](SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: data)))

    put("quick/@v1/cam0/stats", encode_stats(Stats("flow", {"frames": 7}), "cam0", 0))
    put("quick/@v1/cam0/stats", b"\xc1 garbage")
    put("quick/@v1/cam0/stats", encode_stats(Stats("flow", {"frames": 10**12}), "cam9", 1))  # another stream's
    put("quick/@v1/cam0/stats", encode_frame(FRAME, "cam0"))  # not a stats message
    assert board.errors == 3 and board.snapshot() == {("cam0", "flow"): {"frames": 7}}


def test_a_message_its_admit_refuses_takes_no_slot_and_each_one_dropped_for_room_is_told():
    """The flow service's gate (quick_stream/stream/gate.py) decides on a frame as it arrives, from
    the envelope the check read (None for a message that fails it), and names the frames the full
    queue drops."""
    box = Inbox(2, threading.Condition())
    asked, dropped = [], []
    box.admit = lambda key, data, env: asked.append(env) or env is None or env[1] % 2 == 0
    box.on_drop = lambda key, data: dropped.append(peek(data)[1])
    for seq in range(7):
        box._on_sample(sample(seq))
    box._on_sample(sample(0, data=b"not msgpack"))
    assert [e[:2] for e in asked[:7]] == [("frame", s) for s in range(7)] and asked[7] is None
    assert dropped == [0, 2, 4] and box.dropped == 3  # the odd ones never took a slot
    assert [peek(box.pop()[1]) for _ in range(2)] == [("frame", 6), None]

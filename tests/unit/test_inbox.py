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


def test_a_message_that_fails_the_check_is_never_queued_skipped_or_accounted():
    """A malformed frame with a far-future seq: refused on arrival (logged there), and neither the
    queue, the skips nor the arrival ledger (the restart cursor) read its seq."""
    box = Inbox(5, threading.Condition())
    box.skip_through = 10
    box._on_sample(sample(11))
    box._on_sample(sample(0, data=pack({}, "frame", "cam0", 10**12)))
    box._on_sample(sample(3))  # owed? no: <= skip_through, skipped
    box._on_sample(sample(12))
    assert len(box) == 2 and box.skipped == 1 and box.arrivals.invalid == 1
    assert box.arrivals.newest() == {("cam0", "frame"): 12} and box.arrivals.unreceived() == {}


def test_the_status_board_counts_bad_stats_messages_and_keeps_only_good_ones():
    from quick_stream.stream.launcher import StatusBoard
    from quick_stream.stream.wire import Stats, encode_stats

    ring: list = []  # what zenoh's ring channel holds until the board drains it
    board = StatusBoard(SimpleNamespace(declare_subscriber=lambda key, handler: SimpleNamespace(
        try_recv=lambda: ring.pop(0) if ring else None)))

    def put(key: str, data: bytes) -> None:
        ring.append(SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: data)))

    put("quick/@v1/cam0/stats", encode_stats(Stats("flow", {"frames": 7}), "cam0", 0))
    put("quick/@v1/cam0/stats", b"\xc1 garbage")
    put("quick/@v1/cam0/stats", encode_stats(Stats("flow", {"frames": 10**12}), "cam9", 1))  # another stream's
    put("quick/@v1/cam0/stats", encode_frame(FRAME, "cam0"))  # not a stats message
    assert board.errors == 3 and board.snapshot() == {("cam0", "flow"): {"frames": 7}}


def _from(who: str | None, seq: int, mtype: str = "frame", data: bytes | None = None):
    """A sample as zenoh delivers it from publisher session ``who`` (source info and timestamp)."""
    s = sample(seq, mtype, data)
    if who is not None:
        s.source_info = SimpleNamespace(source_id=SimpleNamespace(zid=who, eid=3), source_sn=seq)
        s.timestamp = SimpleNamespace(get_id=lambda: who)
    return s


def test_bad_messages_never_take_a_real_frames_slot():
    """Issue 30 row 6: undecodable and damaged messages took slots in flow's drop-oldest queue before
    being checked, pushing real frames out (151 dropped in the fuzz run). Now they are refused on arrival:
    garbage, a frame whose depth stream is damaged behind an intact header, one of a wrong version."""
    import msgpack

    box = Inbox(3, threading.Condition())
    for seq in (0, 1, 2):
        box._on_sample(sample(seq))
    good = encode_frame(FRAME.with_(seq=3), "cam0", depth="zstd")
    d = msgpack.unpackb(good, raw=False)
    d["depth"]["data"] = d["depth"]["data"][:-10]  # the zstd frame cut short, its header (content size) intact
    damaged = msgpack.packb(d, use_bin_type=True)
    for data in (b"\x00garbage", damaged, msgpack.packb({**d, "v": 9}, use_bin_type=True), good[:-20]) * 5:
        box._on_sample(sample(3, data=data))
    assert box.dropped == 0 and box.arrivals.invalid == 20
    assert [peek(box.pop()[1])[1] for _ in range(3)] == [0, 1, 2]


def test_an_end_is_honoured_only_from_the_streams_own_publisher():
    """Issue 30 row 6: a forged `end` on the frame key ended flow's, motion's and render's stream. An end
    is taken only from the publisher whose message last moved the stream's newest seq, and not when it
    ends behind that seq; any other is counted and never queued (the ledger, the cursor, stay open)."""
    box = Inbox(50, threading.Condition())
    for seq in range(5):
        box._on_sample(_from("capture", seq))
    box._on_sample(_from("fuzzer", 1))  # a foreign frame behind the newest: moves nothing, owns nothing
    for forged in (_from("fuzzer", 4, "end"), _from(None, 9, "end"), _from("capture", 2, "end")):
        box._on_sample(forged)
    copied = _from("capture", 9, "end")  # a source info copied from the capture's samples, stamped by another
    copied.timestamp = SimpleNamespace(get_id=lambda: "fuzzer")
    box._on_sample(copied)
    assert box.arrivals.ignored_ends == 4 and len(box) == 6
    assert box.arrivals.newest() == {("cam0", "frame"): 4}  # the stream is still under way
    box._on_sample(_from("capture", 4, "end"))  # the capture's own end, after its last frame
    assert len(box) == 7 and peek(box._q[-1][1]) == ("end", 4) and box.arrivals.newest() == {}
    box._on_sample(_from("fuzzer", 7, "end"))  # nothing under way: nothing to cut, taken (harmless)
    assert len(box) == 8 and box.arrivals.ignored_ends == 4


def test_a_full_queue_sheds_a_foreign_publishers_messages_before_the_streams():
    """Issue 30 row 6: valid messages from another publisher (fuzzed frames that still decode) filled flow's
    queue and pushed the capture's frames out. A full queue drops a message not from the stream's own
    publisher first (the oldest of them, or the one arriving), the stream's only when none is queued."""
    box = Inbox(4, threading.Condition())
    for seq in range(3):
        box._on_sample(_from("capture", seq))
    for _ in range(10):
        box._on_sample(_from("fuzzer", 1))  # valid, stale: the consumer refuses them, and they cost no slot
    box._on_sample(_from("capture", 3))
    box._on_sample(_from("fuzzer", 2))
    assert box.dropped == box.dropped_foreign == 11
    assert [peek(box.pop()[1])[1] for _ in range(4)] == [0, 1, 2, 3]
    for seq in range(4, 10):  # the stream's own, too many: the oldest go
        box._on_sample(_from("capture", seq))
    assert box.dropped == 13 and box.dropped_foreign == 11 and [peek(it[1])[1] for it in box._q] == [6, 7, 8, 9]
def test_a_message_its_admit_refuses_takes_no_slot_and_each_one_dropped_for_room_is_told():
    """The flow service's gate (quick_stream/stream/gate.py) decides on a frame as it arrives, from
    the envelope the check read (a message that fails the check is refused before it is asked), and
    names the frames the full queue drops."""
    box = Inbox(2, threading.Condition())
    asked, dropped = [], []
    box.admit = lambda key, data, env: asked.append(env) or env is None or env[1] % 2 == 0
    box.on_drop = lambda key, data: dropped.append(peek(data)[1])
    for seq in range(7):
        box._on_sample(sample(seq))
    box._on_sample(sample(0, data=b"not msgpack"))  # refused on arrival: never asked, never queued
    assert [e[:2] for e in asked] == [("frame", s) for s in range(7)]
    assert dropped == [0, 2] and box.dropped == 2  # the odd ones never took a slot
    assert [peek(box.pop()[1]) for _ in range(2)] == [("frame", 4), ("frame", 6)]

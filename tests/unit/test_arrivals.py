"""The recorder's account of seqs that never arrived (quick_stream/stream/arrivals.py)."""
from __future__ import annotations

import numpy as np
import pytest

from quick_stream.stream.arrivals import ArrivalLedger
from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.stream.wire import EndOfStream, StabilizedImage, Stats, encode_end, encode_frame, encode_stabilized, encode_stats
from quick_stream.stream.wire.codec import pack

KEY = "quick/@v1/cam0/stabilized"
_FRAME = next(iter(SyntheticSource(width=64, height=48, frames=1)))
_IMAGE = np.zeros((48, 64, 3), np.uint8)


def msg(seq: int, type: str = "stabilized", stream: str = "cam0") -> bytes:
    """A valid message of ``type`` (the ledger accounts only those)."""
    if type == "stabilized":
        return encode_stabilized(StabilizedImage(seq, 0, _IMAGE, 1.0, []), stream)
    if type == "frame":
        return encode_frame(_FRAME.with_(seq=seq), stream)
    if type == "stats":
        return encode_stats(Stats("render", {}), stream, seq)
    if type == "end":
        return encode_end(EndOfStream(seq, "test"), stream)
    if type == "flow":  # an envelope is enough for the accounting itself
        return pack({}, "flow", stream, seq)
    raise ValueError(type)


def test_a_skipped_run_is_one_gap_counted_per_seq():
    led = ArrivalLedger()
    assert [led.add(KEY, msg(s)) for s in (5, 6, 7)] == [None, None, None]  # starts where it joins
    gap = led.add(KEY, msg(12))
    assert (gap.stream, gap.stage, gap.first, gap.last, gap.count) == ("cam0", "stabilized", 8, 11, 4)
    assert led.unreceived() == {"stabilized": 4}


def test_late_arrivals_fill_their_gap_and_repeats_are_duplicates():
    led = ArrivalLedger()
    for s in (0, 3, 1, 1, 3):
        led.add(KEY, msg(s))
    assert led.unreceived() == {"stabilized": 1}  # 2 never came
    assert (led.late, led.duplicates) == (1, 2)


def test_stages_and_streams_are_separate_and_stats_are_not_counted():
    led = ArrivalLedger()
    for s in (0, 2):
        led.add("quick/@v1/cam0/frame", msg(s, "frame"))
        led.add("quick/@v1/cam1/frame", msg(s * 2, "frame", stream="cam1"))
        led.add("quick/@v1/cam0/stats", msg(s * 5, "stats"))
    assert led.unreceived() == {"frame": 1 + 3}


def test_an_end_closes_the_stream_and_keeps_its_count():
    led = ArrivalLedger()
    for m in (msg(0), msg(2), msg(2, "end"), msg(0), msg(1)):
        led.add(KEY, m)
    assert led.unreceived() == {"stabilized": 1}
    assert led.duplicates == 0  # the new stream's 0 and 1 are new


def test_undecodable_envelopes_are_ignored_and_old_gaps_are_final():
    led = ArrivalLedger(window=10)
    assert led.add(KEY, b"\x00garbage") is None
    led.add(KEY, msg(0))
    led.add(KEY, msg(100))
    assert led.unreceived() == {"stabilized": 99}
    led.add(KEY, msg(95))  # within the window: fills
    led.add(KEY, msg(3))  # far behind: not remembered as missing any more
    assert led.unreceived() == {"stabilized": 98} and (led.late, led.duplicates) == (1, 1)


def test_an_end_past_the_stages_last_seq_is_not_a_loss():
    """A flow is numbered by its pair's first frame: flows 0..298 of frames 0..299 end with the
    frame stream's end marker, seq 299 (the soak's false "flow 18150 never arrived")."""
    led = ArrivalLedger()
    for s in range(299):
        led.account("quick/@v1/cam0/flow", "flow", s)
    assert led.add("quick/@v1/cam0/flow", msg(299, "end")) is None
    assert led.unreceived() == {}


@pytest.mark.parametrize("bad", [
    pack({}, "stabilized", "cam0", 10**12),  # a valid envelope, no image: the poison of a far-future seq
    msg(10**12, "stabilized", stream="cam9"),  # another stream's message on cam0's key
    msg(10**12, "frame"),  # a frame on the stabilized key
    msg(10**12).replace(b"\xa1v\x01", b"\xa1v\x02"),  # format version 2
])
def test_a_message_that_fails_the_check_moves_nothing(bad):
    led = ArrivalLedger()
    led.add(KEY, msg(7))
    assert led.add(KEY, bad) is None
    assert led.newest() == {("cam0", "stabilized"): 7} and led.invalid == 1 and led.last_error
    assert led.add(KEY, msg(8)) is None and led.unreceived() == {}  # the stream goes on, no gap


def test_a_far_future_seq_moves_nothing_until_a_run_confirms_a_new_numbering():
    led = ArrivalLedger()
    for s in (0, 1, 10**12, 2, 3):  # one valid message from the far future: not the stage's newest
        led.add(KEY, msg(s))
    assert led.newest() == {("cam0", "stabilized"): 3} and led.unreceived() == {} and led.jumps == 1
    for s in range(5000, 5005):  # a publisher that really renumbered: taken on the 5th in a row
        led.add(KEY, msg(s))
    assert led.newest() == {("cam0", "stabilized"): 5004} and led.jumps == 1 + 4


def test_a_seeded_account_reveals_the_hole_of_a_restart():
    led = ArrivalLedger()
    led.seed("cam0", "stabilized", 60)  # the predecessor recorded up to 60
    gap = led.add(KEY, msg(108))
    assert (gap.first, gap.last) == (61, 107) and led.unreceived() == {"stabilized": 47}
    late = ArrivalLedger()  # messages arrived before the seed: the hole is before the first of them
    late.add(KEY, msg(90))
    late.add(KEY, msg(91))
    gap = late.seed("cam0", "stabilized", 60)
    assert (gap.first, gap.last) == (61, 89) and late.unreceived() == {"stabilized": 29}

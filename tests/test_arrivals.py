"""The recorder's account of seqs that never arrived (quick_stream/arrivals.py)."""
from __future__ import annotations

from quick_stream.arrivals import ArrivalLedger
from quick_stream.wire.codec import pack

KEY = "quick/@v1/cam0/stabilized"


def msg(seq: int, type: str = "stabilized") -> bytes:
    return pack({}, type, "cam0", seq)


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
        led.add("quick/@v1/cam1/frame", msg(s * 2, "frame"))
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
        led.add("quick/@v1/cam0/flow", msg(s, "flow"))
    assert led.add("quick/@v1/cam0/flow", msg(299, "end")) is None
    assert led.unreceived() == {}

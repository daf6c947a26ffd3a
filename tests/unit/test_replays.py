"""Replays told from new messages by their bytes (quick_stream/stream/replays.py; issue 30, row 8):
a restarted publisher's replay is dropped on arrival, before the arrival ledger, so it is neither a
false renumbering nor a second copy; same seq with other bytes is kept; memory stays bounded."""
import threading
from types import SimpleNamespace

import numpy as np
import pytest

from quick_stream.core.motion import MotionEstimate
from quick_stream.stream.inbox import Inbox
from quick_stream.stream.replays import ReplayFilter
from quick_stream.stream.wire import EndOfStream, encode_end, encode_motion

KEY = "quick/@v1/cam0/motion"


def motion(seq: int, tx: float = 0.01) -> bytes:
    m = np.eye(4)
    m[:3, 3] = (tx * seq, 0.0, 0.02)
    return encode_motion(MotionEstimate(seq, seq + 1, "se3", "exact", m, np.zeros(6), True, "", 100, 1.0, 0.1,
                                        None), "cam0")


def sample(data: bytes, key: str = KEY):
    return SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: data))


def drain(box: Inbox) -> list[bytes]:
    out = []
    while (item := box.pop()) is not None:
        out.append(item[1])
    return out


def test_a_restarted_motion_services_replay_is_queued_once_and_is_no_renumbering():
    """Motions 0..96, then a restarted motion service sends 75..96 again (the same bytes) and goes on:
    without the filter the ledger took the 22 for a renumbering and every one was handed on twice."""
    plain, box = Inbox(1000, threading.Condition()), Inbox(1000, threading.Condition(), replays=ReplayFilter())
    arrived = []
    box.on_arrival = lambda k, d, t: arrived.append(d)
    sent = [motion(s) for s in range(97)] + [motion(s) for s in range(75, 97)] + [motion(s) for s in range(97, 110)]
    for d in sent:
        plain._on_sample(sample(d))
        box._on_sample(sample(d))
    assert plain.arrivals.renumberings == 1 and len(drain(plain)) == len(sent)  # what the recorder did
    assert drain(box) == arrived == [motion(s) for s in range(110)]
    assert box.replays.replays == 22 and box.replays.conflicts == 0
    assert (box.arrivals.renumberings, box.arrivals.duplicates, box.arrivals.unreceived()) == (0, 0, {})
    assert box.arrivals.newest()[("cam0", "motion")] == 109


def test_same_seq_other_bytes_is_a_conflict_kept_and_logged(caplog):
    f = ReplayFilter()
    assert not f.replayed(KEY, "motion", 5, motion(5))
    assert not f.replayed(KEY, "motion", 5, motion(5, tx=0.5))  # other bytes: both are real, kept
    assert f.replayed(KEY, "motion", 5, motion(5, tx=0.5)) and f.replayed(KEY, "motion", 5, motion(5))
    assert (f.replays, f.conflicts) == (2, 1)
    assert "cam0/motion: motion seq 5 arrived again with different bytes (1 such so far)" in caplog.text
    # another key, the same seq and bytes: not a replay (stages and streams are apart)
    assert not f.replayed("quick/@v1/cam1/motion", "motion", 5, motion(5))


def test_stats_pass_unchecked_and_an_end_starts_the_key_afresh():
    f = ReplayFilter()
    stats = b"\x80"
    assert not f.replayed(KEY, "stats", 0, stats) and not f.replayed(KEY, "stats", 0, stats)
    for s in range(10):
        f.replayed(KEY, "motion", s, motion(s))
    end = encode_end(EndOfStream(10, "done"), "cam0")
    assert not f.replayed(KEY, "end", 10, end)
    assert f.replayed(KEY, "end", 10, end)  # the same end again before anything else: a replay
    # a new stream on the key, numbered from 0 again with the same bytes (a deterministic source): new
    assert not any(f.replayed(KEY, "motion", s, motion(s)) for s in range(10))
    assert not f.replayed(KEY, "end", 10, end)  # and so is its end
    assert f.replays == 1


def test_memory_is_bounded_per_key_and_in_keys():
    f = ReplayFilter(window=8, keys=3, per_seq=2)
    for s in range(100):
        f.replayed(KEY, "motion", s, motion(s))
    assert len(f._seen[KEY]) == 8
    assert f.replayed(KEY, "motion", 99, motion(99)) and not f.replayed(KEY, "motion", 50, motion(50))  # forgotten
    for tx in (0.1, 0.2, 0.3, 0.4):
        f.replayed(KEY, "motion", 99, motion(99, tx))
    assert len(f._seen[KEY][99]) == 2
    for i in range(10):
        f.replayed(f"quick/@v1/s{i}/motion", "motion", 0, motion(0))
    assert len(f._seen) == 3


def test_bad_bounds_are_refused():
    with pytest.raises(ValueError, match="window"):
        ReplayFilter(window=0)

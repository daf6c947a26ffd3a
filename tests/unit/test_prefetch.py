"""Prefetch: a source read ahead in a worker thread, in order, bounded, errors where they happened."""
from __future__ import annotations

import threading

import pytest

from quick_stream.io.sources.prefetch import Prefetch


def test_items_come_in_order_and_all_of_them():
    assert list(Prefetch(range(1000), depth=3)) == list(range(1000))
    assert list(Prefetch([], depth=1)) == []


def test_the_worker_reads_at_most_depth_items_ahead():
    read = []
    six = threading.Event()

    def items():
        for i in range(100):
            read.append(i)
            if len(read) == 6:
                six.set()
            yield i

    p = Prefetch(items(), depth=4)
    it = iter(p)
    assert next(it) == 0
    # the worker fills the queue (4) and reads one more it cannot put yet
    assert six.wait(60)
    assert p._q.qsize() <= 4
    assert list(it) == list(range(1, 100))  # and nothing was lost to the bound


def test_an_error_of_the_source_comes_after_the_items_before_it():
    def items():
        yield 1
        yield 2
        raise OSError("disk went away at frame 3")

    got = []
    with pytest.raises(OSError, match="frame 3"):
        for x in Prefetch(items(), depth=2):
            got.append(x)
    assert got == [1, 2]


def test_leaving_early_stops_the_worker():
    p = Prefetch(iter(range(10**9)), depth=2)
    for x in p:
        if x == 5:
            break
    p.close()
    assert not p._thread.is_alive()


def test_depth_below_one_is_refused():
    with pytest.raises(ValueError, match="depth must be >= 1"):
        Prefetch([1], depth=0)
